"""Issue 21 hardening of reading and reconstruction: sensor levels, unobserved channels, divergence."""

from __future__ import annotations

import copy
import json
import logging
import re

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from capssim.camera.sensor import make_sensor, sensor_from_meta
from capssim.captures.capture import Capture, build_meta, read_capture, write_capture
from capssim.errors import CapssimError, CaptureFormatError
from capssim.reconstruct.registry import finite_or_null, reconstruct
from capssim.reconstruct.solvers.interfaces import DivergenceError
from capssim.simulate import simulate_capture


def _gt(size: int = 32) -> np.ndarray:
    rng = np.random.default_rng(0)
    gt = np.stack([gaussian_filter(rng.random((size, size)), 3) for _ in range(12)])
    return (0.1 + 0.8 * (gt - gt.min()) / (gt.max() - gt.min())).astype(np.float32)


@pytest.fixture(scope="module")
def noisy_capture() -> Capture:
    return simulate_capture(_gt(), make_sensor("gaussian", sigma=0.01), seed=1)


#: hand-written sensor entries, as a user with a real camera writes them, per model
HAND_WRITTEN = {
    "gaussian": {"model": "gaussian", "sigma": 0.01, "bit_depth": 12, "black_level": 256, "white_level": 4095},
    "poisson-gaussian": {"model": "poisson-gaussian", "bit_depth": 12, "black_level": 256, "white_level": 4000,
                         "gain_dn_per_e": 0.4, "full_well_e": 10000.0},
    "none": {"model": "none", "black_level": 0.05, "white_level": 0.9},
}


def _hand_written(capture: Capture, sensor_meta: dict) -> Capture:
    """The capture's float frames written as raw values with ``sensor_meta``'s levels."""
    sensor = sensor_from_meta(sensor_meta)
    full_scale = (sensor.white_level - sensor.black_level if sensor.model != "poisson-gaussian"
                  else sensor.gain_dn_per_e * sensor.full_well_e * sensor.exposure)

    def encode(values):
        raw = sensor.black_level + values.astype(np.float64) * full_scale
        return raw.astype(np.float32) if sensor.model == "none" else np.round(raw).astype(np.uint16)

    meta = copy.deepcopy(capture.meta)
    meta["sensor"] = dict(sensor_meta)
    meta["setup"].pop("sensor")  # the set-up block's sensor is then derived from the top level
    return Capture(meta=meta, caps_raw=encode(np.clip(capture.caps_float(), 0, 0.9)),
                   dofp_raw=encode(np.clip(capture.dofp_float(), 0, 0.9)), gt=capture.gt)


@pytest.mark.parametrize("model", sorted(HAND_WRITTEN))
def test_hand_written_levels_reconstruct_as_the_float_twin(model, noisy_capture, tmp_path):
    dn = _hand_written(noisy_capture, HAND_WRITTEN[model])
    write_capture(tmp_path / "dn", dn)
    dn = read_capture(tmp_path / "dn")
    twin = copy.deepcopy(noisy_capture)  # the same values as float32 on [0, 1]
    twin.meta["sensor"] = make_sensor("none").to_meta()
    twin.meta["setup"].pop("sensor")
    twin.caps_raw, twin.dofp_raw = dn.caps_float(), dn.dofp_float()
    assert np.abs(dn.caps_float() - np.clip(noisy_capture.caps_float(), 0, 0.9)).max() < 1e-3
    for method, options in (("caps", {"iterations": 2}), ("dofp-bilinear", {})):
        ours, _ = reconstruct(dn, method, true_warps=True, **options)
        theirs, _ = reconstruct(twin, method, true_warps=True, **options)
        np.testing.assert_allclose(ours.image, theirs.image, atol=1e-6)


def test_sensor_levels_round_trip_through_meta():
    for meta in HAND_WRITTEN.values():
        sensor = sensor_from_meta(meta)
        assert sensor.black_level == meta["black_level"] and sensor.white_level == meta["white_level"]
        assert sensor_from_meta(sensor.to_meta()) == sensor
    gaussian = sensor_from_meta(HAND_WRITTEN["gaussian"])
    raw = gaussian.capture(np.array([0.0, 1.5, 2.0]), np.random.default_rng(0))
    assert raw.min() >= 256 and raw.max() == 4095  # written with the levels
    assert gaussian.saturation_mask(raw).tolist() == [False, True, True]
    none = sensor_from_meta(HAND_WRITTEN["none"])
    np.testing.assert_allclose(none.capture(np.array([0.0, 1.0]), np.random.default_rng(0)), [0.05, 0.9])
    np.testing.assert_allclose(none.to_float(np.array([0.05, 0.9], dtype=np.float32)), [0.0, 1.0], atol=1e-6)


def test_levels_that_disagree_or_exceed_the_adc_are_refused(noisy_capture):
    with pytest.raises(CapssimError, match="black_level"):
        sensor_from_meta({**HAND_WRITTEN["poisson-gaussian"], "black_level_dn": 240})
    with pytest.raises(CapssimError, match="white_level"):
        sensor_from_meta({**HAND_WRITTEN["gaussian"], "white_level": 5000})
    left_aligned = _hand_written(noisy_capture, HAND_WRITTEN["gaussian"])
    left_aligned.caps_raw = left_aligned.caps_raw * np.uint16(16)
    with pytest.raises(CapssimError, match="bit_depth"):
        left_aligned.caps_float()


# -- unobserved channels (defect 3) ---------------------------------------------------------------
def _saturated(capture: Capture, apertures) -> Capture:
    out = copy.deepcopy(capture)
    out.caps_raw[list(apertures)] = np.uint16(capture.sensor.white_level)
    return out


@pytest.mark.parametrize("method", ["caps", "caps-iccp"])
def test_a_saturated_aperture_is_reported_not_silent(method, noisy_capture, caplog):
    plain, _ = reconstruct(noisy_capture, method, iterations=1, true_warps=True)
    with caplog.at_level(logging.WARNING, logger="capssim.reconstruct.registry"):
        out, record = reconstruct(_saturated(noisy_capture, [1]), method, iterations=1, true_warps=True)
    fraction = record["unobserved"]["fraction"]
    assert len(fraction) == 12 and fraction[3:6] == [1.0, 1.0, 1.0]
    assert [c for c, f in enumerate(fraction) if f == 1.0] == [3, 4, 5] and {3, 4, 5} <= set(record["unobserved"]["channels"])
    assert out.unobserved.shape == (12, *noisy_capture.hr_shape) and out.unobserved[3:6].all()
    assert "channels 3 (100 %), 4 (100 %), 5 (100 %)" in caplog.text
    # the image itself is what it was before the report existed
    np.testing.assert_array_equal(plain.image, reconstruct(noisy_capture, method, iterations=1,
                                                           true_warps=True)[0].image)


def test_an_all_saturated_capture_warns_on_the_command_line(noisy_capture, tmp_path):
    from typer.testing import CliRunner

    from capssim.cli import app

    write_capture(tmp_path / "sat", _saturated(noisy_capture, range(4)))
    res = CliRunner().invoke(app, ["reconstruct", str(tmp_path / "sat"), "-m", "caps", "--iterations", "1",
                                   "--true-warps", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "no usable observation" in res.output
    record = json.loads((tmp_path / "sat" / "recon" / "caps.json").read_text())
    assert record["unobserved"]["fraction"] == [1.0] * 12 and record["unobserved"]["channels"] == list(range(12))


# -- divergence and overflow (defect 4) -----------------------------------------------------------
# c2=1e30 no longer reaches the solver: c1 and c2 above 1000x the paper's are refused (issue 34, class 11;
# tests/cli/test_hardening2_commands.py)
@pytest.mark.parametrize("method, option, value", [("caps", "dt", 100.0), ("caps-no-nlstr", "dt", 100.0)])
def test_divergence_is_an_error_naming_the_option(method, option, value, noisy_capture):
    with pytest.raises(DivergenceError, match=re.escape(f"option {option}: got {option}={value}")) as info:
        reconstruct(noisy_capture, method, iterations=3, true_warps=True, **{option: value})
    assert isinstance(info.value, CapssimError) and "diverged at iteration" in str(info.value)


def test_divergence_on_the_command_line_exits_2(noisy_capture, tmp_path):
    from typer.testing import CliRunner

    from capssim.cli import app

    write_capture(tmp_path / "cap", noisy_capture)
    res = CliRunner().invoke(app, ["reconstruct", str(tmp_path / "cap"), "-m", "caps", "--iterations", "3",
                                   "--true-warps", "--no-progress", "-p", "dt=100"])
    # a CapssimError: the console entry point prints it on one line and exits 2
    assert isinstance(res.exception, DivergenceError) and "option dt" in str(res.exception)


def test_a_horizon_across_the_image_is_refused(noisy_capture):
    warps = noisy_capture.aperture_homographies()
    warps[2] = warps[2] @ np.array([[1, 0, 0], [0, 1, 0], [-0.05, 0, 1.0]])
    meta = build_meta(kind="simulated", hr_shape=noisy_capture.hr_shape, aperture_homographies=warps,
                      setup=noisy_capture.setup)
    bad = Capture(meta=meta, caps_raw=noisy_capture.caps_raw, dofp_raw=noisy_capture.dofp_raw)
    with pytest.raises(CaptureFormatError, match=r"aperture_homographies\[2\]: its horizon"):
        reconstruct(bad, "caps", iterations=1, true_warps=True)


def test_records_never_hold_nan():
    found: list[str] = []
    clean = finite_or_null({"a": [1.0, float("nan")], "b": {"c": np.float32("inf")}, "d": 2}, found=found)
    assert clean == {"a": [1.0, None], "b": {"c": None}, "d": 2} and found == ["record.a[1]", "record.b.c"]
    json.dumps(clean, allow_nan=False)


@pytest.mark.parametrize("method", ["caps-naive", "caps-sisr", "dofp-bilinear", "dofp-eari", "dofp-igri2"])
def test_array_baselines_report_unobserved_channels(method, noisy_capture):
    clean = reconstruct(noisy_capture, method, true_warps=True)[1]["unobserved"]
    assert max(clean["fraction"]) < 0.1  # out-of-view border strips of the shifted apertures only
    saturated = copy.deepcopy(noisy_capture)
    if method.startswith("dofp"):
        saturated.dofp_raw[:] = np.uint16(noisy_capture.sensor.white_level)
        expected = list(range(12))
    else:
        saturated.caps_raw[2] = np.uint16(noisy_capture.sensor.white_level)
        expected = [6, 7, 8]
    record = reconstruct(saturated, method, true_warps=True)[1]["unobserved"]
    assert [c for c, f in enumerate(record["fraction"]) if f == 1.0] == expected
