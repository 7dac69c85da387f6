"""Who writes a run's output folder (``-o``): one run at a time, for one suite.

``capssim bench suite`` and ``capssim bench budget`` hold their folders the same way (the one case
runner, :mod:`.runner`, claims it); each kind of run has its own results and owner files
(:class:`OutputKind`: :data:`SUITE_OUTPUT`, :data:`BUDGET_OUTPUT`), and both share the lock, since they
share the folder's capture cache.

* **The lock.** :func:`claim_output` takes an exclusive ``fcntl.flock`` on ``OUT/.lock`` for the
  whole run (cases, report, plots, baseline). A second run on the same folder, in another process,
  is refused at once with one line naming the holder's process and command. The kernel releases the lock when
  its process ends, however it ends (Ctrl-C, ``kill -9``, a lost machine): a stale ``.lock`` file
  never blocks a later run, and an interrupted run resumes as before. Within one thread the claim
  is re-entrant (the command line claims the folder, then :func:`~.suite.run_suite` does again);
  another thread of the same process is refused like another process.
* **The owner.** ``OUT/bench-suite.json`` (``OUT/bench-budget.json`` for a budget) records the suite
  that owns the folder (its name, file and hash). A run of another suite into that folder (or into one
  whose ``results.jsonl``, ``budget.jsonl``, holds another suite's cases) is refused unless
  ``allow_other_suite`` (``--allow-other-suite``) is given: the folder is then handed over, and the other
  suite's records are moved, not lost, to ``OUT/results.<other-suite>.jsonl`` (``budget.<other-suite>.jsonl``),
  so that the results file and the report hold one suite only.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
import platform
import re
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from capssim.errors import InputError
from capssim.imageio import atomic_write_json, atomic_write_text

from .results import read_results, results_text

LOCK_NAME = ".lock"
OWNER_SCHEMA = "capssim.bench-output"
ALLOW_FLAG = "--allow-other-suite"


@dataclass(frozen=True)
class OutputKind:
    """The files one kind of run owns in its folder: ``command`` (in messages), results and owner file."""

    command: str
    results_name: str
    owner_name: str

    @property
    def archive_stem(self) -> str:
        """``results`` for ``results.jsonl``: another suite's records go to ``<stem>.<suite>.jsonl``."""
        return self.results_name.rsplit(".", 1)[0]


SUITE_OUTPUT = OutputKind("bench suite", "results.jsonl", "bench-suite.json")
BUDGET_OUTPUT = OutputKind("bench budget", "budget.jsonl", "bench-budget.json")
OWNER_NAME = SUITE_OUTPUT.owner_name

#: the folders this process's threads hold: (resolved path, thread) -> [descriptor, depth, kinds whose owner was checked]
_HELD: dict[tuple[str, int], list] = {}


def _check_folder(output: Path) -> None:
    """Refuse an ``-o`` that cannot be a folder (a file, a dangling symlink), before any work."""
    if output.is_symlink() and not output.exists():
        raise InputError("-o", f"{output} (a symlink to {os.readlink(output)!r}, which does not exist)",
                         "an output folder", "Remove the symlink or point -o at a folder.")
    if output.exists() and not output.is_dir():
        raise InputError("-o", f"{output} (a file)", "an output folder (resumed if it exists)",
                         "Use another -o, or remove the file.")
    try:
        output.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError("-o", f"{output} ({exc.strerror or type(exc).__name__})", "a folder this user can create",
                         "Use another -o.") from None


def _owner_of(output: Path, kind: OutputKind) -> dict | None:
    """The owner record of ``output`` (None: none, or unreadable: the results then say who wrote it)."""
    try:
        owner = json.loads((output / kind.owner_name).read_text())
    except (OSError, ValueError):
        return None
    return owner if isinstance(owner, dict) and isinstance(owner.get("suite"), str) else None


def _archive_name(output: Path, suite: str, kind: OutputKind) -> Path:
    stem = f"{kind.archive_stem}." + (re.sub(r"[^A-Za-z0-9_.-]", "_", suite) or "other")
    path, n = output / f"{stem}.jsonl", 2
    while path.exists():
        path, n = output / f"{stem}-{n}.jsonl", n + 1
    return path


def _check_owner(output: Path, spec: dict, allow_other_suite: bool, kind: OutputKind) -> list[str]:
    """Refuse another suite's folder (module docstring), or hand it over; returns notes for the run."""
    owner = _owner_of(output, kind)
    results = output / kind.results_name
    records = read_results(results)
    others = sorted({r.get("suite") for r in records.values() if r.get("suite") != spec["name"]} - {None})
    if owner is not None and owner["suite"] != spec["name"]:
        others = sorted(set(others) | {owner["suite"]})
    notes = []
    if others and not allow_other_suite:
        raise InputError("-o", f"{output} (the output of suite {others[0]!r})", f"an output folder of suite "
                         f"{spec['name']!r} or a new one", f"Use another -o, or add {ALLOW_FLAG} to hand it over "
                         f"(the other suite's results are kept in {kind.archive_stem}.{others[0]}.jsonl).")
    if others:
        mine = [r for r in records.values() if r.get("suite") == spec["name"]]
        moved = [r for r in records.values() if r.get("suite") != spec["name"]]
        if moved:
            archive = _archive_name(output, others[0], kind)
            atomic_write_text(archive, results_text(moved))
            atomic_write_text(results, results_text(mine))
            notes.append(f"{output} held suite {', '.join(others)}: its {len(moved)} result(s) moved to {archive.name}")
    if owner is None or owner["suite"] != spec["name"] or owner.get("suite_sha256") != spec.get("sha256"):
        atomic_write_json(output / kind.owner_name, {
            "schema": OWNER_SCHEMA, "suite": spec["name"], "suite_path": spec.get("path"),
            "suite_sha256": spec.get("sha256"),
            "claimed": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")})
    return notes


def _lock(output: Path, kind: OutputKind, spec: dict) -> int:
    """An exclusive, non-blocking flock on ``OUT/.lock``: its descriptor, or a one-line refusal."""
    path = output / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise InputError("-o", f"{output} (cannot open {LOCK_NAME}: {exc.strerror})", "a writable output folder",
                         "Use another -o.") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise InputError("-o", f"{output} (in use by another run: {holder})",
                         "an output folder no other run is writing",
                         "Wait for that run to finish, or use another -o.") from None
    os.ftruncate(fd, 0)
    command = f"capssim {kind.command} {spec.get('name', '?')}"
    os.pwrite(fd, f"pid {os.getpid()} on {platform.node()}, {command}\n".encode(), 0)
    return fd


@contextmanager
def claim_output(output: str | Path, spec: dict, *, allow_other_suite: bool = False, kind: OutputKind = SUITE_OUTPUT):
    """Hold ``output`` for a ``kind`` run of ``spec`` (module docstring): the lock, then the owner check.

    Yields the notes of the claim (a handed-over folder). Raises :class:`InputError` (one line) for a
    folder that another run holds, another suite owns, or that cannot be created.
    """
    output = Path(output)
    _check_folder(output)
    key = (str(output.resolve()), threading.get_ident())
    if key in _HELD:  # this process holds it (the command line around the runner)
        held = _HELD[key]
        notes = [] if kind in held[2] else _check_owner(output, spec, allow_other_suite, kind)
        held[2].add(kind)
        held[1] += 1
        try:
            yield notes
        finally:
            held[1] -= 1
        return
    fd = _lock(output, kind, spec)
    try:
        notes = _check_owner(output, spec, allow_other_suite, kind)
        _HELD[key] = [fd, 1, {kind}]
        yield notes
    finally:
        _HELD.pop(key, None)
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


__all__ = ["ALLOW_FLAG", "BUDGET_OUTPUT", "LOCK_NAME", "OWNER_NAME", "SUITE_OUTPUT", "OutputKind", "claim_output"]
