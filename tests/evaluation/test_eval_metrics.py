"""eval.metrics: definitions pinned against hand-computed values, and the hard inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from capssim.errors import InputError, UnknownNameError
from capssim.eval.metric_records import flatten, metric_direction
from capssim.eval.metrics import PSNR_CAP_DB, crop_border, score
from capssim.stokes.polarization import twelve_from_stokes


def _stokes_scene(s0, dolp, aop_deg, size=32):
    """12-ch image of a uniform polarization state (same for R, G, B)."""
    a = np.deg2rad(aop_deg)
    s0 = np.full((3, size, size), s0, dtype=np.float64) if np.isscalar(s0) else s0
    d = np.broadcast_to(dolp, s0.shape)
    ang = np.broadcast_to(a, s0.shape)
    stokes = np.stack([s0, s0 * d * np.cos(2 * ang), s0 * d * np.sin(2 * ang)])
    return twelve_from_stokes(stokes)


def test_constant_offset_gives_exact_psnrs(smooth_random_scene):
    gt = smooth_random_scene(48, seed=1).astype(np.float64)
    delta = 0.01
    r = score(gt + delta, gt)
    expected = -20 * math.log10(delta)
    assert r["psnr_mean"] == pytest.approx(expected, abs=1e-6)
    assert all(v == pytest.approx(expected, abs=1e-6) for v in r["cpsnr"].values())
    # S0 = sum/2 moves by 2*delta on a range of 2: the same PSNR; S1 and S2 do not move
    assert r["s0_psnr"] == pytest.approx(expected, abs=1e-6)
    assert r["s1_psnr"] == PSNR_CAP_DB and r["s2_psnr"] == PSNR_CAP_DB


def test_stokes_scalings_agree_between_conventions(smooth_random_scene):
    gt = smooth_random_scene(64, seed=2).astype(np.float64)
    est = gt + np.random.default_rng(0).normal(0, 0.02, gt.shape)
    a = score(est, gt, convention="capssim", border=0, with_ssim=False)
    b = score(est, gt, convention="qiu", with_ssim=False)
    for key in ("s0_psnr", "s1_psnr", "s2_psnr", "psnr_mean"):
        assert a[key] == pytest.approx(b[key], abs=1e-9)
    # the masks differ (capssim masks dark / weakly polarized GT pixels), the AoP values may not
    assert b["aop_fraction"] == 1.0


def test_tokyotech_crop_matches_matlab_indexing():
    gt = np.full((12, 64, 64), 0.5)
    # MATLAB X(15:end-15) keeps 0-based rows 14..48
    for row, counted in ((13, False), (14, True), (48, True), (49, False)):
        est = gt.copy()
        est[:, row, 30] += 0.1
        r = score(est, gt, convention="tokyotech", with_ssim=False)
        assert (r["psnr_mean"] < PSNR_CAP_DB) == counted, row
    assert crop_border(gt, 15, matlab=True).shape == (12, 35, 35)
    assert crop_border(gt, 8).shape == (12, 48, 48)


def test_aop_error_is_wrap_aware():
    gt = _stokes_scene(1.0, 0.5, 179.0)
    est = _stokes_scene(1.0, 0.5, 1.0)
    r = score(est, gt, border=0)
    assert r["aop_rmse_deg"] == pytest.approx(2.0, abs=1e-6)
    assert r["aop_mae_deg"] == pytest.approx(2.0, abs=1e-6)
    assert r["aop_psnr"] == pytest.approx(20 * math.log10(90.0), abs=1e-6)


def test_aop_mask_comes_from_ground_truth_only():
    size = 32
    dolp_map = np.where(np.arange(size)[None, :] < size // 2, 0.5, 0.01) * np.ones((size, size))
    gt = _stokes_scene(1.0, dolp_map[None], 30.0, size)
    est = _stokes_scene(1.0, 0.5, 40.0, size)  # 10 deg off everywhere
    r = score(est, gt, border=0)
    assert r["aop_fraction"] == pytest.approx(0.5)
    assert r["aop_rmse_deg"] == pytest.approx(10.0, abs=1e-6)
    # an estimate that darkens itself does not shrink the mask
    r_dark = score(est * 0.0, gt, border=0)
    assert r_dark["aop_fraction"] == pytest.approx(0.5)
    # tokyotech scores all pixels
    assert score(est, gt, convention="qiu")["aop_fraction"] == 1.0


def test_all_dark_images_are_well_defined(smooth_random_scene):
    z = np.zeros((12, 32, 32))
    r = score(z, z)
    assert r["psnr_mean"] == PSNR_CAP_DB and r["ssim_mean"] == pytest.approx(1.0)
    assert r["dolp_psnr"] == PSNR_CAP_DB
    assert r["aop_rmse_deg"] is None and r["aop_mae_deg"] is None and r["aop_psnr"] is None
    assert r["notes"] and "AoP undefined" in r["notes"][0]
    # a dark estimate of a bright scene: finite PSNR, no NaN anywhere
    gt = smooth_random_scene(32)
    flat = flatten(score(np.zeros_like(gt), gt))
    assert all(v is None or math.isfinite(v) for v in flat.values())


def test_zero_dolp_everywhere_gives_undefined_aop():
    gt = _stokes_scene(1.0, 0.0, 0.0)  # unpolarized: AoP undefined
    est = _stokes_scene(1.0, 0.03, 70.0)
    for conv in ("capssim", "tokyotech", "qiu"):
        r = score(est, gt, convention=conv, border=0)
        assert r["aop_rmse_deg"] is None, conv
        assert "DoLP = 0" in r["notes"][0]
        assert r["dolp_psnr"] == pytest.approx(-20 * math.log10(0.03), abs=1e-6)


def test_constant_images_give_finite_ssim():
    gt = np.full((12, 32, 32), 0.5)
    r_same = score(gt.copy(), gt)
    assert r_same["ssim_mean"] == pytest.approx(1.0)
    r = score(np.full_like(gt, 0.6), gt)
    assert r["psnr_mean"] == pytest.approx(20.0, abs=1e-9)
    assert 0.0 < r["ssim_mean"] < 1.0
    assert math.isfinite(r["dolp_ssim"])


def test_nan_in_estimate_is_a_clear_error(smooth_random_scene):
    gt = smooth_random_scene(32)
    est = gt.copy()
    est[4, 3, 3] = np.nan
    with pytest.raises(InputError, match=r"estimate.*1 NaN/inf values \(channels 45-G\)"):
        score(est, gt)
    with pytest.raises(InputError, match="gt"):
        score(gt, est)


def test_bad_shapes_dtypes_and_sizes(smooth_random_scene):
    gt = smooth_random_scene(32)
    with pytest.raises(InputError, match="ground-truth shape"):
        score(gt[:, :30], gt)
    with pytest.raises(InputError, match=r"\(12, H, W\)"):
        score(gt[:4], gt[:4])
    with pytest.raises(InputError, match="dtype"):
        score((gt * 255).astype(np.uint8), gt)
    with pytest.raises(InputError, match="border crop"):
        score(gt[:, :20, :20], gt[:, :20, :20])
    assert score(gt[:, :20, :20], gt[:, :20, :20], border=0)["psnr_mean"] == PSNR_CAP_DB
    with pytest.raises(UnknownNameError):
        score(gt, gt, convention="nope")


def test_torch_tensors_and_directions(smooth_random_scene):
    gt = smooth_random_scene(32)
    r = score(torch.from_numpy(gt) + 0.01, torch.from_numpy(gt))
    assert r["psnr_mean"] == pytest.approx(40.0, abs=1e-3)
    assert metric_direction("psnr.0-R") == 1 and metric_direction("aop_rmse_deg") == -1
    assert metric_direction("dolp_psnr_per_colour.G") == 1 and metric_direction("aop_fraction") == 0
    assert metric_direction("lpips.45") == -1
