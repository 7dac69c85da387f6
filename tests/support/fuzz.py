"""Shared pieces of the fuzz suite (tests/*/test_fuzz_*.py): Hypothesis settings, odd values, the CLI outcome.

Every fuzz test is derandomized (the same examples on every run, so CI is deterministic), has no
deadline (a machine shared with other jobs varies in speed) and keeps no example database.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import resource
import shutil
import traceback
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture
from capssim.cli import app
from capssim.errors import CapssimError
from capssim.runtime.resources import MEMORY_LIMIT_ENV
from capssim.simulate import simulate_capture

#: ``CAPSSIM_FUZZ_SCALE=N`` runs N times the examples (a longer search, locally; CI runs the default 1)
FUZZ_SCALE = float(os.environ.get("CAPSSIM_FUZZ_SCALE", "1"))


def fuzz_settings(max_examples: int) -> settings:
    """Derandomized, no deadline, no database: ``max_examples`` examples (times ``CAPSSIM_FUZZ_SCALE``),
    the same on every run."""
    return settings(max_examples=max(1, round(max_examples * FUZZ_SCALE)), derandomize=True, deadline=None,
                    database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


#: values every numeric option must survive: non-finite, signed, huge, tiny, and no number at all
ODD_WORDS = ["nan", "inf", "-inf", "NaN", "-0", "0", "-1", "1e300", "-1e300", "5e-324", "1e309", "abc", "", "1e",
             "0x10", "1_000", "2.5", "-0.5", "1000000000", "99999999999999999999999"]

#: a numeric option's odd value, as typed on the command line: never an ordinary mid-range value, so
#: a fuzzed command stays cheap (a valid size or count in the thousands would be a long, legal run)
odd_values = st.one_of(
    st.sampled_from(ODD_WORDS),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(max_value=0).map(str),
    st.integers(min_value=10**6, max_value=10**40).map(str),
    st.text(alphabet="0123456789.eE+-_xnaif ", max_size=10),
)

#: the words that must never be accepted by any numeric option
NEVER_VALID = ("nan", "NaN", "-inf", "-1e300")


def invoke(args: list) -> tuple[str, str]:
    """``capssim ARGS`` in this process, as the console entry point sees it: ``(outcome, message)``.

    ``outcome`` is ``ok`` (exit 0), ``error`` (a :class:`~capssim.errors.CapssimError`: the entry
    point prints its one-line message and exits 2) or ``usage`` (click refused the command line,
    exit 2). Anything else (another exception, another exit status) fails the calling test with
    the traceback.
    """
    handlers = logging.root.handlers[:]
    try:
        result = CliRunner().invoke(app, [str(a) for a in args])
    finally:  # the CLI points logging at the runner's stream; give the old handlers back
        logging.root.handlers[:] = handlers
    exc = result.exception
    if result.exit_code == 0:
        return "ok", result.output
    if isinstance(exc, CapssimError):
        message = str(exc)
        assert message and "\n" not in message.strip(), f"capssim {args}: a message of several lines: {message!r}"
        return "error", message
    if isinstance(exc, SystemExit) and result.exit_code == 2:
        assert "Traceback" not in result.output, result.output
        return "usage", result.output
    trace = "".join(traceback.format_exception(exc)) if exc is not None and not isinstance(exc, SystemExit) else ""
    raise AssertionError(f"capssim {' '.join(map(str, args))}: exit {result.exit_code}\n{result.output}\n{trace}")


def peak_rss_bytes() -> int:
    """This process's peak resident memory so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


#: the most a fuzz module may raise this process's peak memory: a huge allocation fails the module
PEAK_GROWTH_LIMIT = 1536 * 2**20


@contextmanager
def address_space_headroom(gib: float):
    """Cap this process's address space at its present size plus ``gib`` GiB (``RLIMIT_AS``), so that an
    allocation a guard missed fails with a MemoryError here instead of taking the machine's memory."""
    with open("/proc/self/status", encoding="ascii") as fh:
        vm_size = next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmSize:"))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (vm_size + int(gib * 2**30), hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def one_line_error(exc: BaseException) -> str:
    """The message of a refused input: a :class:`CapssimError` with one non-empty line, else the test fails."""
    if not isinstance(exc, CapssimError):
        raise AssertionError("not a capssim error:\n" + "".join(traceback.format_exception(exc))) from exc
    message = str(exc)
    assert message.strip() and "\n" not in message.strip(), f"a message of several lines: {message!r}"
    return message


def run_main(args: list, capsys, monkeypatch, *, quiet: bool = False) -> tuple[int | None, str, str]:
    """``capssim [-q] ARGS`` through the console entry point :func:`capssim.cli.main`, in this process.

    Returns the exit status (``SystemExit.code``, ``None`` for 0) and the captured stdout and stderr; the
    root logger's handlers (which the CLI points at the captured stream) are restored.
    """
    import sys

    from capssim.cli import main

    monkeypatch.setattr(sys, "argv", ["capssim", *(["-q"] if quiet else []), *map(str, args)])
    capsys.readouterr()  # what was printed before the command (e.g. a log line through a stale handler) is not its
    handlers = logging.root.handlers[:]
    try:
        try:
            main()
        except SystemExit as exc:
            code = exc.code
        else:
            raise AssertionError(f"capssim {args}: main() returned without exiting")
    finally:  # the CLI points logging at the captured stream; give the old handlers back
        logging.root.handlers[:] = handlers
    out = capsys.readouterr()
    return code, out.out, out.err


def run_cli(args: list, capsys, monkeypatch, *, quiet: bool = False) -> tuple[int, str]:
    """``capssim [-q] ARGS`` (:func:`run_main`): the exit status (0 for success) and what it printed, stderr
    alone with ``quiet`` (``-q``: no log lines), else stdout + stderr."""
    status, out, err = run_main(args, capsys, monkeypatch, quiet=quiet)
    return status or 0, err if quiet else out + err


def one_error_line(status: int, text: str, *fragments: str, skip_log_lines: bool = False,
                   forbidden: tuple = ()) -> str:
    """The one ``error: ...`` line of a refused command (exit 2, no traceback), holding every fragment and
    none of ``forbidden``; ``skip_log_lines`` leaves out ``INFO``/``WARNING`` log lines before counting."""
    assert status == 2, text
    assert "Traceback" not in text, text
    lines = [line for line in text.splitlines()
             if line.strip() and not (skip_log_lines and line.startswith(("INFO", "WARNING")))]
    assert len(lines) == 1 and lines[0].startswith("error: "), text
    for fragment in fragments:
        assert fragment in lines[0], (fragment, text)
    for word in forbidden:
        assert word not in lines[0], (word, text)
    return lines[0]


def refused_before_work(args: list, root, capsys, monkeypatch, *, fragments: tuple = (), forbid=(),
                        env: dict | None = None, not_in: tuple = (), absent: tuple = ()) -> str:
    """Run ``capssim -q ARGS`` (``{root}`` in an argument is the test's folder ``root``) with the command's work
    ``forbid`` (``"module:function"``, one or several) replaced by a function that fails the test, under the
    environment ``env`` (the memory limit of the machine unset otherwise); the command must be refused in one
    ``error:`` line holding every fragment and none of ``not_in``, and leave none of ``absent`` (paths under
    ``root``). Returns the line."""
    monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
    for key, value in (env or {}).items():
        monkeypatch.setenv(key, value)
    for target in ((forbid,) if isinstance(forbid, str) and forbid else tuple(forbid or ())):
        module, name = target.split(":")

        def must_not_run(*_args, _target=target, **_kwargs):
            raise AssertionError(f"{_target} ran: the input was not refused before the work")
        monkeypatch.setattr(importlib.import_module(module), name, must_not_run)
    status, err = run_cli([str(a).replace("{root}", str(root)) for a in args], capsys, monkeypatch, quiet=True)
    line = one_error_line(status, err, *fragments, forbidden=not_in)
    for path in absent:
        assert not (root / path).exists(), f"{path} was created before the refusal"
    return line


# -- meta.json edits (the hardening rounds' capture refusals) -------------------------------------------
def set_key(*keys, value):
    """An edit of a mapping that sets ``value`` at the nested ``keys``."""
    def edit(data):
        for key in keys[:-1]:
            data = data[key]
        data[keys[-1]] = value
    return edit


def small_gaussian_capture(folder: Path) -> Path:
    """A 32x32 HR capture folder (a seeded random scene, sigma 0.01, seed 1) written to ``folder``."""
    rng = np.random.default_rng(0)
    gt = (0.2 + 0.5 * rng.random((12, 32, 32))).astype(np.float32)
    write_capture(folder, simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=1))
    return folder


def edited_capture(src: Path, dst: Path, edit) -> Path:
    """A copy of the capture folder ``src`` at ``dst`` whose ``meta.json`` went through ``edit(meta)``; an edit
    that returns a string writes that text instead."""
    shutil.copytree(src, dst)
    meta = json.loads((dst / "meta.json").read_text())
    text = edit(meta)
    (dst / "meta.json").write_text(text if isinstance(text, str) else json.dumps(meta))
    return dst
