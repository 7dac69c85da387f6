"""``capssim bench suite`` on Dask: the serial run's metrics, a killed run resumed, the regression check."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capssim.cli import app
from capssim.errors import InputError
from capssim.eval.benchmarks.results import ResultsLog, read_results
from capssim.eval.benchmarks.runner import CaseRun, CaseTask
from capssim.eval.benchmarks.suite import load_suite

distributed = pytest.importorskip("distributed")

#: 2 synthetic scenes (one a Siemens star: MTF) x 4 methods; naive-est and naive-est2 estimate the warps
#: (registered once per capture, by one of them)
SUITE = """
name: tiny-dask
seeds: [0]
noise:
  - {name: gauss-0.01, model: gaussian, sigma: 0.01}
methods:
  - dofp-bilinear
  - {name: caps-naive, true_warps: true}
  - {name: caps-naive, label: naive-est}
  - {name: caps-naive, label: naive-est2}
scenes:
  - {name: star, source: synthetic, generator: star, size: 64, cycles: 16}
  - {name: texture, source: synthetic, generator: texture, size: 48}
"""
CASES = 8


@pytest.fixture
def suite(tmp_path, monkeypatch):
    monkeypatch.setenv("CAPSSIM_THREADS", "1")
    path = tmp_path / "tiny.yaml"
    path.write_text(SUITE)
    return path


@pytest.fixture(scope="module")
def cluster():
    """A running 2-worker cluster, for --scheduler."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  silence_logs=logging.ERROR) as running:
        yield running


def _bench(suite: Path, out: Path, *args):
    return CliRunner().invoke(app, ["bench", "suite", str(suite), "-o", str(out), "--no-plots", *map(str, args)])


def _lines(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]


@pytest.mark.processes
def test_two_workers_give_the_serial_metrics_and_pass_its_check(suite, tmp_path):
    serial, dask, baseline = tmp_path / "serial", tmp_path / "dask", tmp_path / "baseline.json"
    r = _bench(suite, serial, "--update-baseline", baseline)
    assert r.exit_code == 0, r.output
    r = _bench(suite, dask, "--workers", 2, "--check", baseline)
    assert r.exit_code == 0, r.output
    assert "ran on 2 Dask worker(s), 1 compute thread(s) each" in r.output
    assert f"PASSED ({CASES} case(s) compared" in r.output
    ours, theirs = _lines(serial), _lines(dask)
    assert [r["key"] for r in theirs] == [r["key"] for r in ours]  # the same file order: the plan's
    assert all(r["status"] == "ok" for r in ours + theirs)
    for a, b in zip(ours, theirs):
        assert a["case_id"] == b["case_id"]
        assert a["metrics"].keys() == b["metrics"].keys()
        for name, value in a["metrics"].items():
            assert b["metrics"][name] == pytest.approx(value, abs=1e-6, nan_ok=True), (a["key"], name)
        assert b["wall_time_s"] > 0 and b["peak_rss_mb"] > 0 and b["stages_s"]
    # measured in the worker processes, not here
    assert {int(r["worker"].split(":")[1]) for r in theirs}.isdisjoint({os.getpid()})
    assert {r["environment"]["torch_threads"] for r in theirs} == {1}
    assert all("mtf" in r for r in theirs if r["scene"] == "star")
    for scene in ("star", "texture"):  # each capture registered once, its other estimated-warps case reused it
        stores = sorted(r["registration"]["store"] for r in theirs
                        if r["scene"] == scene and r["method"] in ("naive-est", "naive-est2"))
        assert stores == ["computed", "reused"], (scene, stores)


def test_captures_that_write_the_same_cache_folder_wait_for_each_other(tmp_path, monkeypatch):
    monkeypatch.setenv("CAPSSIM_SHARED_DATA", str(tmp_path / "no-shared-data"))  # real-a, real-b fall back
    path = tmp_path / "cache-sharing.yaml"
    path.write_text(SUITE.replace("noise:\n", "noise:\n  - {name: clean, model: none}\n") + """\
  - {name: rendered, source: render, scene: siemens-star, size: 64}
  - {name: real-a, source: shared-gt, path: gt/a, fallback: texture}
  - {name: real-b, source: shared-gt, path: gt/b, fallback: texture}
""")
    spec = load_suite(path)
    calls = {}

    class Recorder:
        live_events = False

        def submit(self, fn, *args, tag, after=(), **kwargs):
            calls[tag] = list(after)
            return tag

    (tmp_path / "out").mkdir()
    run = CaseRun(spec, tmp_path / "out", CaseTask(lambda *a, **k: None), device="cpu", cache=tmp_path / "cache",
                  fresh=False, emit=lambda kind, **info: None)
    scenes = {s["name"]: s for s in spec["scenes"]}
    run.groups = [(scenes[name], noise, 0) for name in ("star", "rendered", "real-a", "real-b")
                  for noise in spec["noise"]]
    run.submit_captures(Recorder(), scenes)
    assert calls[("capture", 1)] == []  # the synthetic star: a folder per noise level, nothing shared
    assert calls[("capture", 3)] == [("capture", 2)]  # the noise levels of a render share the render
    # two scenes with the same fallback may both build its capture
    assert calls[("capture", 6)] == [("capture", 4)] and calls[("capture", 7)] == [("capture", 5)]


@pytest.mark.processes
def test_a_killed_run_run_again_does_only_the_missing_cases(suite, tmp_path, cluster):
    out = tmp_path / "out"
    command = [sys.executable, "-m", "capssim", "bench", "suite", str(suite), "-o", str(out), "--no-plots",
               "--scheduler", cluster.scheduler_address]
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    results = out / "results.jsonl"
    try:
        deadline = time.monotonic() + 120
        while not (results.is_file() and results.read_text().count("\n") >= 1):
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "no case finished in 120 s"
            time.sleep(0.02)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
    with results.open("a") as f:  # as if killed while writing a line
        f.write('{"suite": "tiny-dask", "status": "ok", "case_id": "trunc')
    before = read_results(results)
    assert 1 <= len(before) < CASES
    r = _bench(suite, out, "--scheduler", cluster.scheduler_address)
    assert r.exit_code == 0, r.output
    after = _lines(out)
    assert len(after) == CASES and all(rec["status"] == "ok" for rec in after)
    by_id = {rec["case_id"]: rec for rec in after}
    for cid, rec in before.items():  # finished before the kill: kept as they were, not run again
        assert by_id[cid] == rec
    assert "ran on 2 Dask worker(s)" in r.output


def test_results_log_appends_whole_lines_and_drops_a_torn_tail(tmp_path):
    path = tmp_path / "results.jsonl"
    log = ResultsLog(path)
    log.append({"case_id": "a", "status": "ok", "metrics": {"psnr": 30.0}})
    log.append({"case_id": "b", "status": "error"})
    with path.open("a") as f:
        f.write('{"case_id": "c", "stat')
    log = ResultsLog(path)  # the next run: the torn line is gone, new lines start on a line of their own
    assert set(log.previous) == {"a", "b"} and path.read_text().endswith("}\n")
    assert log.done("a") is not None and log.done("b") is None
    log.append({"case_id": "b", "status": "ok"})
    assert read_results(path)["b"]["status"] == "ok"  # the last line of a case wins
    log.finish([{"case_id": "b", "status": "ok"}])
    assert [json.loads(line)["case_id"] for line in path.read_text().splitlines()] == ["b", "a"]
    fresh = ResultsLog(path, fresh=True)  # --fresh -m ONE: that method's cases are redone, the others' kept
    assert fresh.done("b") is None and fresh.done("a") is None
    fresh.finish([{"case_id": "a", "status": "ok", "metrics": {"psnr": 31.0}}])
    assert read_results(path) == {"a": {"case_id": "a", "status": "ok", "metrics": {"psnr": 31.0}},
                                  "b": {"case_id": "b", "status": "ok"}}


def test_results_log_drops_superseded_records_of_the_same_case(tmp_path):
    path = tmp_path / "results.jsonl"
    log = ResultsLog(path)
    log.append({"case_id": "old", "key": "kettle/caps", "status": "ok"})
    log.append({"case_id": "other", "key": "kettle/caps-naive", "status": "ok"})
    log = ResultsLog(path)  # code changed: the same case now has another hash
    log.finish([{"case_id": "new", "key": "kettle/caps", "status": "ok"}])
    assert [json.loads(line)["case_id"] for line in path.read_text().splitlines()] == ["new", "other"]


def test_workers_and_scheduler_exclude_each_other(suite, tmp_path):
    r = _bench(suite, tmp_path / "o", "--workers", 2, "--scheduler", "tcp://127.0.0.1:1")
    assert isinstance(r.exception, InputError) and "--scheduler" in str(r.exception)  # the CLI: exit 2, one line
