"""Calibration captures (capssim.dataset.calibration_captures): each target's ground truth is what
the format says (docs: guides/calibration.md), the raw frames carry the rig's physics, a set
round-trips through read_capture, bad input is refused, and rendered uniform targets agree with
simulated ones."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from capssim.camera.rig import RigModel, read_rig_json
from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_capture
from capssim.dataset.calibration_captures import (
    FLAT_LEVEL,
    POLARIZER_LEVEL,
    STAR_CYCLES,
    make_calibration_captures,
    sweep_angles,
)
from capssim.errors import InputError

SIZE = 64
ANGLES = 4
#: raw pixels left out at each border: the warp and the PSF reach past the frame there
BORDER = 4
#: rendered against simulated uniform targets, per aperture and colour (raw, flat-corrected);
#: measured 7e-8 (llvm_ad_mono_polarized, 64 px, 16 spp): both go through the one camera model
RENDERED_TOLERANCE = 1e-4


@pytest.fixture(scope="module")
def rig() -> RigModel:
    return RigModel.preset("realistic", seed=5).with_overrides(angle_offsets_deg=[1.5, -2.0, 0.7, -0.4])


@pytest.fixture(scope="module")
def noiseless_set(tmp_path_factory, rig):
    out = tmp_path_factory.mktemp("cal") / "set"
    index = make_calibration_captures(out, rig=rig, size=SIZE, sensor=make_sensor("none"), polarizer_angles=ANGLES,
                                      seed=3)
    return out, index


def _channel_angles() -> np.ndarray:
    return np.repeat([0.0, 45.0, 90.0, 135.0], 3)


def _site_means(capture, rig: RigModel) -> np.ndarray:
    """``(4, 3)`` flat-corrected raw means per aperture and colour (R, G1+G2, B), borders left out."""
    raw = capture.caps_float() / rig.flat_field(capture.raw_shape)
    raw = raw[:, BORDER:-BORDER, BORDER:-BORDER]
    sites = [raw[:, 0::2, 0::2], np.concatenate([raw[:, 0::2, 1::2], raw[:, 1::2, 0::2]], axis=1), raw[:, 1::2, 1::2]]
    return np.stack([s.reshape(4, -1).mean(axis=1) for s in sites], axis=1)


def test_index_lists_every_target(noiseless_set):
    out, index = noiseless_set
    assert json.loads((out / "index.json").read_text()) == index
    targets = [c["target"] for c in index["captures"]]
    assert targets == ["flat"] + ["polarizer"] * ANGLES + ["geometry", "star"]
    phis = [c["polarizer_deg"] for c in index["captures"] if c["target"] == "polarizer"]
    assert np.allclose(phis, sweep_angles(ANGLES)) and np.allclose(np.diff(phis), 180.0 / ANGLES)
    assert np.abs(np.array(phis)[:, None] - [0, 45, 90, 135, 180]).min() > 1.0  # none on a nominal angle
    for c in index["captures"]:
        assert (out / c["folder"] / "meta.json").is_file()


def test_flat_ground_truth_is_the_level_in_every_channel(noiseless_set):
    out, _ = noiseless_set
    flat = read_capture(out / "flat")
    assert flat.meta["calibration"] == {"target": "flat", "level": FLAT_LEVEL}
    assert flat.gt.shape == (12, SIZE, SIZE) and np.all(flat.gt == np.float32(FLAT_LEVEL))


def test_polarizer_ground_truth_follows_malus(noiseless_set):
    out, index = noiseless_set
    for entry in (c for c in index["captures"] if c["target"] == "polarizer"):
        cap = read_capture(out / entry["folder"])
        phi, level = entry["polarizer_deg"], entry["level"]
        assert level == POLARIZER_LEVEL and cap.meta["calibration"]["polarizer_deg"] == phi
        expected = 2 * level * np.cos(np.radians(_channel_angles() - phi)) ** 2
        assert np.allclose(cap.gt, expected[:, None, None], atol=1e-6)
        s0 = cap.gt[0:3] + cap.gt[6:9]  # I0 + I90 = S0 for a linear state
        assert np.allclose(s0, 2 * level, atol=1e-6)


def test_raw_uniform_targets_carry_the_rig(noiseless_set, rig):
    """Flat-corrected raw means: L for the flat; L (1 + d cos 2(theta_n - phi)) through the rig's
    true angle theta_n and diattenuation d = (ER - 1) / (ER + 1) per colour for the sweep."""
    out, index = noiseless_set
    assert np.allclose(_site_means(read_capture(out / "flat"), rig), FLAT_LEVEL, atol=1e-5)
    theta = np.array([0.0, 45.0, 90.0, 135.0]) + rig.angle_offsets_deg
    er = np.asarray(rig.extinction_ratio, dtype=np.float64)
    d = np.where(np.isinf(er), 1.0, (er - 1.0) / (er + 1.0))
    for entry in (c for c in index["captures"] if c["target"] == "polarizer"):
        cap = read_capture(out / entry["folder"])
        expected = entry["level"] * (1 + d * np.cos(np.radians(2 * (theta[:, None] - entry["polarizer_deg"]))))
        assert np.allclose(_site_means(cap, rig), expected, atol=1e-5)
        assert cap.caps_float().max() < 0.98 and not cap.caps_saturated().any()


def test_star_has_its_cycles_about_its_centre(noiseless_set):
    out, _ = noiseless_set
    star = read_capture(out / "star")
    entry = star.meta["calibration"]
    assert entry["cycles"] == STAR_CYCLES and np.allclose(entry["center_rowcol"], [(SIZE - 1) / 2] * 2)
    assert np.allclose(star.gt, star.gt[:1])  # unpolarized, neutral
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] - np.reshape(entry["center_rowcol"], (2, 1, 1))
    ring = np.abs(np.hypot(yy, xx) - 0.35 * SIZE) < 1.0
    phi = np.arctan2(-yy[ring], xx[ring])
    residuals = {}
    for n in (STAR_CYCLES - 1, STAR_CYCLES, STAR_CYCLES + 1):
        basis = np.stack([np.ones_like(phi), np.cos(n * phi), np.sin(n * phi)], axis=1)
        coef, *_ = np.linalg.lstsq(basis, star.gt[0][ring], rcond=None)
        residuals[n] = np.sqrt(np.mean((basis @ coef - star.gt[0][ring]) ** 2))
        if n == STAR_CYCLES:
            assert np.hypot(coef[1], coef[2]) > 0.2 and abs(coef[2]) < 1e-4  # cos(N phi): phase 0
    assert residuals[STAR_CYCLES] < 1e-5 < min(residuals[STAR_CYCLES - 1], residuals[STAR_CYCLES + 1])


def test_geometry_target_is_textured_at_every_scale(noiseless_set):
    gt = read_capture(noiseless_set[0] / "geometry").gt.astype(np.float64)
    assert np.allclose(gt, gt[:1])  # unpolarized, neutral: every aperture sees the same pattern
    fine = gt[0] - gaussian_filter(gt[0], 1.0)
    coarse = gaussian_filter(gt[0], 6.0)
    assert fine.std() > 0.01 and coarse.std() > 0.02 and 0.0 < gt.min() and gt.max() < 0.9


def test_set_round_trips_with_one_rig_and_one_geometry(noiseless_set, rig):
    out, index = noiseless_set
    first = read_capture(out / "flat")
    for entry in index["captures"]:
        cap = read_capture(out / entry["folder"])
        assert cap.meta["calibration"] == {k: v for k, v in entry.items() if k != "folder"}
        assert np.array_equal(cap.aperture_homographies(), first.aperture_homographies())
        assert np.allclose(cap.rig.analyzer_matrix(), rig.analyzer_matrix())
        assert np.allclose(cap.rig.flat_field(cap.raw_shape), rig.flat_field(cap.raw_shape))
    truth = read_rig_json(out / "rig.json")
    assert np.allclose(truth.geometry.aperture_homographies, first.aperture_homographies())
    assert np.allclose(truth.rig.angle_offsets_deg, rig.angle_offsets_deg)


def test_given_homographies_are_used_everywhere(tmp_path, rig):
    h = np.stack([np.eye(3)] + [np.array([[1, 0, 0.7 * n], [0, 1, -0.4 * n], [0, 0, 1.0]]) for n in (1, 2, 3)])
    index = make_calibration_captures(tmp_path / "set", rig=rig, size=32, sensor=make_sensor("none"),
                                      polarizer_angles=3, aperture_homographies=h)
    for entry in index["captures"]:
        assert np.allclose(read_capture(tmp_path / "set" / entry["folder"]).aperture_homographies(), h)
    with pytest.raises(InputError, match="aperture_homographies"):
        make_calibration_captures(tmp_path / "bad", rig=rig, size=32, sensor=make_sensor("none"),
                                  aperture_homographies=np.eye(3))


def test_frames_repeat_the_uniform_targets_with_their_own_noise(tmp_path, rig):
    out = tmp_path / "set"
    index = make_calibration_captures(out, rig=rig, size=32, sensor=make_sensor("gaussian", sigma=0.01),
                                      polarizer_angles=3, frames=2)
    folders = [c["folder"] for c in index["captures"]]
    assert folders[:2] == ["flat", "flat-frame01"] and len(folders) == 2 * (1 + 3) + 2
    assert [c.get("frame") for c in index["captures"][:2]] == [0, 1]
    a, b = read_capture(out / "flat"), read_capture(out / "flat-frame01")
    assert np.array_equal(a.gt, b.gt) and not np.array_equal(a.caps_raw, b.caps_raw)
    # overwriting with one frame leaves no stale frame behind (calibrate reads every folder of OUT)
    make_calibration_captures(out, rig=rig, size=32, sensor=make_sensor("none"), polarizer_angles=3, overwrite=True)
    assert not any(p.name.endswith("-frame01") for p in out.iterdir())
    with pytest.raises(InputError, match="frames"):
        make_calibration_captures(tmp_path / "x", rig=rig, size=32, sensor=make_sensor("none"), frames=0)


@pytest.mark.parametrize("options, argument", [
    ({"polarizer_angles": 2}, "polarizer_angles"), ({"polarizer_angles": 4.5}, "polarizer_angles"),
    ({"size": 30}, "size"), ({"size": 16}, "size"), ({"renderer": "blender"}, "renderer"),
])
def test_bad_options_are_refused(tmp_path, rig, options, argument):
    with pytest.raises(InputError) as info:
        make_calibration_captures(tmp_path / "set", rig=rig, sensor=make_sensor("none"), **{"size": 32, **options})
    assert info.value.argument == argument and not (tmp_path / "set").exists()


def test_existing_output_needs_overwrite(noiseless_set, rig):
    with pytest.raises(InputError, match="overwrite"):
        make_calibration_captures(noiseless_set[0], rig=rig, size=32, sensor=make_sensor("none"))


def test_cli_makes_a_set_and_refuses_bad_input(tmp_path):
    from typer.testing import CliRunner

    from capssim.cli import app

    runner = CliRunner()
    good = runner.invoke(app, ["calibration-captures", "-o", str(tmp_path / "set"), "--size", "32", "--rig", "realistic",
                               "--rig-seed", "4", "--polarizer-angles", "3", "--noise", "gaussian", "--sigma", "0.01",
                               "--seed", "2"])
    assert good.exit_code == 0, good.output
    index = json.loads((tmp_path / "set" / "index.json").read_text())
    assert [c["target"] for c in index["captures"]].count("polarizer") == 3
    cap = read_capture(tmp_path / "set" / "flat")
    assert cap.meta["sensor"]["model"] == "gaussian" and cap.meta["sensor"]["sigma"] == 0.01
    assert np.allclose(cap.rig.gain, RigModel.preset("realistic", seed=4).gain)
    listed = runner.invoke(app, ["calibration-captures", "-o", str(tmp_path / "set2"), "--size", "32", "--frames", "2",
                                 "--polarizer-angles", "3", "--json"])
    assert listed.exit_code == 0, listed.output
    index = json.loads(listed.stdout)
    assert index == json.loads((tmp_path / "set2" / "index.json").read_text()) and len(index["captures"]) == 10
    for args, flag in ((["--polarizer-angles", "2"], "--polarizer-angles"), (["--size", "30"], "--size"),
                       (["--renderer", "blender"], "--renderer"), (["--frames", "9"], "--frames")):
        bad = runner.invoke(app, ["calibration-captures", "-o", str(tmp_path / "bad"), *args])
        assert bad.exit_code != 0 and isinstance(bad.exception, InputError) and flag in str(bad.exception)
    # the console entry point: one line, no traceback
    run = subprocess.run([sys.executable, "-m", "capssim", "calibration-captures", "-o", str(tmp_path / "set"),
                          "--size", "32"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "Traceback" not in run.stderr and "overwrite" in run.stderr


def test_rendered_uniform_targets_agree_with_simulated(tmp_path, rig):
    pytest.importorskip("mitsuba")
    sets = {}
    for renderer in ("simulate", "mitsuba"):
        sets[renderer] = make_calibration_captures(tmp_path / renderer, rig=rig, size=SIZE, sensor=make_sensor("none"),
                                                   renderer=renderer, polarizer_angles=3, seed=6, spp=4)
    assert sets["simulate"]["captures"] == sets["mitsuba"]["captures"]
    for entry in sets["simulate"]["captures"]:
        sim, ren = (read_capture(tmp_path / r / entry["folder"]) for r in ("simulate", "mitsuba"))
        assert ren.meta["kind"] == "rendered" and ren.meta["calibration"] == sim.meta["calibration"]
        assert np.array_equal(ren.aperture_homographies(), sim.aperture_homographies())
        if entry["target"] in ("flat", "polarizer"):
            assert np.abs(_site_means(ren, rig) - _site_means(sim, rig)).max() < RENDERED_TOLERANCE
            assert np.abs(ren.gt - sim.gt).max() < RENDERED_TOLERANCE
        elif entry["target"] == "geometry":  # the textured slide without its film: unpolarized
            assert np.allclose(ren.gt.reshape(4, 3, -1), ren.gt.reshape(4, 3, -1)[:1], atol=1e-4)
        else:
            assert len(ren.meta["calibration"]["center_rowcol"]) == 2
