"""``capssim reconstruct`` on a small capture folder."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from capssim.cli import app


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    from capssim.camera.sensor import make_sensor
    from capssim.captures.capture import write_capture
    from capssim.simulate import simulate_capture

    rng = np.random.default_rng(0)
    gt = (0.2 + 0.5 * rng.random((12, 32, 32))).astype(np.float32)
    path = tmp_path_factory.mktemp("cap") / "capture"
    write_capture(path, simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=1))
    return path


def test_reconstruct_writes_tiff_and_json(capture_dir):
    from capssim.files.imageio import read_tiff

    res = CliRunner().invoke(app, ["reconstruct", str(capture_dir), "-m", "caps", "-m", "caps-no-nlstr",
                                   "--true-warps", "--iterations", "3", "-p", "c2=0.02", "--no-progress"])
    assert res.exit_code == 0, res.output
    for name in ("caps", "caps-no-nlstr"):
        image = read_tiff(capture_dir / "recon" / f"{name}.tiff")
        assert image.shape == (12, 32, 32) and image.dtype == np.float32
        record = json.loads((capture_dir / "recon" / f"{name}.json").read_text())
        assert record["method"] == name and len(record["history"]) == 3
        assert record["params"]["iterations"] == 3 and record["true_warps"] is True
        assert "registration" in record and record["stages_s"]
    assert "median error 0.0000 HR px" in res.output


def test_reconstruct_errors_are_clear(capture_dir):
    runner = CliRunner()
    res = runner.invoke(app, ["reconstruct", str(capture_dir), "-m", "no-such-method", "--true-warps"])
    assert res.exit_code != 0 and "no-such-method" in str(res.exception)
    res = runner.invoke(app, ["reconstruct", str(capture_dir), "--true-warps", "-p", "nokey"])
    assert res.exit_code != 0 and "KEY=VALUE" in str(res.exception)
    res = runner.invoke(app, ["reconstruct", str(capture_dir), "--true-warps", "--device", "tpu"])
    assert res.exit_code != 0


def test_list_and_all(capture_dir):
    from capssim.cli.reconstruct import expand_methods

    res = CliRunner().invoke(app, ["reconstruct", str(capture_dir), "--list"])
    assert res.exit_code == 0 and "caps-iccp" in res.output
    names = expand_methods(["all"], capture_dir)
    assert {"caps", "caps-no-cagf", "caps-no-nlstr", "caps-iccp"} <= set(names)


def test_registration_mode_option(capture_dir):
    """``--registration`` reaches the estimate and is recorded; an unknown mode is a clear error."""
    runner = CliRunner()
    res = runner.invoke(app, ["reconstruct", str(capture_dir), "-m", "caps-no-nlstr", "--iterations", "2",
                              "--registration", "stokes-subspace", "--no-progress"])
    assert res.exit_code == 0, res.output
    record = json.loads((capture_dir / "recon" / "caps-no-nlstr.json").read_text())
    assert record["registration"]["mode"] == "stokes-subspace"
    assert np.isfinite(record["registration"]["error_hr_px_median"])
    res = runner.invoke(app, ["reconstruct", str(capture_dir), "-m", "caps", "--registration", "fastest"])
    assert res.exit_code != 0 and "stokes-subspace" in str(res.exception)


def test_iterations_flag_is_not_passed_to_dofp_methods(capture_dir):
    # 'reconstruct CAP -m all --iterations N' (README) reaches the DoFP methods, which take no such option
    res = CliRunner().invoke(app, ["reconstruct", str(capture_dir), "-m", "caps-no-nlstr", "-m", "dofp-bilinear",
                                   "-m", "dofp-eari", "--true-warps", "--iterations", "2", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "--iterations does not apply to the DoFP method dofp-eari" in res.output
    record = json.loads((capture_dir / "recon" / "caps-no-nlstr.json").read_text())
    assert record["params"]["iterations"] == 2
    assert (capture_dir / "recon" / "dofp-bilinear.tiff").exists()
