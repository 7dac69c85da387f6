"""Structure-aware coupling (issue 36, item 2): the analyzers' agreement ``alpha``, the ``cagf-agree`` data
term that mixes eq. 26 and the polarization-split direction by it, and ``caps-plus``'s ``init=agree``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import CapssimError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.model.analyzer_agreement import agreement_confidence_mix, analyzer_agreement
from capssim.reconstruct.model.data_term import confidence_mix
from capssim.reconstruct.model.polarization_split import angle_mean, split_confidence_mix
from capssim.reconstruct.selection import SELECTED_NOTHING
from capssim.simulate import simulate_capture

#: the selection record of a run whose every choice was given as an option

SIZE = 48


def texture(h=24, w=24, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, generator=g, dtype=torch.float64)


def analyzer_stack(per_angle):
    """``(12, h, w)`` angle-major from four ``(h, w)`` analyzer images, the same for the three colours."""
    return torch.stack([img for img in per_angle for _ in range(3)])


def test_proportional_analyzer_images_agree():
    """A uniform degree and angle of polarization: every analyzer image a positive multiple of one texture."""
    t = texture()
    alpha = analyzer_agreement(analyzer_stack([0.9 * t, 0.6 * t, 0.3 * t + 0.05, 0.5 * t]))
    assert alpha.shape == t.shape
    assert float(alpha.min()) > 0.95


def test_opposite_contrast_gives_zero_agreement():
    """Polarization-only structure: I_0 bright where I_90 is dark."""
    t = texture(seed=1)
    alpha = analyzer_agreement(analyzer_stack([t, 0.5 + 0 * t, 1 - t, 0.5 + 0 * t]))
    assert float(alpha.max()) == 0.0


def noisy(images, sigma, seed):
    g = torch.Generator().manual_seed(seed)
    return [img + sigma * torch.randn(img.shape, generator=g, dtype=img.dtype) for img in images]


def test_noise_alone_does_not_read_as_disagreement():
    """A flat, noisy window carries no evidence that the analyzers differ: alpha near 1 (shared residuals)."""
    flat = [0.5 + 0 * texture(32, 32)] * 4
    assert float(analyzer_agreement(analyzer_stack(noisy(flat, 0.01, 2))).mean()) > 0.5  # uncorrected: about 0.1


@pytest.mark.parametrize("sigma", [0.01, 0.03])
def test_agreement_is_corrected_for_the_noise(sigma):
    """Proportional analyzer images under noise still agree; opposite contrast under noise still does not."""
    t = texture(32, 32, seed=3)
    proportional = analyzer_agreement(analyzer_stack(noisy([0.9 * t, 0.6 * t, 0.3 * t, 0.5 * t], sigma, 4)))
    assert float(proportional.median()) > 0.8
    opposite = analyzer_agreement(analyzer_stack(noisy([t, 0.5 + 0 * t, 1 - t, 0.5 + 0 * t], sigma, 5)))
    assert float(opposite.max()) == 0.0


def test_agreement_is_in_zero_one_and_refuses_a_wrong_channel_count():
    g = torch.Generator().manual_seed(3)
    alpha = analyzer_agreement(torch.rand(12, 10, 9, generator=g))
    assert alpha.shape == (10, 9) and float(alpha.min()) >= 0 and float(alpha.max()) <= 1
    with pytest.raises(CapssimError, match="channels"):
        analyzer_agreement(torch.rand(6, 10, 9))
    with pytest.raises(CapssimError, match="cagf_eps"):
        analyzer_agreement(torch.rand(12, 10, 9), eps=0.0)
    given = analyzer_agreement(torch.rand(12, 10, 9, generator=g), noise_std=torch.zeros(12))
    assert given.shape == (10, 9)


def test_the_mix_is_eq26_at_one_and_the_split_at_zero(random_confidence):
    conf = random_confidence(12, 4, 5, seed=4)
    b = torch.randn(12, 4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    ones, zeros = torch.ones(4, 5, dtype=torch.float64), torch.zeros(4, 5, dtype=torch.float64)
    assert torch.allclose(agreement_confidence_mix(conf, b, ones), confidence_mix(conf, b), atol=1e-12)
    assert torch.allclose(agreement_confidence_mix(conf, b, zeros), split_confidence_mix(conf, b), atol=1e-12)


def test_the_mixed_direction_is_symmetric_positive_semidefinite(random_confidence, per_pixel_matrix):
    """alpha L + (1 - alpha) T per pixel: a descent direction with the same fixed points, for any alpha in [0, 1]."""
    conf = random_confidence(12, 3, 4, seed=6)
    alpha = torch.rand(3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    t = per_pixel_matrix(lambda e: agreement_confidence_mix(conf, e, alpha), 12, 3, 4)
    assert torch.allclose(t, t.transpose(-1, -2), atol=1e-12)
    assert torch.linalg.eigvalsh(t).min() > -1e-10


@pytest.fixture(scope="module")
def capture(smooth_random_scene):
    return simulate_capture(smooth_random_scene(SIZE, seed=11), make_sensor("gaussian", sigma=0.01), seed=11)


def test_caps_plus_runs_with_the_agreement_data_term(capture):
    fixed = {"true_warps": True, "iterations": 5, "polarization_filter": "none"}
    out, record = reconstruct(capture, "caps-plus", data_term="cagf-agree", **fixed)
    assert record["params"]["data_term"] == "cagf-agree" and record["params"]["init"] == "agree"
    assert "agreement" in record["stages_s"]
    assert out.image.shape == (12, SIZE, SIZE) and np.isfinite(out.image).all()
    split, _ = reconstruct(capture, "caps-plus", data_term="cagf-split", **fixed)
    assert not np.array_equal(out.image, split.image)


def test_the_agree_initialization_lies_between_split_and_fusion(capture):
    """-p init=agree: the fusion's analyzer mean; per pixel, its polarization part between the demosaicked
    apertures' (alpha 0: ``split``, the fusion's analyzer mean with the apertures' polarization part) and the
    fusion's (alpha 1) (read through 0 iterations, inside a 4 px border)."""
    start = {"true_warps": True, "prior": "none", "iterations": 0, "physical_projection": False,
             "polarization_filter": "none"}
    images = {}
    for init in ("agree", "naive", "fusion"):
        out, record = reconstruct(capture, "caps-plus", init=init, **start)
        assert record["params"]["init"] == init
        images[init] = torch.from_numpy(out.image[:, 4:-4, 4:-4]).double()
    agree, naive, fusion = images["agree"], images["naive"], images["fusion"]
    split = (angle_mean(fusion) + naive - angle_mean(naive)).clamp(0.0, 1.0)
    assert torch.allclose(angle_mean(agree), angle_mean(fusion), atol=1e-5)
    lo, hi = torch.minimum(split, fusion), torch.maximum(split, fusion)
    assert bool(((agree >= lo - 1e-5) & (agree <= hi + 1e-5)).all())
    assert not torch.allclose(agree, split, atol=1e-4) and not torch.allclose(agree, fusion, atol=1e-4)


@pytest.mark.parametrize("init", ["zeros", "split"])
def test_an_unknown_initialization_lists_agree(capture, init):
    with pytest.raises(CapssimError, match="agree"):
        reconstruct(capture, "caps-plus", true_warps=True, init=init)


def test_the_start_and_the_data_term_share_one_agreement_map(capture, monkeypatch):
    """caps-plus's defaults use alpha twice (init=agree, data_term=cagf-stokes): it is computed once per problem
    (here one: the choices are given, so no validation problem is built)."""
    import capssim.reconstruct.pipeline.slots as slots

    computed = []
    original = slots.analyzer_agreement_map
    monkeypatch.setattr(slots, "analyzer_agreement_map", lambda *a, **k: computed.append(1) or original(*a, **k))
    _, record = reconstruct(capture, "caps-plus", true_warps=True, iterations=2, polarization_filter="none",
                            data_term="cagf-stokes", init="agree")
    assert record["params"]["selection"] == SELECTED_NOTHING
    assert len(computed) == 1


def test_the_agree_all_initialization_blends_the_analyzer_mean_too(capture):
    """-p init=agree-all: per pixel ``alpha fusion + (1 - alpha) naive`` for every channel,
    so it lies between the two starts, keeps init=agree's polarization part and differs from it only in the
    analyzer mean (read through 0 iterations, inside a 4 px border)."""
    start = {"true_warps": True, "prior": "none", "iterations": 0, "physical_projection": False,
             "polarization_filter": "none"}
    images = {}
    for init in ("agree-all", "agree", "naive", "fusion"):
        out, record = reconstruct(capture, "caps-plus", init=init, **start)
        assert record["params"]["init"] == init
        images[init] = torch.from_numpy(out.image[:, 4:-4, 4:-4]).double()
    blend, agree, naive, fusion = images["agree-all"], images["agree"], images["naive"], images["fusion"]
    lo, hi = torch.minimum(naive, fusion), torch.maximum(naive, fusion)
    assert bool(((blend >= lo - 1e-5) & (blend <= hi + 1e-5)).all())
    interior = ((agree > 1e-4) & (agree < 1 - 1e-4) & (blend > 1e-4) & (blend < 1 - 1e-4)).all(dim=0)  # no clamp
    assert torch.allclose((blend - angle_mean(blend))[:, interior], (agree - angle_mean(agree))[:, interior], atol=1e-5)
    assert not torch.allclose(angle_mean(blend), angle_mean(fusion), atol=1e-4)
    assert not torch.allclose(blend, naive, atol=1e-4)
