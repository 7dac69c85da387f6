"""Confidence-guided data term (paper eq. 15-16, 25-26) and the field-of-view weights."""

import numpy as np
import pytest
import torch

from capssim.camera.array_geometry import ArrayGeometry, lr_homographies
from capssim.camera.homography import similarity
from capssim.camera.psf import gaussian_psf_kernel
from capssim.conventions import LR_IMAGE_CHANNELS
from capssim.errors import InputError
from capssim.operators.camera import lr_sampling_operator
from capssim.reconstruct.model.data_term import ConfidenceDataTerm, confidence_mix, field_of_view_mask
from capssim.reconstruct.model.rearrange import Observations

HR = (24, 32)


def setup(seed=0, confidence=None, dtype=torch.float64):
    rng = np.random.default_rng(seed)
    hn = np.stack([np.eye(3)] + [similarity(rng.uniform(-1, 1, 2), rng.uniform(-0.5, 0.5), 1.0, (15.5, 11.5))
                                 for _ in range(3)])
    hm = lr_homographies(hn)
    op = lr_sampling_operator(ArrayGeometry(hn, HR), gaussian_psf_kernel(0.5))
    y = torch.as_tensor(rng.random((16, 6, 8)), dtype=dtype)
    w = torch.ones_like(y)
    w[3, 2, 2] = 0  # a saturated pixel
    obs = Observations(y, w, torch.tensor(LR_IMAGE_CHANNELS), 12)
    return ConfidenceDataTerm(obs, op, confidence=confidence), hm


def test_backprojection_is_minus_gradient():
    data, _ = setup()
    x = torch.rand(12, *HR, dtype=torch.float64, requires_grad=True)
    value = 0.5 * data.residual(x).square().sum()
    value.backward()
    with torch.no_grad():
        bp = data.backprojection(x)
        assert torch.allclose(bp, -x.grad, atol=1e-12)
        direction, f = data.descent_direction(x)
        assert torch.allclose(direction, bp) and f == pytest.approx(float(value))


def test_saturated_pixels_have_no_influence():
    data, _ = setup()
    x = torch.rand(12, *HR, dtype=torch.float64)
    before = data.value(x)
    data.obs.images[3, 2, 2] += 100.0
    assert data.value(x) == pytest.approx(before)


def test_confidence_mixes_all_observations():
    gen = torch.Generator().manual_seed(0)
    conf = torch.rand(12, 12, *HR, generator=gen, dtype=torch.float64)
    conf = 0.5 * (conf + conf.transpose(0, 1))
    idx = torch.arange(12)
    conf[idx, idx] = 1.0
    data, _ = setup(confidence=conf)
    plain, _ = setup()
    x = torch.rand(12, *HR, dtype=torch.float64)
    bp = plain.backprojection(x)
    direction, _ = data.descent_direction(x)
    # D_c = sum_m L[c(m), c] M_m^T r_m = sum_j L[j, c] B_j
    expected = sum(conf[j] * bp[j] for j in range(12))
    assert torch.allclose(direction, expected)
    # channel 0 (0-R) now draws on the G observations of aperture 0 too
    assert not torch.allclose(direction[0], bp[0])
    identity = torch.zeros(12, 12, *HR, dtype=torch.float64)
    identity[idx, idx] = 1.0
    data_id, _ = setup(confidence=identity)
    assert torch.allclose(data_id.descent_direction(x)[0], bp)


def test_truth_has_zero_residual():
    data, hm = setup()
    x = torch.rand(12, *HR, dtype=torch.float64)
    obs = data.obs
    obs.images = data.operator(x.index_select(0, obs.channel_of))
    assert ConfidenceDataTerm(obs, data.operator).value(x) < 1e-20


def test_shape_checks():
    data, _ = setup()
    with pytest.raises(InputError):
        ConfidenceDataTerm(data.obs, data.operator, confidence=torch.ones(12, 12, 4, 4))


def test_field_of_view_mask():
    hm = lr_homographies(np.stack([np.eye(3)] * 4))
    inside = field_of_view_mask(hm, (6, 8), HR, half_extent=0.125)
    assert inside.all()  # the reference grid itself: every footprint inside
    shifted = lr_homographies(np.stack([np.eye(3)] + [similarity((3.0, 0.0))] * 3))
    inside = field_of_view_mask(shifted, (6, 8), HR, half_extent=0.125)
    assert inside[:4].all()
    # a +3 px shift moves the first sub-image column outside the reference grid
    assert not inside[4:, :, 0].any() and inside[4:, :, 1:].all()


def test_confidence_mix_equals_the_per_pixel_product():
    gen = torch.Generator().manual_seed(5)
    conf = torch.rand(4, 4, 6, 7, generator=gen, dtype=torch.float64)
    b = torch.randn(4, 6, 7, generator=gen, dtype=torch.float64)
    assert torch.allclose(confidence_mix(conf, b), torch.einsum("jchw,jhw->chw", conf, b))


def test_residual_is_reused_only_for_the_same_unmodified_image():
    data, _ = setup()
    x = torch.rand(12, *HR, dtype=torch.float64)
    calls = []
    forward = data.operator.forward
    data.operator.forward = lambda t: calls.append(1) or forward(t)
    f = data.value(x)
    _, f2 = data.descent_direction(x)                 # same x: M applied once
    assert f2 == f and len(calls) == 1
    x.mul_(0.5)                                       # modified in place: recomputed
    assert data.value(x) != f and len(calls) == 2
    assert data.value(x.clone()) == data.value(x) and len(calls) == 4  # another tensor: recomputed
