"""``capssim evaluate`` and ``capssim mtf``: tables, metrics.json, and clear errors on bad captures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture, write_reconstruction
from capssim.cli import app
from capssim.errors import CaptureFormatError, InputError
from capssim.eval.evaluate import evaluate_capture
from capssim.eval.mtf import sinusoidal_star
from capssim.eval.synthetic import synthetic_scene
from capssim.files.imageio import write_tiff
from capssim.simulate import simulate_capture

runner = CliRunner()


def _capture(path: Path, generator: str = "texture", size: int = 64) -> Path:
    gt, scene = synthetic_scene(generator, size=size, cycles=24)
    cap = simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=1,
                           extra_meta={"scene": {"name": generator, **scene}})
    write_capture(path, cap)
    noisy = gt + np.random.default_rng(0).normal(0, 0.01, gt.shape).astype(np.float32)
    write_reconstruction(path, "gt-plus-noise", noisy, {"wall_time_s": 1.25, "stages_s": {"a": 1.0, "b": 0.25}})
    return path


def test_evaluate_prints_tables_and_writes_metrics(tmp_path):
    cap = _capture(tmp_path / "cap")
    r = runner.invoke(app, ["evaluate", str(cap)])
    assert r.exit_code == 0, r.output
    for text in ("PSNR per channel", "SSIM per channel", "AoP-RMSE", "135-B", "LPIPS: skipped", "1.25"):
        assert text in r.output
    data = json.loads((cap / "metrics.json").read_text())
    m = data["methods"]["gt-plus-noise"]
    assert m["wall_time_s"] == 1.25 and m["stages_s"] == {"a": 1.0, "b": 0.25}
    assert 38 < m["metrics"]["psnr_mean"] < 42
    r = runner.invoke(app, ["evaluate", str(cap), "--json", "--convention", "tokyotech"])
    assert r.exit_code == 0
    assert json.loads(r.output)["settings"]["border"] == 15


def test_evaluate_star_capture_reports_mtf(tmp_path):
    cap = _capture(tmp_path / "star", generator="polarization-star", size=96)
    r = runner.invoke(app, ["evaluate", str(cap)])
    assert r.exit_code == 0, r.output
    assert "Siemens star (24 cycles)" in r.output and "(ground truth)" in r.output
    mt = json.loads((cap / "metrics.json").read_text())["methods"]["gt-plus-noise"]["mtf"]
    assert mt["cycles"] == 24 and set(mt["channels"]) == {"0-R", "0-G", "0-B", "45-R", "45-G", "45-B", "90-R", "90-G",
                                                           "90-B", "135-R", "135-G", "135-B"}
    assert mt["mean"]["magnification"]["hv"] > 2.0  # ground truth plus mild noise: resolved well past 1x


def test_missing_gt_and_no_reconstruction_are_clear_errors(tmp_path):
    cap = _capture(tmp_path / "cap")
    (cap / "gt.tiff").unlink()
    with pytest.raises(CaptureFormatError, match="no gt.tiff; scoring needs the ground truth"):
        evaluate_capture(cap)
    r = runner.invoke(app, ["evaluate", str(cap)])
    assert r.exit_code != 0 and isinstance(r.exception, CaptureFormatError)
    cap2 = _capture(tmp_path / "cap2")
    for f in (cap2 / "recon").iterdir():
        f.unlink()
    with pytest.raises(CaptureFormatError, match="no reconstructions"):
        evaluate_capture(cap2)
    with pytest.raises(InputError, match="methods"):
        evaluate_capture(_capture(tmp_path / "cap3"), methods=["nope"])


def test_bad_reconstructions_are_reported_per_method(tmp_path):
    cap = _capture(tmp_path / "cap")
    bad = np.zeros((12, 64, 64), dtype=np.float32)
    bad[2, 10, 10] = np.nan
    write_tiff(cap / "recon" / "has-nan.tiff", bad)
    write_tiff(cap / "recon" / "wrong-shape.tiff", np.zeros((12, 32, 32), dtype=np.float32))
    r = runner.invoke(app, ["evaluate", str(cap)])
    assert r.exit_code == 1
    assert "has-nan" in r.output and "NaN/inf values (channels 0-B)" in r.output
    assert "wrong-shape" in r.output and "shape (12, 32, 32)" in r.output
    data = json.loads((cap / "metrics.json").read_text())
    assert "metrics" in data["methods"]["gt-plus-noise"]  # the good one is still scored


def test_mtf_command_on_grey_rgb_and_twelve_channel_images(tmp_path):
    import cv2

    star = sinusoidal_star((128, 128), 36, center_rowcol=(62.3, 66.8), blur_sigma=1.0, supersample=5)
    grey = tmp_path / "star.png"
    cv2.imwrite(str(grey), np.round(star * 65535).astype(np.uint16))
    r = runner.invoke(app, ["mtf", str(grey), "--cycles", "36"])
    assert r.exit_code == 0, r.output
    assert "(found)" in r.output and "row 62.3" in r.output and "MTF-hv" in r.output and "mag-hv" in r.output
    r = runner.invoke(app, ["mtf", str(grey), "--cycles", "36", "--center", "62.3,66.8", "--json",
                            "--reference-pitch", "2"])
    d = json.loads(r.output)["channels"]["grey"]
    assert d["reference_pitch"] == 2 and d["magnification"]["hv"] == pytest.approx(d["limit_cyc_per_px"]["hv"] * 4)
    assert d["limit_cyc_per_px"]["hv"] == pytest.approx(0.4215, abs=0.01)  # Gaussian sigma 1: exp(-2 pi^2 f^2) = 0.03
    rgb = tmp_path / "star_rgb.png"
    cv2.imwrite(str(rgb), np.round(np.stack([star] * 3, -1) * 255).astype(np.uint8))
    r = runner.invoke(app, ["mtf", str(rgb), "--cycles", "36", "--channel", "G", "--channel", "B"])
    assert r.exit_code == 0 and "channel mean" in r.output
    tw = tmp_path / "star12.tiff"
    write_tiff(tw, np.stack([star] * 12).astype(np.float32))
    r = runner.invoke(app, ["mtf", str(tw), "--cycles", "36", "--channel", "0-R"])
    assert r.exit_code == 0 and "reference pitch: 4 px" in r.output
    r = runner.invoke(app, ["mtf", str(grey), "--cycles", "36", "--center", "nonsense"])
    assert isinstance(r.exception, InputError)
    r = runner.invoke(app, ["mtf", str(rgb), "--cycles", "36", "--channel", "X"])
    assert isinstance(r.exception, InputError)
