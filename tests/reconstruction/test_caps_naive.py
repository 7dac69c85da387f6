"""``caps-naive`` and ``caps-sisr``: exactness, accuracy with true warps, CLI files, bad input, SR hook."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
import torch
import torch.nn.functional as F

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture
from capssim.errors import CapssimError, InputError, UnknownNameError
from capssim.reconstruct.registry import reconstruct
from capssim.simulate import simulate_capture


def _capture(gt, *, seed=0, psf=None, homographies=None):
    return simulate_capture(gt, make_sensor("none"), seed=seed, psf=psf or {"type": "none"},
                            aperture_homographies=homographies)


@pytest.fixture
def correlated_scene(smooth_random_scene):
    """Factory: ``(size, seed) -> (12, size, size)`` with correlated channels."""

    def _correlated_scene(size, seed):
        """A smooth scene whose colours share one texture (as in natural images; the colour-
        correlation priors of Menon/Malvar fail on independent per-colour textures)."""
        scene = smooth_random_scene(size, seed=seed).reshape(4, 3, size, size)
        gains = np.array([0.9, 1.0, 0.8], np.float32)[None, :, None, None]
        return (scene.mean(axis=1, keepdims=True) * gains).reshape(12, size, size)

    return _correlated_scene


def _psnr(a, b):
    return float(10 * np.log10(1.0 / max(np.mean((np.asarray(a, np.float64) - b) ** 2), 1e-30)))


@pytest.mark.parametrize("bayer", ["menon2007", "malvar2004", "bilinear", "ri"])
def test_constant_image_is_exact(bayer):
    gt = np.broadcast_to(np.linspace(0.2, 0.7, 12, dtype=np.float32)[:, None, None], (12, 32, 32)).copy()
    out, record = reconstruct(_capture(gt), "caps-naive", true_warps=True, bayer_method=bayer,
                              physical_projection=False)  # gt is not Stokes-consistent: test the method alone
    np.testing.assert_allclose(out.image, gt, atol=2e-6)
    assert record["params"]["bayer_method"] == bayer


def test_ri_demosaicking_is_accurate_on_tiny_and_smooth_frames(correlated_scene):
    """Residual interpolation (caps-iccp's default) through the shared padding: frames down to 2x2 keep their
    shape and a constant colour; on a smooth correlated scene it is as good as Menon 2007 (within 1 dB)."""
    from capssim.reconstruct.methods.caps_naive import demosaic_apertures

    for side in (2, 4, 10):
        raw = np.tile(np.array([[0.2, 0.5], [0.5, 0.8]], np.float32), (4, side // 2, side // 2))
        rgb = demosaic_apertures(raw, bayer_method="ri")
        assert rgb.shape == (4, 3, side, side)
        np.testing.assert_allclose(rgb, np.broadcast_to(np.array([0.2, 0.5, 0.8])[None, :, None, None], rgb.shape),
                                   atol=1e-6)
    gt = correlated_scene(64, seed=4).reshape(4, 3, 64, 64)[0]  # one aperture's RGB on the raw grid
    raw = gt[1].copy()
    raw[0::2, 0::2], raw[1::2, 1::2] = gt[0][0::2, 0::2], gt[2][1::2, 1::2]
    crop = (slice(None), slice(4, -4), slice(4, -4))
    scores = {m: _psnr(demosaic_apertures(raw[None], bayer_method=m)[0][crop], gt[crop]) for m in ("ri", "menon2007")}
    assert scores["ri"] > scores["menon2007"] - 1.0, scores


def test_smooth_scene_with_true_warps_is_accurate(correlated_scene):
    gt = correlated_scene(96, seed=3)
    capture = _capture(gt)
    out, record = reconstruct(capture, "caps-naive", true_warps=True)
    border = 8  # replicate border outside each aperture's field of view
    crop = (slice(None), slice(border, -border), slice(border, -border))
    psnr = _psnr(out.image[crop], gt[crop])
    assert psnr > 45.0, psnr
    # registration matters: ignoring the warps (all identity) must be clearly worse
    import copy

    from capssim.camera.array_geometry import ArrayGeometry

    shifted = copy.deepcopy(capture)
    identity = ArrayGeometry.identity(capture.hr_shape).to_meta()  # identity aperture warps
    shifted.meta["aperture_homographies"] = identity["aperture_homographies"]
    for entry, h in zip(shifted.meta["lr_images"], identity["lr_homographies"]):
        entry["homography"] = h
    wrong, _ = reconstruct(shifted, "caps-naive", true_warps=True)
    assert _psnr(wrong.image[crop], gt[crop]) < psnr - 3
    assert set(record["stages_s"]) >= {"demosaic", "registration", "resample"}


def test_reference_aperture_equals_bicubic_upsampling_of_demosaicked_frame(smooth_random_scene):
    from capssim.reconstruct.methods.caps_naive import demosaic_apertures

    gt = smooth_random_scene(64, seed=1)
    capture = _capture(gt)
    out, _ = reconstruct(capture, "caps-naive", true_warps=True, clip=False, physical_projection=False)
    rgb = torch.from_numpy(demosaic_apertures(capture.caps_float()))
    ref = F.interpolate(rgb[:1], scale_factor=2, mode="bicubic", align_corners=False)[0].numpy()
    np.testing.assert_allclose(out.image[:3], ref, atol=1e-5)


def test_cli_writes_tiff_and_json_with_timings(tmp_path, smooth_random_scene):
    from typer.testing import CliRunner

    from capssim.cli import app

    path = write_capture(tmp_path / "cap", _capture(smooth_random_scene(48, seed=2)))
    result = CliRunner().invoke(app, ["reconstruct", str(path), "-m", "caps-naive", "--true-warps",
                                      "--no-progress", "-p", "bayer_method=malvar2004"])
    assert result.exit_code == 0, result.output
    image = tifffile.imread(path / "recon" / "caps-naive.tiff")
    assert image.shape == (12, 48, 48) and image.dtype == np.float32
    record = json.loads((path / "recon" / "caps-naive.json").read_text())
    assert record["method"] == "caps-naive" and record["true_warps"] is True
    assert record["params"]["bayer_method"] == "malvar2004"
    assert record["wall_time_s"] > 0 and {"demosaic", "registration", "resample"} <= set(record["stages_s"])


def test_odd_sub_image_sizes_and_dark_input(smooth_random_scene):
    gt = smooth_random_scene(64, seed=4)[:, :20, :36] * 1e-4  # sub-images 5 x 9, nearly black
    out, _ = reconstruct(_capture(np.ascontiguousarray(gt)), "caps-naive", true_warps=True)
    assert out.image.shape == (12, 20, 36) and np.all(np.isfinite(out.image))
    zero, _ = reconstruct(_capture(np.zeros((12, 20, 36), np.float32)), "caps-naive", true_warps=True)
    assert np.all(zero.image == 0)


def test_bad_options_give_clear_errors(smooth_random_scene):
    capture = _capture(smooth_random_scene(32))
    with pytest.raises(UnknownNameError, match="menon2007"):
        reconstruct(capture, "caps-naive", true_warps=True, bayer_method="ahd")
    with pytest.raises(UnknownNameError, match="bayer_method"):
        reconstruct(capture, "caps-naive", true_warps=True, colour="x")
    with pytest.raises(InputError):
        reconstruct(capture, "caps-naive", true_warps=True, clip="maybe")
    out, _ = reconstruct(capture, "caps-naive", true_warps=True, iterations=5)  # a caps option: ignored
    assert out.image.shape == (12, 32, 32)


class _BicubicX2(torch.nn.Module):
    def forward(self, x):
        return F.interpolate(x, scale_factor=2.0, mode="bicubic", align_corners=False)


class _Wrong(torch.nn.Module):
    def forward(self, x):
        return x


def test_sisr_torchscript_model_matches_bicubic(tmp_path, smooth_random_scene):
    model = tmp_path / "bicubic_x2.pt"
    torch.jit.script(_BicubicX2()).save(str(model))
    capture = _capture(smooth_random_scene(64, seed=5))
    plain, rec_plain = reconstruct(capture, "caps-sisr", true_warps=True, model="bicubic")
    assert rec_plain["upsampler"] == "bicubic (no model)"
    for channels in ("1", "3"):
        hooked, rec = reconstruct(capture, "caps-sisr", true_warps=True, model=str(model), model_channels=channels)
        assert rec["upsampler"].startswith("torchscript:")
        np.testing.assert_allclose(hooked.image, plain.image, atol=1e-6)
    # the reference aperture is not re-warped (identity), so it matches caps-naive there
    naive, _ = reconstruct(capture, "caps-naive", true_warps=True, physical_projection=False)
    unprojected, _ = reconstruct(capture, "caps-sisr", true_warps=True, physical_projection=False, model="bicubic")
    np.testing.assert_allclose(unprojected.image[:3], naive.image[:3], atol=1e-5)
    assert _psnr(plain.image, capture.gt) > 30


def test_sisr_bad_models(tmp_path, smooth_random_scene):
    capture = _capture(smooth_random_scene(32))
    with pytest.raises(InputError, match="model"):
        reconstruct(capture, "caps-sisr", true_warps=True, model=str(tmp_path / "missing.pt"))
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a model")
    with pytest.raises(InputError, match="TorchScript"):
        reconstruct(capture, "caps-sisr", true_warps=True, model=str(junk))
    wrong = tmp_path / "wrong.pt"
    torch.jit.script(_Wrong()).save(str(wrong))
    with pytest.raises(CapssimError, match="x2 model must return"):
        reconstruct(capture, "caps-sisr", true_warps=True, model=str(wrong))
    onnx = tmp_path / "m.onnx"
    onnx.write_bytes(b"x")
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        with pytest.raises(CapssimError, match="onnxruntime"):
            reconstruct(capture, "caps-sisr", true_warps=True, model=str(onnx))
