"""``capssim bench SUBJECT``: one command-line shape for every benchmark, the former commands gone, results pages."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture
from capssim.cli import app
from capssim.eval.benchmarks.suite import BenchRun
from capssim.eval.suite_report import results_page, write_results_page
from capssim.eval.synthetic import texture_scene
from capssim.simulate import simulate_capture

SUBJECTS = ("suite", "reconstruct", "registration", "dofp", "render", "dataset")


def _invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_every_subject_is_a_bench_command():
    r = _invoke("bench", "--help")
    assert r.exit_code == 0, r.output
    for subject in SUBJECTS:
        assert subject in r.output
        assert _invoke("bench", subject, "--help").exit_code == 0, subject


def test_the_former_commands_are_gone():
    """0.2.0 removed the hidden compatibility commands (CHANGELOG.md): they are unknown commands now."""
    for old in (["bench", "--suite", "quick"], ["reconstruct-benchmark"], ["render-bench"]):
        r = _invoke(*old)
        assert r.exit_code == 2 and "No such" in r.output, (old, r.output)


@pytest.fixture
def texture_gt_folder(write_png_gt):
    """Factory: ``(path, size=64) -> path`` of a texture scene as PNGs."""

    def _gt_folder(path: Path, size: int = 64) -> Path:
        return write_png_gt(path, texture_scene(size, seed=3)[0])

    return _gt_folder


def test_dofp_subject_scores_the_published_columns(tmp_path, texture_gt_folder):
    texture_gt_folder(tmp_path / "gt" / "tiny")
    r = _invoke("bench", "dofp", tmp_path / "gt", "--scene", "tiny", "-m", "dofp-bilinear", "--threads", 1, "--json")
    assert r.exit_code == 0, r.output
    assert "border crop 15 px" in r.stderr and "dofp-bilinear" in r.stderr  # the table: stdout is the JSON alone
    (row,) = json.loads(r.stdout)
    assert row["scene"] == "tiny" and row["method"] == "dofp-bilinear" and row["time_s"] >= 0
    for key in ("psnr_0", "psnr_135", "psnr_s0", "psnr_s1", "psnr_s2", "psnr_dolp"):
        assert 15 < row[key] <= 100, key
    assert 0 <= row["aop_rmse_deg"] < 90
    r = _invoke("bench", "dofp", tmp_path / "gt", "--scene", "missing")
    assert r.exit_code != 0


def test_registration_subject(tmp_path):
    gt, _ = texture_scene(128, seed=1)
    capture = tmp_path / "cap"
    write_capture(capture, simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=2))
    r = _invoke("bench", "registration", capture, "--registration", "ri-luminance", "--json")
    assert r.exit_code == 0, r.output
    result = json.loads(r.stdout)
    (row,) = result["rows"]
    assert result["mode"] == "ri-luminance" and row["capture"] == str(capture)
    assert 0 <= row["median_hr_px"] < 1.0 and len(row["per_aperture_hr_px"]) == 4


def _run(records):
    spec = {"name": "tiny", "description": "A tiny suite.\n  Two lines.", "methods": [{"label": "m1"}, {"label": "m2"}],
            "convention": "capssim"}
    env = {"git": {"revision": "abc", "dirty": False}, "cpu": "cpu", "cpu_count": 2, "torch_threads": 2,
           "gpu": None, "device": "cpu", "versions": {"capssim": "0"}}
    return BenchRun(spec=spec, output=Path("."), results_path=Path("r"), records=records, environment=env)


def test_results_page_is_written_atomically_and_listed(tmp_path):
    base = {"status": "ok", "scene": "star", "noise": "clean", "seed": 0, "convention": "capssim",
            "stages_s": {"cagf": 0.5}, "wall_time_s": 1.5, "peak_rss_mb": 100.0}
    records = [dict(base, method="m1", metrics={"psnr_mean": 30.0, "ssim_mean": 0.9}),
               dict(base, method="m2", metrics={"psnr_mean": 28.0, "ssim_mean": None}),
               {"status": "skipped", "key": "real/clean/seed0/m1", "reason": "no data", "scene": "real"}]
    run = _run(records)
    page = results_page(run, written="2026-01-01")
    assert page.startswith("# Results: suite `tiny`") and "A tiny suite. Two lines." in page
    assert "| m1 | 30.00 | 0.9000 |" in page and "| m2 | 28.00 | - |" in page
    assert "Time per stage (s):" in page and "real/clean/seed0/m1" in page and "2026-01-01" in page
    assert "](" not in page  # no link the docs site could find broken
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / "index.md").write_text("# Results\n\nPages:\n")
    for _ in range(2):
        path = write_results_page(run, folder / "tiny.md")
    assert path.read_text() == results_page(run)
    assert (folder / "index.md").read_text().count("(tiny.md)") == 1
    assert sorted(p.name for p in folder.iterdir()) == ["index.md", "tiny.md"]  # no temporary file left


@pytest.mark.slow
def test_reconstruct_subject_runs_its_worker_in_a_subprocess(tmp_path):
    r = _invoke("bench", "reconstruct", "--size", 64, "--device", "cpu", "--iterations", 1, "--threads", 1, "--json")
    assert r.exit_code == 0, r.output
    (result,) = json.loads(r.stdout)
    assert result["hr_size"] == 64 and result["threads"] == 1 and result["wall_s"] > 0
