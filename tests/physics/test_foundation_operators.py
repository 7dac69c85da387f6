"""Adjointness (dot test) of every camera operator and composite, and their exact behaviour."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.homography import random_aperture_homographies, similarity
from capssim.camera.psf import airy_psf_kernel, gaussian_psf_kernel
from capssim.conventions import LR_IMAGE_CHANNELS
from capssim.errors import InputError
from capssim.operators import (
    Analyzer,
    BayerMosaic,
    BayerSplit,
    BlurIntegrateDecimate,
    ChannelMix,
    ChannelSelect,
    Composition,
    Convolve,
    Decimation,
    DoFPMosaic,
    IntegrateDecimate,
    PixelIntegration,
    Reshape,
    Stack,
    Warp,
    adjointness_error,
    caps_raw_operator,
    dofp_raw_operator,
    lr_observation_operator,
    lr_sampling_operator,
    operator_norm_estimate,
)

TOL = 1e-10
HR = (24, 32)


def _aperture_h():
    rng = np.random.default_rng(3)
    h, _ = random_aperture_homographies(rng, HR, shift_max_px=3.0, rotation_max_deg=2.0, scale_max=0.02)
    return h


def _operators():
    hn = _aperture_h()
    k = gaussian_psf_kernel(0.8)
    persp = similarity((1.3, -0.7), 5.0, 1.05, (10, 12))
    persp[2, :2] = [1e-4, -2e-4]
    return {
        "analyzer": Analyzer(*HR),
        "analyzer_er": Analyzer(*HR, extinction_ratio=30.0),
        "channel_mix": ChannelMix(np.random.default_rng(0).normal(size=(5, 12)), *HR, out_lead=(5,)),
        "channel_select": ChannelSelect(LR_IMAGE_CHANNELS, 12, *HR),
        "warp_similarity": Warp(hn, 3, HR),
        "warp_perspective_resize": Warp(persp[None], 2, (20, 22), (17, 25)),
        "convolve_gauss": Convolve(k, (2, 3, *HR)),
        "convolve_airy": Convolve(airy_psf_kernel(2.8, 550, 1.2), (3, 19, 23)),
        "convolve_asym": Convolve(np.random.default_rng(1).random((3, 5)), (2, 11, 9)),
        "pixel_integration": PixelIntegration(2, (3, *HR)),
        "pixel_integration_3": PixelIntegration(3, (2, 9, 12)),
        "decimation_shared": Decimation(2, (3, 2, *HR), (1, 0)),
        "decimation_per_batch": Decimation(2, (4, 1, *HR), [(0, 0), (0, 1), (1, 0), (1, 1)]),
        "integrate_decimate": IntegrateDecimate(2, (4, 3, *HR)),
        "blur_integrate_decimate": BlurIntegrateDecimate(
            [k, np.random.default_rng(2).random((3, 5)), airy_psf_kernel(2.8, 550, 1.2), np.ones((1, 1))],
            (8, 1, *HR), integrate=2, decimate=2, offsets=[(0, 0), (0, 1), (1, 0), (1, 1)] * 2),
        "blur_integrate_decimate_3": BlurIntegrateDecimate(k, (2, 3, 18, 36), integrate=3, decimate=2,
                                                           offsets=(1, 0)),
        "bayer_mosaic": BayerMosaic((4, 3, *HR)),
        "bayer_split": BayerSplit((4, *HR)),
        "dofp_mosaic": DoFPMosaic(*HR, layout="sony"),
        "dofp_mosaic_alt": DoFPMosaic(*HR, layout="0-45-135-90"),
        "reshape": Reshape((12, *HR), (4, 3, *HR)),
        "caps_raw": caps_raw_operator(HR, hn, k),
        "caps_raw_er": caps_raw_operator(HR, hn, k, extinction_ratio=100.0),
        "lr_sampling": lr_sampling_operator(ArrayGeometry(hn, HR), k),
        "lr_observation": lr_observation_operator(ArrayGeometry(hn, HR), k, extinction_ratio=50.0),
        "dofp_raw": dofp_raw_operator(HR, k),
        "dofp_raw_er": dofp_raw_operator(HR, k, layout="0-45-135-90", extinction_ratio=80.0),
        "stack_caps_dofp": Stack([caps_raw_operator(HR, hn, k), dofp_raw_operator(HR, k)]),
        "composition_adjoint": Composition([BayerSplit((4, *HR)).T, BayerSplit((4, *HR))]),
    }


@pytest.mark.parametrize("name", sorted(_operators()))
def test_dot_product_adjointness(name):
    op = _operators()[name]
    for seed in range(3):
        assert adjointness_error(op, seed=seed) < TOL, op.describe()


def test_adjoint_of_adjoint_is_forward():
    op = _operators()["caps_raw"]
    x = torch.rand(op.input_shape, dtype=torch.float64)
    assert torch.equal(op.T.T(x), op(x))


def test_integrate_decimate_equals_integration_then_decimation():
    x = torch.rand(2, 3, *HR, dtype=torch.float64)
    fast = IntegrateDecimate(2, x.shape)(x)
    slow = Decimation(2, x.shape)(PixelIntegration(2, x.shape)(x))
    torch.testing.assert_close(fast, slow, rtol=0, atol=1e-14)


@pytest.mark.parametrize("integrate,decimate,shape", [(2, 2, (8, 1, *HR)), (3, 2, (2, 2, 18, 30)),
                                                     (1, 4, (4, 1, 16, 8)), (2, 1, (4, 1, 6, 10))])
def test_blur_integrate_decimate_equals_the_three_operators(integrate, decimate, shape):
    rng = np.random.default_rng(4)
    kernels = [rng.random((5, 5)), rng.random((3, 7)), gaussian_psf_kernel(0.8), np.ones((1, 1))]
    offsets = [(int(a), int(b)) for a, b in rng.integers(0, decimate, size=(shape[0], 2))]
    fused = BlurIntegrateDecimate(kernels, shape, integrate=integrate, decimate=decimate, offsets=offsets)
    mid = (*shape[:-2], shape[-2] // integrate, shape[-1] // integrate)
    slow = Composition([Convolve(kernels, shape), IntegrateDecimate(integrate, shape),
                        Decimation(decimate, mid, offsets)])
    x = torch.rand(shape, dtype=torch.float64)
    y = torch.rand(fused.output_shape, dtype=torch.float64)
    torch.testing.assert_close(fused(x), slow(x), rtol=0, atol=1e-13)
    torch.testing.assert_close(fused.adjoint(y), slow.adjoint(y), rtol=0, atol=1e-13)


def test_blur_integrate_decimate_rejects_bad_offsets_and_sizes():
    with pytest.raises(InputError, match="offsets"):
        BlurIntegrateDecimate(np.ones((3, 3)), (2, 1, 8, 8), integrate=2, decimate=2, offsets=[(0, 2), (0, 0)])
    with pytest.raises(InputError, match="divisible"):
        BlurIntegrateDecimate(np.ones((3, 3)), (2, 1, 10, 8), integrate=2, decimate=2)


def test_warp_identity_and_integer_shift():
    x = torch.rand(1, 2, 12, 14, dtype=torch.float64)
    torch.testing.assert_close(Warp(np.eye(3)[None], 2, (12, 14))(x), x, rtol=0, atol=1e-14)
    shift = np.array([[1, 0, 3.0], [0, 1, -2.0], [0, 0, 1]])  # content moves +3 cols, -2 rows
    y = Warp(shift[None], 2, (12, 14))(x)
    torch.testing.assert_close(y[0, :, 0:10, 3:], x[0, :, 2:12, 0:11], rtol=0, atol=1e-14)


def test_warp_preserves_affine_ramp_under_rotation():
    rows, cols = np.meshgrid(np.arange(40.0), np.arange(40.0), indexing="ij")
    ramp = torch.from_numpy(0.3 * cols - 0.2 * rows + 5)[None, None]
    h = similarity((0.4, -0.3), 3.0, 1.01, (19.5, 19.5))
    out = Warp(h[None], 1, (40, 40))(ramp)[0, 0].numpy()
    src = np.linalg.inv(h) @ np.stack([cols.ravel(), rows.ravel(), np.ones(cols.size)])
    expected = (0.3 * src[0] - 0.2 * src[1] + 5).reshape(40, 40)
    inner = (slice(3, -3), slice(3, -3))  # borders clamp
    np.testing.assert_allclose(out[inner], expected[inner], atol=1e-9)


def test_psf_kernels_normalised_and_identity_at_zero():
    assert gaussian_psf_kernel(0.0).shape == (1, 1)
    for k in (gaussian_psf_kernel(0.5), gaussian_psf_kernel(2.0), airy_psf_kernel(1.65, 550, 2.4)):
        assert k.shape[0] % 2 == 1 and abs(k.sum() - 1) < 1e-12
        np.testing.assert_allclose(k, k[::-1, ::-1], atol=1e-15)
    x = torch.rand(1, 9, 9, dtype=torch.float64)
    torch.testing.assert_close(Convolve(gaussian_psf_kernel(0.0), (1, 9, 9))(x), x)


def test_gaussian_kernel_variance_matches_sigma():
    k = gaussian_psf_kernel(2.0)
    r = np.arange(k.shape[0]) - k.shape[0] // 2
    var = (k.sum(axis=1) * r**2).sum()
    assert abs(var - (4.0 + 1 / 12)) < 0.02  # pixel integration adds 1/12


def test_airy_first_zero_position():
    # first dark ring at 1.22 lambda N: with pitch = 1.22 lambda N / 4, it lies 4 pixels out
    pitch = 1.22 * 0.55 * 2.0 / 4
    k = airy_psf_kernel(2.0, 550, pitch, supersample=15)
    c = k.shape[0] // 2
    profile = k[c, c:]
    assert np.argmin(profile[:6]) == 4


def test_bayer_split_matches_lr_observation_exactly():
    hn = _aperture_h()
    k = gaussian_psf_kernel(0.6)
    x = torch.rand(12, *HR, dtype=torch.float64)
    raw = caps_raw_operator(HR, hn, k)(x)
    split = BayerSplit((4, HR[0] // 2, HR[1] // 2))(raw).reshape(16, HR[0] // 4, HR[1] // 4)
    lr = lr_observation_operator(ArrayGeometry(hn, HR), k)(x)
    torch.testing.assert_close(split, lr, rtol=0, atol=1e-12)


def test_analyzer_extinction_ratio_physics():
    # unpolarized light reads S0/2 through any polarizer, whatever the extinction ratio
    hh, ww = 4, 4
    x = torch.full((12, hh, ww), 0.5, dtype=torch.float64)
    for er in (None, 2.0, 1000.0):
        y = Analyzer(hh, ww, extinction_ratio=er)(x)
        torch.testing.assert_close(y, torch.full_like(y, 0.5))
    # fully polarized at 0 deg: I0=1, I90=0, I45=I135=0.5; an ER=9 polarizer at 90 leaks 10 %
    pol = torch.tensor([1.0, 0.5, 0.0, 0.5], dtype=torch.float64).repeat_interleave(3)[:, None, None].expand(12, 1, 1)
    y = Analyzer(1, 1, extinction_ratio=9.0)(pol.contiguous())
    assert abs(float(y[2, 0]) - 0.1) < 1e-12 and abs(float(y[0, 0]) - 0.9) < 1e-12


def test_operator_norm_of_sampling_is_bounded():
    hn = _aperture_h()
    op = lr_sampling_operator(ArrayGeometry(hn, HR), gaussian_psf_kernel(0.5))
    assert 0.1 < operator_norm_estimate(op, iterations=20) <= 1.0 + 1e-6


def test_shape_and_dtype_errors_are_clear():
    op = BayerSplit((4, 8, 8))
    with pytest.raises(InputError, match=r"shape \(4, 8, 8\)"):
        op(torch.zeros(4, 8, 6))
    with pytest.raises(InputError, match="floating dtype"):
        op(torch.zeros(4, 8, 8, dtype=torch.int64))
    with pytest.raises(InputError, match="divisible"):
        IntegrateDecimate(2, (1, 7, 8))
    with pytest.raises(InputError, match="odd"):
        Convolve(np.ones((2, 2)), (1, 8, 8))
    with pytest.raises(InputError, match="invertible"):
        Warp(np.zeros((1, 3, 3)), 1, (8, 8))
    with pytest.raises(InputError, match="divisible by 4"):
        caps_raw_operator((30, 32), np.stack([np.eye(3)] * 4), np.ones((1, 1)))
    with pytest.raises(InputError, match="output_shape equal"):
        Composition([BayerSplit((4, 8, 8)), BayerSplit((4, 8, 8))])


def test_float32_and_float64_agree():
    op = _operators()["caps_raw"]
    x = torch.rand(op.input_shape, dtype=torch.float64)
    torch.testing.assert_close(op(x.float()).double(), op(x), rtol=0, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    op = _operators()["lr_observation"]
    x = torch.rand(op.input_shape, dtype=torch.float64)
    torch.testing.assert_close(op(x.cuda()).cpu(), op(x))
    assert adjointness_error(op, device="cuda") < TOL
