"""Issue 34 ("Hardening, second round"), the benchmark floor: classes 1 (bench suite), 3, 4 and 8.

Table-driven: each :class:`Row` names its class from the issue. A mistake in a suite file, a
baseline or the output folder exits 2 with one line naming the file (or option), the key and the
fix, before any case runs (the output folder is not even created); the regression gate cannot be
switched off by accident. Runs use a 32 px synthetic scene and ``dofp-bilinear`` (about a second).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from support.fuzz import invoke
from typer.testing import CliRunner

from capssim.cli import app
from capssim.errors import InputError
from capssim.eval.benchmarks.output_claim import LOCK_NAME, OWNER_NAME, claim_output
from capssim.eval.benchmarks.suite import load_suite
from capssim.schema import ConfigError

SUITE = """\
name: tiny-h2
seeds: [0]
noise:
  - {name: clean, noise: none}
methods:
  - dofp-bilinear
  - {name: dofp-bilinear, label: bilinear-2}
scenes:
  - {name: tex, source: synthetic, generator: texture, size: 32}
"""


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    old: str  # replaced in SUITE (or appended when empty)
    new: str
    fragments: tuple = ()  # in the one-line message

    def __str__(self):
        return f"class{self.cls}-{self.name.replace(' ', '-')}"


_TEX = "  - {name: tex, source: synthetic, generator: texture, size: 32}\n"
_M2 = "{name: dofp-bilinear, label: bilinear-2}"


def _scene(text: str) -> tuple[str, str]:
    return _TEX, f"  - {text}\n"


SUITE_ROWS = [
    Row(8, "misspelt option key", _M2, "{name: dofp-bilinear, label: bilinear-2, option: {iterations: 2}}",
        ("methods[1].option", "Did you mean 'options'")),
    Row(8, "misspelt true_warps", _M2, "{name: dofp-bilinear, label: bilinear-2, true-warps: true}",
        ("methods[1].true-warps", "Did you mean 'true_warps'")),
    Row(8, "misspelt size", *_scene("{name: tex, source: synthetic, generator: texture, sizee: 32}"),
        ("scenes[0].sizee", "Did you mean 'size'")),
    Row(8, "crop on a synthetic scene", *_scene("{name: tex, source: synthetic, generator: texture, crop: 32}"),
        ("scenes[0].crop", "a key of shared-gt, gt scenes")),
    Row(8, "psf_sigma for psf_sigma_hr_px", *_scene("{name: tex, source: synthetic, psf_sigma: 1}"),
        ("scenes[0].psf_sigma", "psf_sigma_hr_px")),
    Row(8, "misspelt top-level key", "scenes:", "scene:", ("'scene'", "Did you mean 'scenes'")),
    Row(8, "duplicate noise names", "  - {name: clean, noise: none}\n",
        "  - {name: clean, noise: none}\n  - {name: clean, noise: gaussian, sigma: 0.01}\n",
        ("noise[1].name", "distinct noise level names")),
    Row(8, "duplicate seeds", "seeds: [0]", "seeds: [0, 1, 0]", ("seeds[2]", "as seeds[0]")),
    Row(8, "duplicate method labels", _M2, "dofp-bilinear", ("methods[1].label", "own label")),
    Row(8, "duplicate scene names", _TEX, _TEX * 2, ("scenes[1].name", "distinct scene names")),
    Row(8, "unknown method", "  - dofp-bilinear\n", "  - dofp-bilinearr\n",
        ("methods[0].name", "Did you mean 'dofp-bilinear'")),
    Row(8, "unknown render scene", *_scene("{name: star, source: render, scene: siemens-starr, size: 32}"),
        ("scenes[0].scene", "Did you mean 'siemens-star'")),
    Row(8, "missing gt path", *_scene("{name: real, source: gt, path: /no/such/gt-folder}"),
        ("scenes[0].path", "/no/such/gt-folder")),
    Row(8, "missing shared-gt path under a data root", *_scene("{name: real, source: shared-gt, path: gt/nope}"),
        ("scenes[0].path", "data root")),
    Row(8, "negative size", "size: 32", "size: -32", ("scenes[0].size", "-32")),
    Row(8, "non-numeric size", "size: 32", "size: big", ("scenes[0].size", "'big'")),
    Row(8, "seed -5", "seeds: [0]", "seeds: [-5]", ("seeds[0]", ">= 0")),
    Row(8, "sigma -3", "  - {name: clean, noise: none}\n", "  - {name: g, noise: gaussian, sigma: -3}\n",
        ("noise[0].sigma", ">= 0")),
    Row(8, "sigma for noise none", "{name: clean, noise: none}", "{name: clean, noise: none, sigma: 0.1}",
        ("noise[0].sigma", "Noise 'none' takes")),
    Row(8, "crop 30", *_scene("{name: real, source: gt, path: eval/suites, crop: 30}"),
        ("scenes[0].crop", "multiple of 4", "Try 28")),
    Row(8, "crop too small", *_scene("{name: real, source: gt, path: eval/suites, crop: 8}"),
        ("scenes[0].crop", ">= 16")),
    Row(8, "fallback to an unknown scene", *_scene("{name: tex, source: synthetic, fallback: nowhere}"),
        ("scenes[0].fallback", "another scene")),
    Row(8, "unknown rig key", *_scene("{name: tex, source: synthetic, rig: {preset: realistic, gian: [1, 1, 1, 1]}}"),
        ("scenes[0].rig.gian", "Did you mean 'gain'")),
    Row(8, "rig value out of range", *_scene("{name: tex, source: synthetic, rig: {vignetting_corner: 5}}"),
        ("scenes[0].rig.vignetting_corner", "<= 0.9")),
    Row(8, "unknown registration mode", _M2, "{name: dofp-bilinear, label: b2, registration: phase}",
        ("methods[1].registration",)),
    Row(8, "no methods", "methods:\n  - dofp-bilinear\n  - " + _M2 + "\n", "methods: []\n",
        ("'methods'", "at least 1")),
    Row(8, "broken YAML", "seeds: [0]", "seeds: [0", ("not valid YAML", "line")),
    Row(1, "synthetic size 2048 past the memory limit", "size: 32", "size: 2048",
        ("scenes[0].size", "2048x2048 scene", "CAPSSIM_MEMORY_LIMIT_GB=1")),
    Row(1, "crop 2048 past the memory limit", *_scene("{name: real, source: gt, path: eval/suites, crop: 2048}"),
        ("scenes[0].crop", "CAPSSIM_MEMORY_LIMIT_GB=1")),
]


@pytest.fixture
def shared_root(tmp_path, monkeypatch) -> Path:
    """An existing (empty) shared-data root, and a 1 GiB memory limit."""
    root = tmp_path / "shared"
    (root / "gt").mkdir(parents=True)
    monkeypatch.setenv("CAPSSIM_SHARED_DATA", str(root))
    monkeypatch.setenv("CAPSSIM_MEMORY_LIMIT_GB", "1")
    return root


def _suite(tmp_path: Path, text: str = SUITE, name: str = "tiny-h2.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("row", SUITE_ROWS, ids=str)
def test_suite_mistakes_are_one_line_before_any_work(row, tmp_path, shared_root):
    assert row.old in SUITE
    suite = _suite(tmp_path, SUITE.replace(row.old, row.new, 1))
    out = tmp_path / "out"
    for command in (["bench", "suite", suite, "-o", out], ["bench", "budget", suite, "-o", out]):
        outcome, message = invoke(command)
        assert outcome == "error", message
        assert str(suite) in message, message
        for fragment in row.fragments:
            assert fragment in message, (fragment, message)
        assert not out.exists()  # refused before any work


def test_every_shipped_suite_loads_and_a_shared_scene_without_data_root_is_kept(tmp_path, monkeypatch):
    from capssim.eval.benchmarks.suite import available_suites

    monkeypatch.setenv("CAPSSIM_SHARED_DATA", str(tmp_path / "absent"))  # CI: no shared data
    for name in available_suites():
        assert load_suite(name)["scenes"], name
    spec = load_suite(_suite(tmp_path, SUITE + "  - {name: real, source: shared-gt, path: gt/qiu-kettle}\n"))
    assert [s["name"] for s in spec["scenes"]] == ["tex", "real"]
    with pytest.raises(ConfigError, match="scenes"):  # the Python API raises the same one-line error
        load_suite(_suite(tmp_path, SUITE.replace("scenes:", "scene:"), name="bad.yaml"))


# -- class 3: baselines ------------------------------------------------------------------------------
def _baseline(**changes) -> dict:
    base = {"schema": "capssim.bench-baseline", "version": 1, "suite": "tiny-h2", "suite_sha256": None,
            "tolerances": {"psnr_db": 0.1, "ssim": 0.005}, "cases": {
                "tex/clean/seed0/dofp-bilinear": {"metrics": {"psnr_mean": 30.0}, "wall_time_s": 0.1}}}
    base.update(changes)
    return base


def _text(obj) -> str:
    return obj if isinstance(obj, str) else json.dumps(obj)


BASELINE_ROWS = [
    Row(3, "a list", "", _text([1, 2, 3]), ("a baseline written by --update-baseline",)),
    Row(3, "a string tolerance", "", _text(_baseline(tolerances={"psnr_db": "0.1"})), ("tolerances.psnr_db", "quotes")),
    Row(3, "a NaN tolerance", "", _text(_baseline(tolerances={"psnr_db": float("nan")})),
        ("tolerances.psnr_db", "finite number >= 0")),
    Row(3, "a negative tolerance", "", _text(_baseline(tolerances={"ssim": -0.01})), ("tolerances.ssim", ">= 0")),
    Row(3, "an unknown tolerance", "", _text(_baseline(tolerances={"psnr": 0.1})),
        ("tolerances.psnr", "Did you mean 'psnr_db'")),
    Row(3, "a metric that is a word", "", _text(_baseline(cases={"k": {"metrics": {"psnr_mean": "high"}}})),
        ("cases.k.metrics.psnr_mean",)),
    Row(3, "cases a list", "", _text(_baseline(cases=[])), ("'cases'",)),
    Row(3, "another schema", "", _text(_baseline(schema="something")), ("'schema'",)),
    Row(3, "not JSON", "", "{oops", ("not valid JSON",)),
]


@pytest.mark.parametrize("row", BASELINE_ROWS, ids=str)
def test_bad_baselines_are_refused_before_the_run(row, tmp_path):
    suite = _suite(tmp_path)
    bad = tmp_path / "baseline.json"
    bad.write_text(row.new)
    out = tmp_path / "out"
    for option in ("--check", "--update-baseline"):
        outcome, message = invoke(["bench", "suite", suite, "-o", out, option, bad])
        assert outcome == "error", message
        assert str(bad) in message
        for fragment in row.fragments:
            assert fragment in message, (fragment, message)
        assert not out.exists()


def _bench(*args):
    return CliRunner().invoke(app, ["bench", "suite", *map(str, args), "--no-plots"])


def test_check_fails_when_nothing_is_scored(tmp_path, monkeypatch):
    """Class 3: a suite whose every case is skipped (no shared data) fails --check, and says why."""
    monkeypatch.setenv("CAPSSIM_SHARED_DATA", str(tmp_path / "absent"))
    suite = _suite(tmp_path, SUITE.replace(_TEX, "  - {name: real, source: shared-gt, path: gt/x}\n"))
    base = tmp_path / "b.json"
    base.write_text(json.dumps(_baseline(cases={"real/clean/seed0/dofp-bilinear": {"metrics": {"psnr_mean": 30.0}}})))
    result = _bench(suite, "-o", tmp_path / "out", "--check", base)
    assert result.exit_code == 1, result.output
    assert "nothing scored" in result.output and "FAILED" in result.output


def test_update_baseline_merges_a_subset_and_replace_baseline_drops(tmp_path):
    """Class 3: ``--update-baseline -m`` keeps the other cases and the edited tolerances."""
    suite, out, base = _suite(tmp_path), tmp_path / "out", tmp_path / "b.json"
    assert _bench(suite, "-o", out, "--update-baseline", base).exit_code == 0
    written = json.loads(base.read_text())
    assert len(written["cases"]) == 2
    written["tolerances"]["psnr_db"] = 0.5
    base.write_text(json.dumps(written))
    result = _bench(suite, "-o", out, "-m", "bilinear-2", "--update-baseline", base)
    assert result.exit_code == 0, result.output
    assert "(2 cases, 1 kept from the existing baseline" in result.output
    merged = json.loads(base.read_text())
    assert set(merged["cases"]) == set(written["cases"]) and merged["tolerances"]["psnr_db"] == 0.5
    result = _bench(suite, "-o", out, "-m", "bilinear-2", "--update-baseline", base, "--replace-baseline")
    assert result.exit_code == 0, result.output
    assert list(json.loads(base.read_text())["cases"]) == ["tex/clean/seed0/bilinear-2"]
    assert _bench(suite, "-o", out, "--check", base).exit_code == 0  # the kept case passes its own check


@pytest.mark.parametrize("row", [
    Row(3, "replace-baseline alone", "", "--replace-baseline", ("--replace-baseline", "--update-baseline PATH")),
    Row(3, "update another suite's baseline", "", "other-suite", ("the baseline of suite 'other'",
                                                                   "--replace-baseline")),
], ids=str)
def test_baseline_options_are_checked_before_the_run(row, tmp_path):
    suite, out = _suite(tmp_path), tmp_path / "out"
    if row.new == "--replace-baseline":
        args = ["--replace-baseline"]
    else:
        other = tmp_path / "other.json"
        other.write_text(json.dumps(_baseline(suite="other")))
        args = ["--update-baseline", other]
    outcome, message = invoke(["bench", "suite", suite, "-o", out, *args])
    assert outcome == "error"
    for fragment in row.fragments:
        assert fragment in message, (fragment, message)
    assert not out.exists()


# -- class 4: one suite and one run per output folder ---------------------------------------------------------
def test_another_suite_needs_the_flag_and_keeps_the_first_suites_results(tmp_path):
    first, out = _suite(tmp_path), tmp_path / "out"
    assert _bench(first, "-o", out).exit_code == 0
    before = (out / "results.jsonl").read_text()
    other = _suite(tmp_path, SUITE.replace("name: tiny-h2", "name: other-h2"), name="other.yaml")
    outcome, message = invoke(["bench", "suite", other, "-o", out])
    assert outcome == "error" and "the output of suite 'tiny-h2'" in message and "--allow-other-suite" in message
    assert (out / "results.jsonl").read_text() == before  # untouched
    result = _bench(other, "-o", out, "--allow-other-suite")
    assert result.exit_code == 0, result.output
    assert (out / "results.tiny-h2.jsonl").read_text() == before  # moved, not lost
    suites = {json.loads(line)["suite"] for line in (out / "results.jsonl").read_text().splitlines()}
    assert suites == {"other-h2"} and json.loads((out / OWNER_NAME).read_text())["suite"] == "other-h2"


def test_a_folder_without_owner_record_is_owned_by_its_results(tmp_path):
    """Class 4: a folder written before the owner record existed: its results.jsonl names its suite."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.jsonl").write_text(json.dumps({"suite": "quick", "case_id": "a", "status": "ok", "key": "k"}) + "\n")
    outcome, message = invoke(["bench", "suite", _suite(tmp_path), "-o", out])
    assert outcome == "error" and "the output of suite 'quick'" in message


_HOLDER = """
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
os.write(fd, b"pid %d on test" % os.getpid())
print("locked", flush=True)
time.sleep(60)
"""


def test_a_second_run_on_a_locked_folder_is_refused_and_a_killed_holder_releases_it(tmp_path):
    """Class 4: the lock is the kernel's (flock), so a holder killed with SIGKILL never blocks a later run."""
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(out / LOCK_NAME)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        outcome, message = invoke(["bench", "suite", _suite(tmp_path), "-o", out])
        assert outcome == "error" and "in use by another run" in message and f"pid {holder.pid}" in message
        assert not (out / "results.jsonl").exists()
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
        holder.stdout.close()
    spec = load_suite(_suite(tmp_path))
    with claim_output(out, spec) as notes:  # the stale .lock file is no obstacle
        assert notes == []
        with claim_output(out, spec):  # re-entrant in one process (the command line, then run_suite)
            pass
    assert (out / LOCK_NAME).is_file()


@pytest.mark.parametrize("row", [
    Row(4, "output is a file", "", "file", ("(a file)",)),
    Row(4, "output is a dangling symlink", "", "dangling", ("does not exist",)),
], ids=str)
def test_an_output_that_cannot_be_a_folder_is_refused(row, tmp_path):
    out = tmp_path / "out"
    if row.new == "file":
        out.write_text("x")
    else:
        out.symlink_to(tmp_path / "nowhere")
    with pytest.raises(InputError) as err:
        with claim_output(out, {"name": "tiny-h2"}):
            pass
    for fragment in row.fragments:
        assert fragment in str(err.value)
