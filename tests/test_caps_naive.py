"""The naive camera-array baseline ``caps-naive`` (demosaic, register, bicubic x2)."""

import numpy as np
import pytest
import torch

from capssim.errors import UnknownNameError
from capssim.sensor import make_sensor
from capssim.simulate import PoseRanges, simulate_capture
from reconstruct.methods.caps_naive import resample_bicubic
from reconstruct.registry import reconstruct
from conftest import smooth_random_scene


def simulated(gt, sigma=0.0, seed=0, **pose):
    sensor = make_sensor("gaussian", sigma=sigma) if sigma else make_sensor("none")
    return simulate_capture(gt, sensor, seed=seed, pose_ranges=PoseRanges(**pose))


def psnr(x, gt, border=6):
    sl = (slice(None), slice(border, -border), slice(border, -border))
    return float(-10 * np.log10(np.mean((np.clip(x[sl], 0, 1) - gt[sl]) ** 2) + 1e-20))


def test_constant_scene_is_exact():
    gt = np.full((12, 40, 40), 0.37, np.float32)
    out, record = reconstruct(simulated(gt), "caps-naive", true_warps=True)
    assert out.image.shape == (12, 40, 40) and out.image.dtype == np.float32
    np.testing.assert_allclose(out.image, 0.37, atol=1e-5)
    assert {"demosaic", "registration", "resample"} <= set(record["stages_s"])
    assert record["wall_time_s"] > 0


def test_resampling_with_identity_is_the_x2_bicubic_on_the_raw_grid():
    # raw pixel j has its centre at HR coordinate 2j + 0.5: identity aperture -> R = raw_matrix()
    from capssim.homography import raw_matrix

    rng = np.random.default_rng(0)
    frames = torch.as_tensor(rng.random((1, 1, 10, 12)), dtype=torch.float64)
    hr = resample_bicubic(frames, raw_matrix()[None], (20, 24))[0, 0]
    # HR pixel 2j+0.5 is not on the grid; HR pixels 1, 3, ... lie at raw j + 0.25: check a linear ramp
    ramp = torch.arange(12, dtype=torch.float64).expand(10, 12)[None, None].clone()
    hr_ramp = resample_bicubic(ramp, raw_matrix()[None], (20, 24))[0, 0]
    x = np.arange(24) * 0.5 - 0.25
    inner = slice(4, -4)
    # Keys a = -0.75 moves a ramp by at most ~0.05 px with the phase; a misplaced grid moves it by 0.25+
    np.testing.assert_allclose(hr_ramp[5, inner].numpy(), x[inner], atol=0.06)
    assert torch.isfinite(hr).all()


def test_smooth_scene_is_recovered_with_true_and_estimated_warps():
    gt = smooth_random_scene(64, seed=3)
    cap = simulated(gt, sigma=0.0, seed=1)
    true_out, true_rec = reconstruct(cap, "caps-naive", true_warps=True)
    assert psnr(true_out.image, gt) > 33
    est_out, est_rec = reconstruct(cap, "caps-naive", true_warps=False)
    assert est_rec["registration"]["source"].startswith("estimated")
    assert psnr(est_out.image, gt) > 28


def test_the_true_warps_matter():
    # with the apertures' offsets ignored (identity warps) the result is measurably worse
    from capssim.homography import lr_homographies

    gt = smooth_random_scene(64, seed=5, dolp_max=0.2)
    cap = simulated(gt, seed=2, shift_max_px=4.0)
    good, _ = reconstruct(cap, "caps-naive", true_warps=True)
    identity = lr_homographies(np.tile(np.eye(3), (4, 1, 1)))
    for m, entry in enumerate(cap.meta["lr_images"]):
        entry["homography"] = identity[m].tolist()
    bad, _ = reconstruct(cap, "caps-naive", true_warps=True)
    assert psnr(good.image, gt) > psnr(bad.image, gt) + 1.5


@pytest.mark.parametrize("method", ["menon2007", "malvar2004", "bilinear"])
def test_bayer_methods_selectable(method):
    gt = smooth_random_scene(32, seed=1)
    out, record = reconstruct(simulated(gt), "caps-naive", true_warps=True, bayer_method=method)
    assert record["params"]["bayer_method"] == method
    assert psnr(out.image, gt, border=4) > 25


def test_unknown_bayer_method_and_option_are_clear_errors():
    cap = simulated(smooth_random_scene(32))
    with pytest.raises(UnknownNameError, match="menon2007"):
        reconstruct(cap, "caps-naive", true_warps=True, bayer_method="nearest")
    with pytest.raises(UnknownNameError, match="bayer_method"):
        reconstruct(cap, "caps-naive", true_warps=True, sharpen=1)


@pytest.mark.parametrize("shape", [(12, 36, 44), (12, 20, 28)])
def test_odd_sizes_and_dark_input_give_finite_output(shape):
    gt = np.full(shape, 1e-4, np.float32)
    gt[:, ::3] = 0.0
    out, _ = reconstruct(simulated(gt, sigma=0.01), "caps-naive", true_warps=True)
    assert out.image.shape == shape and np.isfinite(out.image).all()
    assert out.image.min() >= 0 and out.image.max() <= 1
