"""Imperfect rigs on the simulation path: simulate_capture(rig=), meta.json["rig"], Capture.rig, the
simulate CLI flags and the dataset-config form (issue 22, item 1)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.homography import random_aperture_homographies
from capssim.camera.rig import RigModel, write_rig_json
from capssim.camera.sensor import GaussianSensor, NoNoiseSensor
from capssim.captures.capture import CaptureFormatError, read_capture, write_capture
from capssim.cli import app
from capssim.conventions import BAYER_OFFSETS, BAYER_SITE_COLOUR, POLARIZER_ANGLES_DEG
from capssim.errors import InputError
from capssim.files.imageio import write_tiff
from capssim.operators.measurement import CameraArrayMeasurement
from capssim.simulate import simulate_capture

torch.set_num_threads(1)
HR = 32
IDENTITY = np.tile(np.eye(3), (4, 1, 1))


def textured(seed: int = 0, size: int = HR) -> np.ndarray:
    """A physically consistent (12, size, size) image: random S0, DoLP and AoP per pixel, per colour."""
    rng = np.random.default_rng(seed)
    s0 = rng.uniform(0.2, 0.8, (3, size, size))
    dolp, aop = rng.uniform(0, 1, (3, size, size)), rng.uniform(0, math.pi, (3, size, size))
    return np.concatenate([0.5 * s0 * (1 + dolp * np.cos(2 * (aop - math.radians(a)))) for a in POLARIZER_ANGLES_DEG]
                          ).astype(np.float32)


def polarized_field(phi_deg: float, level=(0.6, 0.5, 0.4), size: int = HR) -> np.ndarray:
    """Uniform fully linearly polarized light at ``phi_deg``: ``I(a) = L_k cos^2(phi - a)``."""
    return np.stack([np.full((size, size), lk * math.cos(math.radians(phi_deg - a)) ** 2)
                     for a in POLARIZER_ANGLES_DEG for lk in level]).astype(np.float64)


def site_values(raw: np.ndarray, margin: int = 3) -> np.ndarray:
    """``(4, 4)`` [aperture, Bayer site q]: the interior values of a uniform raw frame (checked uniform)."""
    out = np.empty((4, 4))
    for q, (r, c) in enumerate(BAYER_OFFSETS):
        block = raw[:, r::2, c::2][:, margin:-margin, margin:-margin]
        assert np.ptp(block, axis=(1, 2)).max() < 1e-9
        out[:, q] = block.mean(axis=(1, 2))
    return out


def test_ideal_rig_reproduces_todays_capture_bit_for_bit():
    gt, sensor = textured(1), GaussianSensor(sigma=0.01, bit_depth=12)
    today = simulate_capture(gt, sensor, seed=5, extinction_ratio=200.0)
    ideal = simulate_capture(gt, sensor, seed=5, extinction_ratio=200.0, rig=RigModel.ideal())
    assert np.array_equal(today.caps_raw, ideal.caps_raw) and np.array_equal(today.dofp_raw, ideal.dofp_raw)
    assert json.dumps(today.meta, sort_keys=True, default=str) == json.dumps(ideal.meta, sort_keys=True, default=str)
    assert "rig" not in ideal.meta and ideal.rig is None


def test_gain_only_rig_scales_the_caps_irradiance_exactly_and_leaves_dofp_alone():
    gt = textured(2).astype(np.float64)
    gain = np.array([1.05, 0.95, 1.0, 1.02])
    ideal = CameraArrayMeasurement(NoNoiseSensor())
    rigged = CameraArrayMeasurement(NoNoiseSensor(), rig=RigModel().with_overrides(gain=gain))
    h, _ = random_aperture_homographies(np.random.default_rng(0), (HR, HR))
    caps0, dofp0 = ideal.irradiance(gt, h)
    caps1, dofp1 = rigged.irradiance(gt, h)
    assert np.array_equal(caps1, caps0 * gain[:, None, None])
    assert np.array_equal(dofp1, dofp0)


@pytest.mark.parametrize("phi", [0.0, 17.0, 60.0, 122.5])
def test_angle_offsets_follow_malus_law(phi):
    offsets = np.array([1.5, -2.0, 0.7, -1.2])
    rig = RigModel().with_overrides(angle_offsets_deg=offsets)
    level = (0.6, 0.5, 0.4)
    caps, _ = CameraArrayMeasurement(NoNoiseSensor(), rig=rig).irradiance(polarized_field(phi, level), IDENTITY)
    values = site_values(caps)
    for n, nominal in enumerate(POLARIZER_ANGLES_DEG):
        malus = math.cos(math.radians(phi - nominal - offsets[n])) ** 2
        for q in range(4):
            assert values[n, q] == pytest.approx(level[BAYER_SITE_COLOUR[q]] * malus, abs=1e-12)
    # the ideal array reads the nominal angle: the offsets are what changed the values
    ideal, _ = CameraArrayMeasurement(NoNoiseSensor()).irradiance(polarized_field(phi, level), IDENTITY)
    assert not np.allclose(site_values(ideal), values, atol=1e-4)


def test_extinction_ratio_per_aperture_and_colour():
    er = np.array([[300.0, 200.0, 50.0], [250.0, 150.0, 40.0], [100.0, 90.0, 30.0], [1000.0, 500.0, 60.0]])
    rig = RigModel().with_overrides(extinction_ratio=er.ravel())
    level = (0.6, 0.5, 0.4)
    measurement = CameraArrayMeasurement(NoNoiseSensor(), rig=rig)
    for n, nominal in enumerate(POLARIZER_ANGLES_DEG):
        for phi, expected in ((nominal, er[n] / (er[n] + 1)), (nominal + 90.0, 1 / (er[n] + 1))):
            caps, _ = measurement.irradiance(polarized_field(phi, level), IDENTITY)
            values = site_values(caps)
            for q in range(4):
                k = BAYER_SITE_COLOUR[q]
                assert values[n, q] == pytest.approx(level[k] * expected[k], rel=1e-10)


def test_meta_json_round_trip_of_the_true_rig(tmp_path):
    rig = RigModel.preset("realistic", seed=3)
    cap = simulate_capture(textured(3), NoNoiseSensor(), seed=1, rig=rig)
    assert cap.meta["rig"] == rig.to_dict()
    back = read_capture(write_capture(tmp_path / "cap", cap))
    assert back.rig.to_dict() == rig.to_dict()
    assert np.array_equal(back.rig.analyzer_matrix(), rig.analyzer_matrix())
    assert np.array_equal(back.rig.flat_field((HR // 2, HR // 2)), rig.flat_field((HR // 2, HR // 2)))
    meta = json.loads((tmp_path / "cap" / "meta.json").read_text())
    meta["rig"]["gain"] = [1.0, 2.0]
    (tmp_path / "cap" / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(CaptureFormatError, match="meta.json rig.*gain"):
        read_capture(tmp_path / "cap")


def test_explicit_homographies_are_kept_with_a_rig():
    geometry = simulate_capture(textured(4), NoNoiseSensor(), seed=9).aperture_homographies()
    rig = RigModel.preset("realistic", seed=1)
    a = simulate_capture(textured(4), NoNoiseSensor(), seed=2, rig=rig, aperture_homographies=geometry)
    b = simulate_capture(polarized_field(30.0).astype(np.float32), NoNoiseSensor(), seed=3, rig=rig,
                         aperture_homographies=geometry)
    assert np.array_equal(a.aperture_homographies(), geometry) and np.array_equal(b.aperture_homographies(), geometry)
    model = CameraArrayMeasurement(NoNoiseSensor(), rig=rig).irradiance(textured(4).astype(np.float64), geometry)[0]
    assert np.allclose(a.caps_raw, model, atol=1e-6)


# -- the command line ---------------------------------------------------------------------------------
@pytest.fixture
def gt_file(tmp_path):
    path = tmp_path / "gt.tiff"
    write_tiff(path, textured(5))
    return path


def test_cli_rig_preset_and_overrides(tmp_path, gt_file):
    runner = CliRunner()
    res = runner.invoke(app, ["simulate", str(gt_file), "-o", str(tmp_path / "a"), "--rig", "realistic",
                              "--rig-seed", "4"])
    assert res.exit_code == 0, res.output
    assert read_capture(tmp_path / "a").rig.to_dict() == RigModel.preset("realistic", seed=4).to_dict()
    res = runner.invoke(app, ["simulate", str(gt_file), "-o", str(tmp_path / "b"),
                              "--angle-offsets", "1,-1,0.5,0", "--extinction-ratios", "300,100,30",
                              "--gains", "1.05,0.95,1,1", "--vignetting", "0.2", "--aperture-psf-sigmas",
                              "0.4,0.5,0.6,0.5"])
    assert res.exit_code == 0, res.output
    rig = read_capture(tmp_path / "b").rig
    assert np.array_equal(rig.angle_offsets_deg, [1, -1, 0.5, 0]) and np.array_equal(rig.gain, [1.05, 0.95, 1, 1])
    assert np.array_equal(rig.extinction_ratio, np.tile([300.0, 100.0, 30.0], (4, 1)))
    assert [p["sigma_hr_px"] for p in rig.psf] == [0.4, 0.5, 0.6, 0.5]
    corner = rig.flat_field((HR // 2, HR // 2))[:, 0, 0]
    assert np.allclose(corner, 0.8 * rig.gain, atol=0.01)
    # the one --extinction-ratio stays the CAPS polarizers' on the ideal array with overrides
    res = runner.invoke(app, ["simulate", str(gt_file), "-o", str(tmp_path / "c"), "--extinction-ratio",
                              "80", "--gains", "1.05,0.95,1,1"])
    assert res.exit_code == 0, res.output
    assert np.array_equal(read_capture(tmp_path / "c").rig.extinction_ratio, np.full((4, 3), 80.0))


def test_cli_rig_file_gives_its_geometry(tmp_path, gt_file):
    geometry = ArrayGeometry(simulate_capture(textured(5), NoNoiseSensor(), seed=7).aperture_homographies(), (HR, HR))
    rig = RigModel.preset("realistic", seed=6)
    write_rig_json(tmp_path / "rig.json", rig, geometry=geometry)
    res = CliRunner().invoke(app, ["simulate", str(gt_file), "-o", str(tmp_path / "a"), "--rig",
                                   str(tmp_path / "rig.json"), "--gains", "1,1,1,1.1"])
    assert res.exit_code == 0, res.output
    cap = read_capture(tmp_path / "a")
    assert np.allclose(cap.aperture_homographies(), geometry.aperture_homographies)
    assert np.array_equal(cap.rig.gain, [1, 1, 1, 1.1]) and np.array_equal(cap.rig.angle_offsets_deg,
                                                                            rig.angle_offsets_deg)
    write_rig_json(tmp_path / "big.json", rig, geometry=ArrayGeometry(geometry.aperture_homographies, (64, 64)))
    res = CliRunner().invoke(app, ["simulate", str(gt_file), "-o", str(tmp_path / "b"), "--rig",
                                   str(tmp_path / "big.json")])
    assert isinstance(res.exception, InputError) and res.exception.argument == "--rig"
    assert "64x64" in str(res.exception)


@pytest.mark.parametrize("flags, named", [
    (["--rig", "perfect"], "--rig"),
    (["--rig", "missing.json"], "--rig"),
    (["--rig-seed", "-1"], "--rig-seed"),
    (["--angle-offsets", "1,2,3"], "--angle-offsets"),
    (["--angle-offsets", "30,0,0,0"], "--angle-offsets"),
    (["--extinction-ratios", "100,50"], "--extinction-ratios"),
    (["--extinction-ratios", "0.5"], "--extinction-ratios"),
    (["--gains", "a,b,c,d"], "--gains"),
    (["--gains", "1,1,1,0"], "--gains"),
    (["--vignetting", "1.5"], "--vignetting"),
    (["--aperture-psf-sigmas", "0.5,0.5,0.5,-1"], "--aperture-psf-sigmas"),
    (["--aperture-psf-sigmas", "0.5,0.5,0.5,40"], "--aperture-psf-sigmas"),
])
def test_cli_bad_rig_values_name_their_flag(tmp_path, gt_file, flags, named):
    """An InputError naming the flag: ``capssim`` (cli.main) prints it as one line, no traceback."""
    res = CliRunner().invoke(app, ["simulate", str(gt_file), "-o", str(tmp_path / "x"), *flags])
    assert res.exit_code != 0
    assert isinstance(res.exception, InputError) and res.exception.argument == named, repr(res.exception)
    assert not (tmp_path / "x").exists()


def test_cli_bad_rig_value_is_one_line_without_traceback(tmp_path, gt_file):
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "capssim", "simulate", str(gt_file), "-o",
                          str(tmp_path / "x"), "--gains", "1,1"], capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "--gains" in run.stderr + run.stdout
    assert "Traceback" not in run.stderr + run.stdout


# -- the dataset config -------------------------------------------------------------------------------
def _config(tmp_path, rig_text: str) -> str:
    write_tiff(tmp_path / "gt.tiff", textured(6))
    text = f"seed: 1\nsamples: 2\ndefaults: {{rig: {rig_text}}}\nsources: [{{gt: gt.tiff, size: {HR}}}]\n"
    (tmp_path / "ds.yaml").write_text(text)
    return tmp_path / "ds.yaml"


def test_dataset_config_rig_reaches_the_sample(tmp_path):
    from capssim.dataset.config import load_config
    from capssim.dataset.sample import build_capture, check_sample

    config = load_config(_config(tmp_path, "{preset: ideal, angle_offsets_deg: [{uniform: [-2, 2]}, 0, 1, -1], "
                                           "extinction_ratio: [300, 200, 50], gain: [1.05, 0.95, 1, 1], "
                                           "vignetting_corner: 0.2, psf_sigmas_hr_px: [0.4, 0.5, 0.6, 0.5]}"))
    spec = config.sample_spec(1)
    check_sample(spec)
    capture = build_capture(spec)[0]
    rig = capture.rig
    assert -2 <= rig.angle_offsets_deg[0] <= 2 and np.array_equal(rig.angle_offsets_deg[1:], [0, 1, -1])
    assert np.array_equal(rig.extinction_ratio, np.tile([300.0, 200.0, 50.0], (4, 1)))
    assert np.array_equal(rig.gain, [1.05, 0.95, 1, 1]) and len(rig.psf) == 4
    assert config.sample_spec(1) == spec  # deterministic in (config, index)


@pytest.mark.parametrize("rig_text, key", [
    ("{gain: [1, 2]}", "defaults.rig.gain"),
    ("{extinction_ratio: [300, 1]}", "defaults.rig.extinction_ratio"),
    ("{extinction_ratio: 1}", "defaults.rig.extinction_ratio"),
    ("{angle_offsets_deg: [0, 0, 0, 45]}", "defaults.rig.angle_offsets_deg[3]"),
    ("{vignetting_corner: 2}", "defaults.rig.vignetting_corner"),
    ("{preset: perfect}", "defaults.rig.preset"),
    ("{gains: [1, 1, 1, 1]}", "defaults.rig.gains"),
])
def test_dataset_config_bad_rig_names_the_key(tmp_path, rig_text, key):
    from capssim.dataset.config import load_config

    with pytest.raises(InputError) as info:
        load_config(_config(tmp_path, rig_text)).sample_spec(0)
    assert key in str(info.value)
