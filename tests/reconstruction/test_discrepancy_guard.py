"""The discrepancy guard of dofp-nafnet: the truth passes untouched, an estimate that contradicts the samples is
moved towards the fallback, the method's option and record, and hard inputs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import InputError, UnknownNameError
from capssim.reconstruct.methods.dofp_nafnet import TRAINED_NOISE_STD_MIN, demosaic_dofp_nafnet
from capssim.reconstruct.networks.cpdnet import sparse_channels
from capssim.reconstruct.networks.discrepancy_guard import THRESHOLD, WINDOW_SIGMA, discrepancy_guard
from capssim.reconstruct.registry import reconstruct
from capssim.simulate import simulate_capture

SIGMA = 0.01


def _sampled(image: torch.Tensor, layout="sony") -> torch.Tensor:
    """The DoFP mosaic of a ``(12, H, W)`` image: each pixel keeps the channel it samples."""
    return (image * sparse_channels(torch.ones(1, *image.shape[1:]), layout)[0]).sum(0)


@pytest.fixture
def scene(smooth_random_scene):
    gt = torch.from_numpy(smooth_random_scene(64, seed=11).astype(np.float64))
    noise = SIGMA * torch.from_numpy(np.random.default_rng(3).standard_normal((64, 64)))
    return gt, _sampled(gt) + noise


def test_the_truth_passes_and_a_contradicting_estimate_moves_to_the_fallback(scene):
    gt, mosaic = scene
    fallback = gt + 0.002  # any other estimate
    kept, share = discrepancy_guard(gt, fallback, mosaic, torch.full_like(mosaic, SIGMA), "sony", noise_floor=0.002)
    assert float(share.max()) == 0.0 and torch.equal(kept, gt)  # the truth's local residual energy is about 1
    # an estimate off by 5 sigma in one corner contradicts the samples there (e = 1 + 25: b = 1 - 1.5 / 26)
    wrong = gt.clone()
    wrong[:, :24, :24] += 5 * SIGMA
    guarded, share = discrepancy_guard(wrong, gt, mosaic, torch.full_like(mosaic, SIGMA), "sony", noise_floor=0.002)
    assert float(share[4:20, 4:20].min()) > 0.9 and float(share[40:, 40:].max()) == 0.0
    assert float((guarded - gt).abs()[:, 4:20, 4:20].max()) < 0.1 * 5 * SIGMA
    assert torch.equal(guarded[:, 40:, 40:], wrong[:, 40:, 40:])
    # the share is 1 - THRESHOLD / e of the residual's local mean square e
    uniform = gt + 3 * SIGMA  # every sample off by 3 sigma (plus its noise): e = 1 + 9
    _, share = discrepancy_guard(uniform, gt, mosaic, torch.full_like(mosaic, SIGMA), "sony", noise_floor=0.002)
    assert float(share[16:48, 16:48].mean()) == pytest.approx(1 - THRESHOLD / 10, abs=0.05)
    assert WINDOW_SIGMA > 0


def test_a_noise_free_mosaic_is_judged_against_the_floor(scene):
    gt, _ = scene
    exact = _sampled(gt)
    off = gt + 0.5 * TRAINED_NOISE_STD_MIN  # within the floor: kept
    _, share = discrepancy_guard(off, gt, exact, torch.zeros_like(exact), "sony", noise_floor=TRAINED_NOISE_STD_MIN)
    assert float(share.max()) == 0.0
    off = gt + 3 * TRAINED_NOISE_STD_MIN
    _, share = discrepancy_guard(off, gt, exact, torch.zeros_like(exact), "sony", noise_floor=TRAINED_NOISE_STD_MIN)
    assert float(share.min()) > 0.5


@pytest.mark.parametrize("fill", [0.0, 1e-6, 1.0])
def test_hard_mosaics_stay_finite(fill):
    for shape in ((4, 4), (12, 20), (26, 38)):
        mosaic = torch.full(shape, fill, dtype=torch.float64)
        estimate = torch.rand(12, *shape, dtype=torch.float64)
        out, share = discrepancy_guard(estimate, torch.full((12, *shape), fill, dtype=torch.float64), mosaic, 0.0,
                                       "0-45-135-90", noise_floor=0.002)
        assert torch.isfinite(out).all() and torch.isfinite(share).all()
        assert float(share.min()) >= 0 and float(share.max()) <= 1


def test_the_method_option_record_and_warning(smooth_random_scene, caplog):
    capture = simulate_capture(smooth_random_scene(48, seed=5), make_sensor("gaussian", sigma=SIGMA), seed=2)
    plain, plain_record = reconstruct(capture, "dofp-nafnet")
    guarded, record = reconstruct(capture, "dofp-nafnet", guard="true")
    assert plain_record["params"]["guard"] is False and record["params"]["guard"] is True
    share = record["params"]["discrepancy_share"]
    assert 0.0 <= share <= 1.0 and plain_record["params"]["discrepancy_share"] == share
    assert record["params"]["guard_noise_floor"] == TRAINED_NOISE_STD_MIN
    if share == 0.0:
        np.testing.assert_array_equal(guarded.image, plain.image)
    # a mosaic the network cannot explain: each 4x4 cell's samples shuffled between cells (no scene looks like it)
    mosaic = capture.dofp_float().copy()
    cells = mosaic.reshape(12, 4, 12, 4).transpose(0, 2, 1, 3).reshape(144, 16)
    shuffled = cells[:, np.random.default_rng(0).permutation(16)].reshape(12, 12, 4, 4).transpose(0, 2, 1, 3)
    caplog.set_level("WARNING")
    out = demosaic_dofp_nafnet(shuffled.reshape(48, 48), noise_std=SIGMA)
    assert np.isfinite(out).all()
    assert any("guard=true" in r.getMessage() for r in caplog.records), [r.getMessage() for r in caplog.records]
    with pytest.raises(InputError, match="option guard") as info:
        reconstruct(capture, "dofp-nafnet", guard="maybe")
    assert "guard=true" in str(info.value)
    with pytest.raises(UnknownNameError, match="guard, weights"):  # the unknown-option error lists it
        reconstruct(capture, "dofp-nafnet", gaurd="false")


def test_the_options_listing_names_both_options_and_the_method_takes_them(smooth_random_scene):
    from capssim.reconstruct.methods.dofp_nafnet import dofp_nafnet_options
    from capssim.reconstruct.networks import WEIGHTS_DIR

    listed = {option.name: option for option in dofp_nafnet_options()}
    assert set(listed) == {"weights", "guard"} and listed["guard"].default is False
    capture = simulate_capture(smooth_random_scene(24, seed=6), make_sensor("gaussian", sigma=SIGMA), seed=1)
    _, record = reconstruct(capture, "dofp-nafnet", weights=str(WEIGHTS_DIR / "dofp-nafnet.pt"), guard=True)
    assert record["params"]["guard"] is True
