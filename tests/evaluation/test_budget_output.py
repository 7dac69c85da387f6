"""``capssim bench budget`` owns its output folder like ``bench suite`` (issue 60 item 1): one case runner.

Two budgets into one folder at once, another suite's budget into a folder, two suites of one name in
one call; each run is a tiny synthetic suite (one 32 px texture) with the fast methods.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading

from typer.testing import CliRunner

from capssim.cli import app
from capssim.errors import InputError
from capssim.eval.benchmarks.output_claim import BUDGET_OUTPUT, LOCK_NAME
from capssim.eval.benchmarks.suite import load_suite
from capssim.eval.error_budget import runner

SUITE = """
name: {name}
seeds: [0]
noise:
  - {{name: gauss-0.02, noise: gaussian, sigma: 0.02}}
methods: [dofp-bilinear]
scenes:
  - {{name: texture, source: synthetic, generator: texture, size: 32}}
"""


def _suite(tmp_path, name="tiny-own", file=None):
    path = tmp_path / (file or f"{name}.yaml")
    path.write_text(SUITE.format(name=name))
    return path


def _lines(out):
    return [json.loads(x) for x in (out / "budget.jsonl").read_text().splitlines()]


def _budget(*args):
    return CliRunner().invoke(app, ["bench", "budget", *map(str, args), "--no-plots"])


def test_two_budgets_at_once_into_one_folder_keep_every_case_or_refuse_in_one_line(tmp_path):
    """Two processes started together, different -m: each either runs (and its cases are all in
    budget.jsonl, once each) or is refused with one line naming the run that holds the folder."""
    suite, out = _suite(tmp_path), tmp_path / "out"
    env = dict(os.environ, CAPSSIM_THREADS="1")
    procs = {m: subprocess.Popen([sys.executable, "-m", "capssim", "bench", "budget", str(suite), "-o", str(out),
                                  "-m", m, "--no-plots"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                 env=env)
             for m in ("dofp-bilinear", "caps-naive")}
    results = {m: (p.wait(timeout=300), p.stdout.read(), p.stderr.read()) for m, p in procs.items()}
    for p in procs.values():
        p.stdout.close()
        p.stderr.close()
    ran = [m for m, (rc, _, _) in results.items() if rc == 0]
    assert ran, results
    for m, (rc, _, err) in results.items():
        if rc != 0:
            assert rc == 2 and "in use by another run" in err and "capssim bench budget tiny-own" in err, err
            assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    lines = _lines(out)
    assert sorted(r["method"] for r in lines) == sorted(ran)  # every case of every run that ran, once
    assert all(r["status"] == "ok" and r["suite"] == "tiny-own" for r in lines)


def test_a_second_budget_while_one_runs_is_refused_with_one_line(tmp_path, monkeypatch):
    """Deterministic: the first run (a thread here) holds the folder inside its first case; the second is
    refused before it touches anything, and the first run's case ends up in budget.jsonl."""
    suite, out = _suite(tmp_path), tmp_path / "out"
    inside, release = threading.Event(), threading.Event()
    real = runner.budget_task

    def held(*args, **kwargs):
        inside.set()
        release.wait(60)
        return real(*args, **kwargs)

    monkeypatch.setattr(runner, "budget_task", held)
    first = threading.Thread(target=runner.run_budget, args=(load_suite(suite), out), kwargs={"views": False})
    first.start()
    try:
        assert inside.wait(120)
        second = _budget(suite, "-o", out, "-m", "caps-naive")
        assert second.exit_code != 0 and isinstance(second.exception, InputError)
        message = str(second.exception)
        assert "in use by another run" in message and "\n" not in message and "-o" in message
    finally:
        release.set()
        first.join(120)
    assert [r["method"] for r in _lines(out)] == ["dofp-bilinear"]
    assert (out / LOCK_NAME).is_file() and (out / BUDGET_OUTPUT.owner_name).is_file()


def test_another_suites_budget_is_refused_and_handed_over_keeps_the_first_rows(tmp_path):
    first, out = _suite(tmp_path), tmp_path / "out"
    assert _budget(first, "-o", out).exit_code == 0
    before = (out / "budget.jsonl").read_text()
    other = _suite(tmp_path, "other-own")
    refused = _budget(other, "-o", out)
    assert isinstance(refused.exception, InputError)
    message = str(refused.exception)
    assert "the output of suite 'tiny-own'" in message and "--allow-other-suite" in message and "\n" not in message
    assert (out / "budget.jsonl").read_text() == before
    handed = _budget(other, "-o", out, "--allow-other-suite")
    assert handed.exit_code == 0, handed.output
    assert (out / "budget.tiny-own.jsonl").read_text() == before  # moved, not lost
    assert {r["suite"] for r in _lines(out)} == {"other-own"}
    assert "other-own" in (out / "budget.md").read_text().splitlines()[0]
    assert json.loads((out / BUDGET_OUTPUT.owner_name).read_text())["suite"] == "other-own"


def test_two_suites_of_one_name_in_one_call_are_refused_before_any_work(tmp_path):
    a = _suite(tmp_path, "same", file="a.yaml")
    b = _suite(tmp_path, "same", file="b.yaml")
    result = _budget(a, b, "-o", tmp_path / "out")
    assert isinstance(result.exception, InputError)
    message = str(result.exception)
    assert "both named 'same'" in message and "SUITE" in message and "\n" not in message
    assert not (tmp_path / "out").exists()


def test_a_budget_and_a_suite_share_a_folder_each_with_its_own_results(tmp_path):
    """The suite's results.jsonl and the budget's budget.jsonl sit side by side (one lock, two owners)."""
    suite, out = _suite(tmp_path), tmp_path / "out"
    assert CliRunner().invoke(app, ["bench", "suite", str(suite), "-o", str(out), "--no-plots"]).exit_code == 0
    assert _budget(suite, "-o", out).exit_code == 0
    assert [r["method"] for r in _lines(out)] == ["dofp-bilinear"]
    assert [json.loads(x)["method"] for x in (out / "results.jsonl").read_text().splitlines()] == ["dofp-bilinear"]
