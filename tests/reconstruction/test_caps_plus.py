"""``caps-plus`` (issue 36, item 2): the polarization-split data term, the demosaicked initialization and
the method as a configuration of the CAPS pipeline."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import CapssimError
from capssim.eval.metrics import score
from capssim.reconstruct import reconstruct
from capssim.reconstruct.methods.caps_plus import frame_iterations, noise_adaptive_iterations, raw_noise_sigma
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
    assert params["mu0"] == 0.25 and params["c2"] == 0.01 and params["iterations"] == 6
    assert "init_demosaic" in record["stages_s"]
    assert score(out.image, capture.gt, with_ssim=False)["psnr_mean"] > 25


def test_caps_plus_is_caps_with_its_slots_changed(capture):
    """With caps's data term, initialization and schedule, caps-plus is caps, bit for bit."""
    same = {"iterations": 4, "mu0": 0.5, "c2": 0.02}
    plus, _ = reconstruct(capture, "caps-plus", true_warps=True, data_term="cagf", init="fusion", **same)
    caps, _ = reconstruct(capture, "caps", true_warps=True, **same)
    assert np.array_equal(plus.image, caps.image)


def test_the_naive_initialization_is_caps_naives_image(capture):
    """-p prior=none with 0 iterations of steepest descent leaves the initialization: caps-naive's image
    (inside a 4 px border, where the two methods' unobserved pixels are filled differently)."""
    plus, record = reconstruct(capture, "caps-plus", true_warps=True, prior="none", iterations=0, init="naive")
    naive, _ = reconstruct(capture, "caps-naive", true_warps=True)
    inner = (slice(None), slice(4, -4), slice(4, -4))
    assert np.allclose(plus.image[inner], naive.image[inner], atol=1e-5)
    assert not np.allclose(plus.image[inner], reconstruct(capture, "caps", true_warps=True, prior="none",
                                                          iterations=0)[0].image[inner], atol=1e-3)


def test_the_split_initialization_takes_the_fusions_mean_and_the_apertures_polarization(capture):
    """-p init=split: the analyzer mean of each colour from caps's fused start, the rest from the demosaicked
    apertures (read through 0 iterations of steepest descent, no physical projection; inside a 4 px border)."""
    start = {"true_warps": True, "prior": "none", "iterations": 0, "physical_projection": False}
    split, record = reconstruct(capture, "caps-plus", init="split", **start)
    fusion, _ = reconstruct(capture, "caps-plus", init="fusion", **start)
    naive, _ = reconstruct(capture, "caps-plus", init="naive", **start)
    assert record["params"]["init"] == "split"
    inner = (slice(None), slice(4, -4), slice(4, -4))
    split, fusion, naive = (torch.from_numpy(x.image[inner]) for x in (split, fusion, naive))
    assert torch.allclose(angle_mean(split), angle_mean(fusion), atol=1e-5)
    assert torch.allclose(split - angle_mean(split), naive - angle_mean(naive), atol=1e-5)
    assert not torch.allclose(split, naive, atol=1e-3) and not torch.allclose(split, fusion, atol=1e-3)


def test_caps_plus_refuses_an_unknown_initialization(capture):
    with pytest.raises(CapssimError, match="init"):
        reconstruct(capture, "caps-plus", true_warps=True, init="zeros")


# -- the noise-adaptive schedule ---------------------------------------------------------------------
def test_the_iteration_count_grows_with_the_noise_and_is_clipped():
    assert [noise_adaptive_iterations(s) for s in (0.0, 0.005, 0.01, 0.02, 0.5)] == [10, 15, 20, 30, 50]
    assert noise_adaptive_iterations(float("nan")) == 50 and noise_adaptive_iterations(float("inf")) == 50


def test_raw_noise_sigma_reads_white_noise_on_smooth_planes():
    g = torch.Generator().manual_seed(0)
    ramp = 0.2 + 0.5 * torch.linspace(0, 1, 64)[None, :, None] * torch.ones(16, 64, 64)
    assert raw_noise_sigma(ramp) < 1e-5  # a linear ramp holds no noise
    for sigma in (0.005, 0.01, 0.02):
        assert raw_noise_sigma(ramp + sigma * torch.randn(16, 64, 64, generator=g)) == pytest.approx(sigma, rel=0.1)
    assert raw_noise_sigma(torch.zeros(16, 2, 2)) == 0.0  # too small to estimate


def test_caps_plus_takes_its_iterations_from_the_noise_unless_given(capture):
    out, record = reconstruct(capture, "caps-plus", true_warps=True, stopping="noise")
    params = record["params"]
    assert params["iterations_from"] == "noise" and 0.005 < params["noise_sigma_estimate"] < 0.03
    assert params["iterations"] == noise_adaptive_iterations(params["noise_sigma_estimate"])
    assert len(out.history) == params["iterations"]
    assert frame_iterations(capture, {}) == {"stopping": "noise", "polarization_filter": "none", "iterations": params["iterations"]}  # a tiled run
    assert frame_iterations(capture, {"stopping": "holdout"}) == {}
    for given, count in (({"iterations": 3}, 3), ({"preset": "fast"}, 7)):
        out, record = reconstruct(capture, "caps-plus", true_warps=True, **given)
        assert record["params"]["iterations_from"] == "options" and frame_iterations(capture, given) == {}
        assert record["params"]["iterations"] == count and len(out.history) == count


def test_a_clean_capture_gets_fewer_iterations_than_a_noisy_one(smooth_random_scene):
    scene = smooth_random_scene(SIZE, seed=3)
    sensors = (make_sensor("none"), make_sensor("gaussian", sigma=0.01), make_sensor("gaussian", sigma=0.03))
    counts = [frame_iterations(simulate_capture(scene, sensor, seed=3), {})["iterations"] for sensor in sensors]
    assert counts[0] < counts[1] < counts[2]
