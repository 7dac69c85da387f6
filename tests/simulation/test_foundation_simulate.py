"""simulate: reproducibility, the model checked by an independent implementation, errors, atomicity."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage
from support.fuzz import run_main

from capssim.camera.homography import random_aperture_homographies
from capssim.camera.sensor import GaussianSensor, NoNoiseSensor, make_sensor
from capssim.captures.capture import list_reconstructions, read_capture, write_capture, write_reconstruction
from capssim.conventions import bayer_channel_map, dofp_channel_map
from capssim.errors import CaptureFormatError, InputError
from capssim.files.imageio import read_gt_scene
from capssim.operators.measurement import CameraArrayMeasurement, seed_streams
from capssim.simulate import PoseRanges, prepare_ground_truth, simulate_capture

CLI = [sys.executable, "-m", "capssim.cli.__main__"]


def _write_png_scene(folder: Path, gt12: np.ndarray, bits: int = 8) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    scale = 2**bits - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    for p, angle in enumerate((0, 45, 90, 135)):
        rgb = np.round(np.clip(gt12[3 * p:3 * p + 3], 0, 1) * scale).astype(dtype).transpose(1, 2, 0)
        cv2.imwrite(str(folder / f"{angle}.png"), rgb[..., ::-1])
    return folder


def _by_hand_raw(gt: np.ndarray, meta: dict) -> np.ndarray:
    """An independent implementation (scipy) of the documented model, from meta.json alone."""
    from capssim.camera.psf import gaussian_psf_kernel

    hh, ww = gt.shape[1:]
    kernel = gaussian_psf_kernel(meta["psf"]["sigma_hr_px"])
    rows, cols = np.meshgrid(np.arange(hh, dtype=float), np.arange(ww, dtype=float), indexing="ij")
    raws = []
    for n, h in enumerate(np.asarray(meta["aperture_homographies"])):
        src = np.linalg.inv(h) @ np.stack([cols.ravel(), rows.ravel(), np.ones(cols.size)])
        sx = np.clip(src[0] / src[2], 0, ww - 1).reshape(hh, ww)
        sy = np.clip(src[1] / src[2], 0, hh - 1).reshape(hh, ww)
        rgb = []
        for k in range(3):
            warped = ndimage.map_coordinates(gt[3 * n + k].astype(np.float64), [sy, sx], order=1, mode="nearest")
            blurred = ndimage.correlate(warped, kernel, mode="nearest")
            rgb.append(blurred.reshape(hh // 2, 2, ww // 2, 2).mean(axis=(1, 3)))
        rgb = np.stack(rgb)
        cmap = bayer_channel_map(hh // 2, ww // 2)
        raws.append(np.take_along_axis(rgb, cmap[None], axis=0)[0])
    return np.stack(raws)


def test_noise_free_capture_reproduced_by_hand(smooth_random_scene, tmp_path):
    gt = smooth_random_scene(48, seed=4)
    cap = simulate_capture(gt, NoNoiseSensor(), seed=7, pose_ranges=PoseRanges(2.0, 1.0, 0.01))
    write_capture(tmp_path / "cap", cap)
    back = read_capture(tmp_path / "cap")
    np.testing.assert_allclose(back.caps_raw, _by_hand_raw(back.gt, back.meta), atol=2e-6)
    # reference aperture R = 2x2 box of the PSF-blurred GT red channel at 0 deg
    from capssim.camera.psf import gaussian_psf_kernel

    red = ndimage.correlate(back.gt[0].astype(np.float64), gaussian_psf_kernel(0.5), mode="nearest")
    box = red.reshape(24, 2, 24, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(back.caps_raw[0, 0::2, 0::2], box[0::2, 0::2], atol=2e-6)
    # DoFP: the blurred GT sampled by the layout
    blurred = np.stack([ndimage.correlate(c.astype(np.float64), gaussian_psf_kernel(0.5), mode="nearest") for c in back.gt])
    dofp = np.take_along_axis(blurred, dofp_channel_map(48, 48, "sony")[None], axis=0)[0]
    np.testing.assert_allclose(back.dofp_raw, dofp, atol=2e-6)


def test_seeded_simulation_is_byte_reproducible(smooth_random_scene, tmp_path):
    gt = smooth_random_scene(32, seed=1)
    sensor = make_sensor("poisson-gaussian", preset="python1300")
    paths = []
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        write_capture(tmp_path / name, simulate_capture(gt, sensor, seed=seed))
        paths.append(tmp_path / name)
    def digest(p):
        return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(p.iterdir())}
    assert digest(paths[0]) == digest(paths[1])
    assert digest(paths[0])["caps_raw.tiff"] != digest(paths[2])["caps_raw.tiff"]


def test_noisy_capture_is_uint16_and_decodes(smooth_random_scene, tmp_path):
    gt = smooth_random_scene(32, seed=2)
    cap = simulate_capture(gt, GaussianSensor(sigma=0.01), seed=0)
    write_capture(tmp_path / "cap", cap)
    back = read_capture(tmp_path / "cap")
    assert back.caps_raw.dtype == np.uint16 and back.dofp_raw.dtype == np.uint16
    clean = simulate_capture(gt, NoNoiseSensor(), seed=0)
    resid = back.caps_float() - clean.caps_raw
    assert abs(resid.std() - 0.01) < 0.001
    lr, sat = back.lr_images()
    assert lr.shape == (16, 8, 8) and sat.dtype == bool


def test_seed_streams_are_the_spawned_seed_sequence():
    expected = [np.random.default_rng(s) for s in np.random.SeedSequence(11).spawn(3)]
    for stream, reference in zip(seed_streams(11), expected):
        assert np.array_equal(stream.random(5), reference.random(5))


def test_simulate_is_the_camera_array_measurement(smooth_random_scene):
    """simulate_capture's raw frames are y = sensor(A x) of the measurement object with the same seed."""
    gt = smooth_random_scene(32, seed=4)
    homographies, _ = random_aperture_homographies(np.random.default_rng(1), (32, 32), shift_max_px=1.5,
                                                   rotation_max_deg=0.5, scale_max=0.005)
    sensor = GaussianSensor(sigma=0.01)
    cap = simulate_capture(gt, sensor, seed=3, aperture_homographies=homographies, extinction_ratio=50.0)
    measurement = CameraArrayMeasurement(sensor, seed=3, extinction_ratio=50.0)
    caps, dofp = measurement.measure(gt, homographies)
    assert np.array_equal(caps, cap.caps_raw) and np.array_equal(dofp, cap.dofp_raw)
    assert cap.meta["psf"] == measurement.psf.to_spec()


def test_gt_reading_8_and_16_bit_and_errors(smooth_random_scene, tmp_path):
    gt = smooth_random_scene(32, seed=0)
    g8, info8 = read_gt_scene(_write_png_scene(tmp_path / "s8", gt, 8))
    g16, info16 = read_gt_scene(_write_png_scene(tmp_path / "s16", gt, 16))
    assert info8["bit_depth"] == 8 and info16["bit_depth"] == 16
    assert np.abs(g8 - gt).max() <= 0.5 / 255 + 1e-6 and np.abs(g16 - gt).max() <= 0.5 / 65535 + 1e-6
    # mixed bit depths
    mixed = _write_png_scene(tmp_path / "mixed", gt, 8)
    cv2.imwrite(str(mixed / "90.png"), (np.ones((32, 32, 3)) * 1000).astype(np.uint16))
    with pytest.raises(InputError, match="bit depth"):
        read_gt_scene(mixed)
    # mismatched sizes
    sizes = _write_png_scene(tmp_path / "sizes", gt, 8)
    cv2.imwrite(str(sizes / "45.png"), np.zeros((16, 32, 3), np.uint8))
    with pytest.raises(InputError, match="different sizes"):
        read_gt_scene(sizes)
    # unreadable file
    bad = _write_png_scene(tmp_path / "bad", gt, 8)
    (bad / "135.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="unreadable"):
        read_gt_scene(bad)
    # missing file
    (bad / "135.png").unlink()
    with pytest.raises(InputError, match="135.png"):
        read_gt_scene(bad)
    # 12-channel TIFF, both layouts
    import tifffile

    tifffile.imwrite(tmp_path / "g.tiff", gt)
    tifffile.imwrite(tmp_path / "g_hwc.tiff", np.moveaxis(gt, 0, 2).copy())
    np.testing.assert_array_equal(read_gt_scene(tmp_path / "g.tiff")[0], gt)
    np.testing.assert_array_equal(read_gt_scene(tmp_path / "g_hwc.tiff")[0], gt)
    tifffile.imwrite(tmp_path / "g5.tiff", gt[:5])
    with pytest.raises(InputError, match="12-channel"):
        read_gt_scene(tmp_path / "g5.tiff")


def test_sizes_odd_and_crop_rules(smooth_random_scene):
    gt = smooth_random_scene(40, seed=0)
    odd = gt[:, :38, :37]
    trimmed, info = prepare_ground_truth(odd)
    assert trimmed.shape == (12, 36, 36) and info["trimmed_to"] == [36, 36]
    with pytest.raises(InputError, match="multiple of 4"):
        prepare_ground_truth(gt, crop=30)
    with pytest.raises(InputError, match="at most"):
        prepare_ground_truth(gt, crop=44)
    with pytest.raises(InputError, match="at least"):
        prepare_ground_truth(gt[:, :12, :12])
    bad = gt.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        prepare_ground_truth(bad)


def test_capture_round_trip_and_corruption(smooth_random_scene, tmp_path):
    cap = simulate_capture(smooth_random_scene(32), NoNoiseSensor(), seed=0)
    path = write_capture(tmp_path / "cap", cap)
    with pytest.raises(InputError, match="--overwrite"):
        write_capture(path, cap)
    write_capture(path, cap, overwrite=True)
    back = read_capture(path)
    assert np.array_equal(back.caps_raw, cap.caps_raw) and back.meta == json.loads(json.dumps(cap.meta))
    # recon outputs
    write_reconstruction(path, "dummy", np.zeros((12, 32, 32), np.float32), {"wall_time_s": 0.0})
    assert list_reconstructions(path) == ["dummy"]
    with pytest.raises(InputError, match="NaN"):
        write_reconstruction(path, "nan", np.full((12, 32, 32), np.nan, np.float32), {})
    # corruptions
    meta = json.loads((path / "meta.json").read_text())
    (path / "meta.json").write_text("{ not json")
    with pytest.raises(CaptureFormatError, match="corrupt JSON"):
        read_capture(path)
    meta["schema_version"] = 99
    (path / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(CaptureFormatError, match="schema_version"):
        read_capture(path)
    meta["schema_version"] = 1
    (path / "meta.json").write_text(json.dumps(meta))
    (path / "gt.tiff").unlink()
    assert read_capture(path).gt is None
    with pytest.raises(CaptureFormatError, match="gt.tiff"):
        read_capture(path, require_gt=True)
    (path / "caps_raw.tiff").write_bytes(b"garbage")
    with pytest.raises(InputError, match="unreadable TIFF"):
        read_capture(path)
    with pytest.raises(InputError, match="existing capture folder"):
        read_capture(tmp_path / "nowhere")


def test_failed_write_leaves_nothing_behind(smooth_random_scene, tmp_path, monkeypatch):
    cap = simulate_capture(smooth_random_scene(32), NoNoiseSensor(), seed=0)
    import capssim.captures.capture as capture_mod

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(capture_mod, "atomic_write_json", boom)
    with pytest.raises(RuntimeError):
        write_capture(tmp_path / "cap", cap)
    assert list(tmp_path.iterdir()) == []


def test_cli_simulate_and_design(smooth_random_scene, tmp_path, capsys, monkeypatch):
    scene = _write_png_scene(tmp_path / "scene", smooth_random_scene(40, seed=3))
    out = tmp_path / "cap"
    r = subprocess.run(CLI + ["simulate", str(scene), "-o", str(out), "--crop", "32", "--noise", "gaussian",
                              "--sigma", "0.02"], capture_output=True, text=True)  # the console command itself
    assert r.returncode == 0, r.stderr
    assert read_capture(out).meta["source"]["crop"] == 32

    def run(*args):  # the same entry point in this process: no second start-up (torch's import) per command
        return run_main(list(args), capsys, monkeypatch)

    code, _, err = run("simulate", scene, "-o", out)
    assert code == 2 and "--overwrite" in err
    code, _, err = run("simulate", scene, "-o", tmp_path / "x", "--noise", "poisson-gaussian", "--sensor", "nikon")
    assert code == 2 and "imx250myr" in err
    assert not (tmp_path / "x").exists()
    code, text, _ = run("design")
    assert code in (0, None) and "8.67" in text
    d = json.loads(run("design", "--json")[1])
    assert round(d["diffraction_to_nyquist_ratio"], 1) == 8.7 and d["r_sr"] == 2.0


def test_shared_kettle_simulate_done_when(shared_data, tmp_path):
    out = tmp_path / "kettle"
    r = subprocess.run(CLI + ["simulate", str(shared_data / "gt" / "qiu-kettle"), "-o", str(out),
                              "--crop", "256", "--noise", "none", "--seed", "0"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    cap = read_capture(out)
    assert cap.gt.shape == (12, 256, 256) and cap.caps_raw.shape == (4, 128, 128)
    np.testing.assert_allclose(cap.caps_raw, _by_hand_raw(cap.gt, cap.meta), atol=2e-6)
