"""``array-kr``: accuracy with true warps, zero weight for saturated and unseen samples, odd and tiny frames,
CUDA, option refusal."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.array_geometry import raw_matrix
from capssim.camera.sensor import make_sensor
from capssim.errors import InputError
from capssim.reconstruct.kernel_regression import fusion
from capssim.reconstruct.kernel_regression.fusion import fuse_apertures, visibility
from capssim.reconstruct.kernel_regression.gather import SampleField
from capssim.reconstruct.kernel_regression.merge import aperture_weights
from capssim.reconstruct.methods.array_kr import parse_options, reconstruct_raw
from capssim.reconstruct.registry import available_methods, reconstruct
from capssim.simulate import simulate_capture


def _psnr(a, b):
    return float(10 * np.log10(1.0 / max(np.mean((np.asarray(a, np.float64) - b) ** 2), 1e-30)))


@pytest.fixture(scope="module")
def smooth_capture(smooth_random_scene):
    """A noise-free capture (rig's default sub-pixel warps) of a smooth 64 px scene whose colours share one
    texture, with its ground truth."""
    scene = smooth_random_scene(64, seed=3).reshape(4, 3, 64, 64)
    gt = (scene.mean(axis=1, keepdims=True) * np.array([0.9, 1.0, 0.8], np.float32)[None, :, None, None])
    gt = gt.reshape(12, 64, 64)
    return simulate_capture(gt, make_sensor("none"), seed=0, psf={"type": "none"}), gt


def _raw_h(shifts_hr):
    """HR -> raw maps of four apertures translated by ``shifts_hr`` ``(4, 2)`` HR px."""
    out = []
    for dx, dy in shifts_hr:
        h = np.eye(3)
        h[0, 2], h[1, 2] = dx, dy
        out.append(raw_matrix() @ h)
    return np.stack(out)


def test_registered_with_options_and_reference():
    spec = available_methods()["array-kr"]
    assert spec.input_kind == "caps" and "Wronski" in spec.reference and spec.tuned_on
    assert [o.name for o in spec.options()] == ["samples", "detail", "sharpen", "scale", "steer", "polarization",
                                                "clip"]


@pytest.mark.parametrize("samples", ["demosaicked", "raw"])
def test_noise_free_smooth_scene_with_true_warps_is_reproduced(smooth_capture, samples):
    capture, gt = smooth_capture
    out, record = reconstruct(capture, "array-kr", true_warps=True, physical_projection=False, samples=samples)
    assert out.image.shape == gt.shape
    assert _psnr(out.image[:, 4:-4, 4:-4], gt[:, 4:-4, 4:-4]) >= 40.0
    # the polarization parts too: each analyzer minus the mean of the four
    own = out.image.reshape(4, 3, 64, 64) - out.image.reshape(4, 3, 64, 64).mean(0)
    truth = gt.reshape(4, 3, 64, 64) - gt.reshape(4, 3, 64, 64).mean(0)
    assert _psnr(own[..., 4:-4, 4:-4], truth[..., 4:-4, 4:-4]) >= 40.0
    assert record["params"]["polarization"] == "ratio"


def test_weights_vanish_on_saturated_and_unseen_samples():
    raw = np.full((4, 16, 16), 0.4, np.float32)
    saturated = np.zeros_like(raw, bool)
    saturated[1, 4:12, 4:12] = True  # aperture 1: a saturated block
    raw[1][saturated[1]] = 1.0
    shifts = [(0, 0), (0.5, 0.5), (-0.5, 0.25), (24.0, 0.0)]  # aperture 3 sees only the left part of the grid
    field = SampleField.build(torch.from_numpy(raw), torch.from_numpy(~saturated), _raw_h(shifts), (0, 1, 1, 2))
    weights = aperture_weights(field, (32, 32)).numpy()
    assert np.all(weights[1, 12:20, 12:20] == 0.0)  # inside the saturated block (HR 8..24), beyond the kernel's reach
    assert np.all(weights[0, 12:20, 12:20] > 0.1) and np.all(weights[2, 12:20, 12:20] > 0.1)
    # aperture 3 reads raw x = (X + 24) / 2 - 0.25: HR columns X > 7.5 are out of its 16-px frame
    assert np.all(weights[3, :, 12:] == 0.0) and np.all(weights[3, :, :6] > 0.1)
    # the saturated aperture does not leak into the others' images; its own stays at its clip level
    image, _ = reconstruct_raw(raw, saturated, _raw_h(shifts), (32, 32), sigma_n=0.0)
    np.testing.assert_allclose(image[[0, 2], :, 12:20, 4:10].numpy(), 0.4, atol=1e-4)
    np.testing.assert_allclose(image[1, :, 12:20, 12:20].numpy(), 1.0, atol=1e-4)


@pytest.mark.parametrize("raw_hw", [(9, 13), (2, 2), (2, 3)])
def test_odd_and_tiny_frames(raw_hw):
    h, w = raw_hw
    value = np.array([0.2, 0.3, 0.5, 0.4], np.float32)[:, None, None]  # one polarized constant per aperture
    raw = np.broadcast_to(value, (4, h, w)).copy()
    hr = (2 * h, 2 * w)
    image, record = reconstruct_raw(raw, np.zeros_like(raw, bool), _raw_h([(0, 0)] * 4), hr, sigma_n=0.0)
    assert image.shape == (4, 3, *hr) and torch.isfinite(image).all()
    np.testing.assert_allclose(image.numpy(), np.broadcast_to(value[:, None], image.shape), atol=1e-4)


def test_bad_input_is_refused_in_one_line():
    with pytest.raises(InputError, match="raw"):
        reconstruct_raw(np.zeros((3, 4, 4)), np.zeros((3, 4, 4), bool), _raw_h([(0, 0)] * 4), (8, 8))
    with pytest.raises(InputError, match="hr_shape"):
        reconstruct_raw(np.zeros((4, 1, 1)), np.zeros((4, 1, 1), bool), _raw_h([(0, 0)] * 4), (1, 1))


def test_options_are_checked():
    assert parse_options({"scale": "1.5", "polarization": "Difference"})["polarization"] == "difference"
    assert "iterations" not in parse_options({"iterations": 3})  # a caps option (-m all --iterations N): ignored
    with pytest.raises(InputError, match="Did you mean 'scale'"):
        parse_options({"scal": 1})
    with pytest.raises(InputError, match="scale"):
        parse_options({"scale": 10})
    with pytest.raises(InputError, match="polarization"):
        parse_options({"polarization": "stokes"})
    assert parse_options({"samples": "RAW"})["samples"] == "raw"
    with pytest.raises(InputError, match="samples"):
        parse_options({"samples": "bayer"})
    with pytest.raises(InputError, match="sharpen"):
        parse_options({"sharpen": 3})


def test_fusion_replaces_an_aperture_where_it_is_saturated_or_out_of_view():
    """Aperture 0 saturated in a block and all apertures shifted: where aperture 0 does not see a pixel its image
    is I_45 + I_135 - I_90 of the others, exact on a constant polarized scene."""
    levels = torch.tensor([0.7, 0.4, 0.1, 0.4])  # I_0 + I_90 = I_45 + I_135
    rgb = levels.view(4, 1, 1, 1).expand(4, 3, 16, 16).clone()
    usable = torch.ones(4, 16, 16, dtype=torch.bool)
    rgb[0, :, 4:9, 4:9] = 1.0  # saturated, masked
    usable[0, 4:9, 4:9] = False
    raw_h = _raw_h([(0, 0), (3, 0), (0, 3), (3, 3)])
    vis = visibility(usable, raw_h, (32, 32))
    assert vis[0, 12:14, 12:14].sum() == 0 and vis[0, :4, :4].min() == 1 and vis[1, :, -3:].max() == 0
    out = fuse_apertures(rgb, usable, raw_h, (32, 32), 0.0)
    np.testing.assert_allclose(out[0, :, 8:16, 8:16].numpy(), 0.7, atol=1e-5)
    np.testing.assert_allclose(out.numpy(), levels.view(4, 1, 1, 1).expand(4, 3, 32, 32).numpy(), atol=1e-4)


def test_fusion_in_chunks_of_rows_equals_one_piece(monkeypatch):
    rgb = torch.rand(4, 3, 40, 12)
    usable = torch.rand(4, 40, 12) > 0.05
    raw_h = _raw_h([(0, 0), (1, 0.5), (0.5, 1), (1, 1)])
    whole = fuse_apertures(rgb, usable, raw_h, (80, 24), 0.01)
    monkeypatch.setattr(fusion, "CHUNK_PIXELS", 24 * 7)  # 7 rows a chunk
    np.testing.assert_allclose(fuse_apertures(rgb, usable, raw_h, (80, 24), 0.01).numpy(), whole.numpy(), atol=1e-6)


def test_detail_noise_energy_matches_white_noise():
    """DETAIL_NOISE_ENERGY is the analyzers' detail energy of pure sensor noise per unit raw variance: four
    white-noise frames, Menon demosaicking and bicubic x2 resampling at four sub-pixel phases, as array-kr does."""
    from capssim.reconstruct.model.aperture_demosaic import demosaic_apertures

    sigma = 0.01
    raw = 0.5 + sigma * np.random.default_rng(0).standard_normal((4, 96, 96)).astype(np.float32)
    rgb = torch.from_numpy(demosaic_apertures(raw, bayer_method="menon2007"))
    raw_h = _raw_h([(0, 0), (1, 0), (0, 1), (1, 1)])
    for k in range(3):
        b = fusion._warp(rgb[:, k:k + 1], raw_h, (0, 192), 192, "bicubic", "border")[:, 0]
        d = b - b.mean(0)
        d -= fusion.gaussian(d, fusion.POL_SIGMA)
        energy = float((d * d).sum(0)[16:-16, 16:-16].mean()) / sigma ** 2
        assert energy == pytest.approx(fusion.DETAIL_NOISE_ENERGY, rel=0.1), k


def test_shared_intensity_energy_sees_intensity_edges_not_polarization_patterns():
    """An intensity edge seen by all four analyzers counts; detail that differs between the analyzer pairs (a
    polarization pattern's interpolation error: vertical stripes in one pair, horizontal in the other) or
    independent noise does not, while the energy of the four's mean (the previous rule) sees the stripes."""
    x = torch.arange(48, dtype=torch.float32)
    edge = (x[None, :] > 24).float().expand(48, 48) * 0.4 + 0.3
    assert fusion.shared_intensity_energy(edge.expand(4, 48, 48))[:, 20:28].mean() > 1e-3
    vertical = 0.1 * torch.sign(torch.sin(x[None, :] * 1.3)).expand(48, 48)
    pairs = torch.stack([0.5 + vertical, 0.5 + vertical.T, 0.5 + vertical, 0.5 + vertical.T])
    m = pairs.mean(0)
    mean_energy = fusion.gaussian((m - fusion.gaussian(m, fusion.POL_SIGMA)) ** 2, fusion.ENERGY_SIGMA)
    shared = fusion.shared_intensity_energy(pairs)
    assert float(shared[8:-8, 8:-8].mean()) < 0.1 * float(mean_energy[8:-8, 8:-8].mean())
    noise = 0.5 + 0.01 * torch.randn(4, 48, 48, generator=torch.Generator().manual_seed(0))
    assert float(fusion.shared_intensity_energy(noise).mean()) < 0.2 * 0.01 ** 2


def test_detail_weight_keeps_polarization_only_structure_and_drops_noise():
    """On a flat intensity with polarization stripes well above the noise, the fused analyzers keep the stripes
    (w near 1); on pure noise the detail is dropped (the output's detail energy far below the input's)."""
    x = torch.arange(24, dtype=torch.float32)
    stripes = 0.1 * torch.sign(torch.sin(x[None, :] * 0.9)).expand(24, 24)
    levels = torch.stack([0.5 + stripes, torch.full_like(stripes, 0.5), 0.5 - stripes, torch.full_like(stripes, 0.5)])
    rgb = levels[:, None].expand(4, 3, 24, 24).contiguous()
    usable = torch.ones(4, 24, 24, dtype=torch.bool)
    raw_h = _raw_h([(0, 0)] * 4)
    out = fuse_apertures(rgb, usable, raw_h, (48, 48), 0.005)
    ref = fuse_apertures(rgb, usable, raw_h, (48, 48), 0.005, detail=False)
    truth = fusion._warp(rgb, raw_h, (0, 48), 48, "bicubic", "border")
    assert (out - truth).abs()[..., 8:-8, 8:-8].mean() < 0.2 * (ref - truth).abs()[..., 8:-8, 8:-8].mean()
    flat = 0.5 + 0.01 * torch.randn(4, 3, 24, 24, generator=torch.Generator().manual_seed(1))
    noisy = fuse_apertures(flat, usable, raw_h, (48, 48), 0.01)
    warped = fusion._warp(flat, raw_h, (0, 48), 48, "bicubic", "border")
    def detail(a):
        return float(((a - a.mean(0)) ** 2)[..., 8:-8, 8:-8].mean())
    assert detail(noisy) < 0.3 * detail(warped)


@pytest.mark.parametrize("raw_hw", [(1, 1), (3, 5), (7, 2)])
def test_fusion_on_odd_and_tiny_frames(raw_hw):
    rgb = torch.rand(4, 3, *raw_hw)
    hr = (2 * raw_hw[0], 2 * raw_hw[1])
    out = fuse_apertures(rgb, torch.ones(4, *raw_hw, dtype=torch.bool), _raw_h([(0, 0)] * 4), hr, 0.01)
    assert out.shape == (4, 3, *hr) and torch.isfinite(out).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(smooth_capture):
    capture, _ = smooth_capture
    cpu, _ = reconstruct(capture, "array-kr", true_warps=True, device="cpu")
    gpu, _ = reconstruct(capture, "array-kr", true_warps=True, device="cuda")
    np.testing.assert_allclose(gpu.image, cpu.image, atol=2e-4)


def test_array_kr_as_caps_plus_start_is_the_fast_methods_image(smooth_capture):
    """``-p init=array-kr`` (issue 58): with no iteration, caps-plus returns its start, which is array-kr's image."""
    capture, _ = smooth_capture
    fast, _ = reconstruct(capture, "array-kr", true_warps=True, physical_projection=False)
    started, record = reconstruct(capture, "caps-plus", true_warps=True, init="array-kr", iterations=0,
                                  physical_projection=False)  # the two mark other pixels unobserved
    assert record["params"]["init"] == "array-kr"
    assert np.allclose(started.image, fast.image, atol=1e-5)
