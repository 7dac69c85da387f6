"""``caps-plus`` (issue 36, item 2): the polarization-split data term, the demosaicked start and the method as
caps's pipeline with its slots changed. Its choices (count, filter): tests/reconstruction/test_caps_plus_model.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import CapssimError, InputError
from capssim.eval.metrics import score
from capssim.reconstruct import reconstruct
from capssim.reconstruct.model.data_term import confidence_mix
from capssim.reconstruct.model.polarization_split import angle_mean, split_confidence_mix
from capssim.simulate import simulate_capture

SIZE = 48


def split_matrix(conf, n_angles=4):
    """The per-pixel matrix T of D = T b, built column by column from unit vectors."""
    c = conf.shape[0]
    cols = []
    for j in range(c):
        e = torch.zeros(c, *conf.shape[2:], dtype=conf.dtype)
        e[j] = 1
        cols.append(split_confidence_mix(conf, e, n_angles))
    return torch.stack(cols, dim=1).permute(2, 3, 0, 1)  # (H, W, C, C): T[:, :, i, j] = D_i of e_j


def test_angle_mean_is_the_mean_over_analyzers_of_each_colour():
    b = torch.arange(12 * 2 * 3, dtype=torch.float64).reshape(12, 2, 3)
    m = angle_mean(b)
    expected = b.reshape(4, 3, 2, 3).mean(0)
    for p in range(4):
        assert torch.equal(m[3 * p:3 * p + 3], expected)
    assert torch.allclose(angle_mean(m), m)  # a projection


@pytest.mark.parametrize("channels", [12, 4])
def test_split_direction_is_symmetric_positive_semidefinite(channels, random_confidence):
    """T = P L P + (I-P) L_angle (I-P) is symmetric PSD: a descent direction with the same fixed points."""
    conf = random_confidence(channels, 3, 4, seed=channels)
    t = split_matrix(conf)
    assert torch.allclose(t, t.transpose(-1, -2), atol=1e-12)
    assert torch.linalg.eigvalsh(t).min() > -1e-10
    b = torch.randn(channels, 3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    assert float((b * split_confidence_mix(conf, b)).sum()) >= 0


def test_split_direction_on_angle_means_is_the_projected_cagf_direction(random_confidence):
    conf = random_confidence(12, 5, 5, seed=3)
    b = angle_mean(torch.randn(12, 5, 5, dtype=torch.float64))
    assert torch.allclose(split_confidence_mix(conf, b), angle_mean(confidence_mix(conf, b)), atol=1e-12)


def test_polarization_part_is_shared_only_within_one_analyzer():
    """A residual of analyzer 0 alone with zero angle mean moves only analyzer 0's colours (and the
    angle-mean correction), never pushes the other analyzers the same way."""
    conf = torch.ones(12, 12, 2, 2, dtype=torch.float64)  # every pair fully confident
    b = torch.zeros(12, 2, 2, dtype=torch.float64)
    b[0], b[6] = 1.0, -1.0  # I_0 must rise and I_90 fall, red: S0 unchanged
    d = split_confidence_mix(conf, b)
    assert torch.allclose(angle_mean(d), torch.zeros_like(d), atol=1e-12)  # no intensity change
    assert (d[0:3] > 0).all() and (d[6:9] < 0).all()  # the colours of analyzer 0 rise, of 90 fall
    assert torch.allclose(d[3:6], torch.zeros_like(d[3:6])) and torch.allclose(d[9:12], torch.zeros_like(d[9:12]))
    cagf = confidence_mix(conf, b)  # eq. 26 with full confidence: opposite residuals cancel everywhere
    assert torch.allclose(cagf, torch.zeros_like(cagf))


def test_split_direction_checks_the_channel_count():
    conf = torch.ones(6, 6, 2, 2)
    with pytest.raises(CapssimError, match="channels"):
        split_confidence_mix(conf, torch.zeros(6, 2, 2))


@pytest.fixture(scope="module")
def capture(smooth_random_scene):
    return simulate_capture(smooth_random_scene(SIZE, seed=7), make_sensor("gaussian", sigma=0.01), seed=7)


def test_caps_plus_runs_and_records_its_ingredients(capture):
    out, record = reconstruct(capture, "caps-plus", true_warps=True, iterations=6)
    assert out.image.shape == (12, SIZE, SIZE) and out.image.dtype == np.float32 and np.isfinite(out.image).all()
    params = record["params"]
    assert params["data_term"] == "cagf-stokes" and params["init"] == "agree"
    assert params["mu0"] == 0.25 and params["c2"] == 0.01 and params["iterations"] == 6 and len(out.history) == 6
    assert params["holdout_fraction"] == 0.05 and params["selection"]["iterations_from"] == "options"
    assert "init_demosaic" in record["stages_s"]
    assert score(out.image, capture.gt, with_ssim=False)["psnr_mean"] > 25


def test_caps_plus_is_caps_with_its_slots_changed(capture):
    """With caps's data term, start, schedule and no polarization filter, caps-plus is caps, bit for bit."""
    same = {"iterations": 4, "mu0": 0.5, "c2": 0.02}
    plus, _ = reconstruct(capture, "caps-plus", true_warps=True, data_term="cagf", init="fusion",
                          polarization_filter="none", **same)
    caps, _ = reconstruct(capture, "caps", true_warps=True, **same)
    assert np.array_equal(plus.image, caps.image)


def test_the_naive_initialization_is_caps_naives_image(capture):
    """-p prior=none with 0 iterations of steepest descent leaves the initialization: caps-naive's image
    (inside a 4 px border, where the two methods' unobserved pixels are filled differently)."""
    plus, record = reconstruct(capture, "caps-plus", true_warps=True, prior="none", iterations=0, init="naive",
                               polarization_filter="none")
    naive, _ = reconstruct(capture, "caps-naive", true_warps=True)
    inner = (slice(None), slice(4, -4), slice(4, -4))
    assert np.allclose(plus.image[inner], naive.image[inner], atol=1e-5)
    assert not np.allclose(plus.image[inner], reconstruct(capture, "caps", true_warps=True, prior="none",
                                                          iterations=0)[0].image[inner], atol=1e-3)


def test_caps_naive_still_offers_the_moved_demosaicking_helpers():
    """demosaicked_frames and bicubic_warp moved to capssim.reconstruct.model.aperture_demosaic; caps_naive
    re-exports them (the same functions)."""
    from capssim.reconstruct.methods import caps_naive
    from capssim.reconstruct.model import aperture_demosaic

    assert caps_naive.demosaicked_frames is aperture_demosaic.demosaicked_frames
    assert caps_naive.bicubic_warp is aperture_demosaic.bicubic_warp


@pytest.mark.parametrize("init", ["zeros", "split"])
def test_caps_plus_refuses_an_unknown_initialization_listing_the_starts(capture, init):
    """``split`` (the fusion's analyzer mean, the apertures' polarization part) is no start of caps-plus any more."""
    with pytest.raises(InputError, match="option init") as refused:
        reconstruct(capture, "caps-plus", true_warps=True, iterations=1, init=init)
    assert all(name in str(refused.value) for name in ("agree", "agree-all", "fusion", "naive"))
