"""The error budget of every case of a suite: one task per capture, one per (capture, method).

The captures are the suite's own (:func:`~capssim.eval.benchmarks.cases.capture_task`, the same
cache and seeds as ``capssim bench suite``), and the cases run through the same case runner
(:func:`capssim.eval.benchmarks.runner.run_cases`: the folder's lock and owner file
``bench-budget.json``, cache-write and registration order, case hash, results log, notes); the
per-case task here is :func:`budget_task`, each case's ladder (:func:`~.ladder.run_ladder`), in this
process or on Dask. ``budget.jsonl`` gets each case's line as soon as it finishes; a run started again
does only the cases missing or changed (the case hash covers the capture, the method, the device, the
views and fingerprints of the reconstruction, scoring and budget code).
"""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from capssim.captures.capture import read_capture
from capssim.errors import InputError, UnknownNameError
from capssim.reconstruct.registry import available_methods, default_registration, resolve_device

from ..benchmarks.executors import check_execution
from ..benchmarks.output_claim import BUDGET_OUTPUT
from ..benchmarks.provenance import code_fingerprint
from ..benchmarks.results import read_results
from ..benchmarks.runner import CaseTask, run_cases
from ..benchmarks.suite import RECONSTRUCTION_CODE, SCORING_CODE, plan
from ..evaluate import CaptureScorer
from .ladder import run_ladder

#: the methods of the results page (issue 32): the paper's method, its cascade ablation, the two
#: camera-array methods without iterations (the baseline and array-kr), the best classical and the two learned DoFP
#: methods, and capssim's caps-plus and its prior-choice ablation caps-plus-cv
BUDGET_METHODS = ("caps", "caps-iccp", "caps-naive", "array-kr", "dofp-igri2", "cpdnet", "dofp-nafnet", "caps-plus",
                  "caps-plus-cv")
#: the code whose change redoes a case (the report, plots and command do not change a number)
BUDGET_CODE = ("eval/error_budget/ladder.py", "eval/error_budget/oracles.py")
RESULTS_NAME = BUDGET_OUTPUT.results_name


@dataclass
class BudgetRun:
    """A finished budget run: ``records`` in plan order (scene x noise x seed x method)."""

    spec: dict
    output: Path
    results_path: Path
    records: list[dict]
    wall_time_s: float = 0.0
    execution: dict = field(default_factory=dict)
    #: what the run wants its reader to know (a fallback scene used, a handed-over folder)
    notes: list[str] = field(default_factory=list)

    @property
    def n_errors(self) -> int:
        return sum(r["status"] == "error" for r in self.records)


def budget_methods(spec: dict, names=None) -> list[dict]:
    """The method entries of a budget: the suite's own (``names`` None), else each name's entry in the
    suite (by label or name) or a plain entry of a registered method (defaults, estimated warps)."""
    registered = available_methods()
    suite_entries = [m for m in spec["methods"] if not m.get("true_warps")]
    if not names:
        return [m for m in suite_entries if m["name"] in registered]
    entries = []
    for name in names:
        found = [m for m in suite_entries if m["label"] == name] or [m for m in suite_entries if m["name"] == name]
        if found:
            entries.append(found[0])
        elif name in registered:
            entries.append({"name": name, "label": name, "options": {}, "registration": default_registration(name),
                            "true_warps": False})
        else:
            raise UnknownNameError("--method", name, sorted(registered))
    if len({e["label"] for e in entries}) != len(entries):
        raise InputError("--method", list(names), "each method once")
    return entries


def check_budget(spec: dict, *, methods=None, scenes=None, workers: int | None = None,
                 scheduler: str | None = None) -> None:
    """Every check of a budget run that needs no work (``-m``, ``--scene``, scene memory, ``--workers``/
    ``--scheduler``), for the command line to make before it claims the output folder."""
    budget_methods(spec, list(methods) if methods else None)
    plan(spec, methods=None, scenes=list(scenes) if scenes else None, emit=lambda kind, **info: None)
    check_execution(workers=workers, scheduler=scheduler)


def budget_task(rec: dict, method: dict, capture_path: str, capture_key: str, capture_info: dict, *, device: str,
                convention: str, views: bool) -> dict:
    """The ladder of one case (``rec`` holds its identity), a task of the case runner
    (:class:`~capssim.eval.benchmarks.runner.CaseTask`); never raises: a failure is in the record."""
    rec = dict(rec)
    t0 = time.perf_counter()
    try:
        capture = read_capture(capture_path, require_gt=True)
        if available_methods()[method["name"]].input_kind == "dofp" and capture.dofp_raw is None:
            rec.update(status="skipped", skip_kind="data", reason="this capture has no DoFP frame")
            return rec
        scorer = CaptureScorer(capture, convention=convention)
        rec.update(status="ok", **run_ladder(capture, method, scorer, device=device, views=views))
    except Exception as exc:  # one failing case must not stop the budget
        rec.update(status="error", reason=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc(limit=8))
    rec["wall_time_s"] = time.perf_counter() - t0
    return rec


def run_budget(spec: dict, output: str | Path, *, methods=None, scenes=None, device: str = "cpu",
               cache_dir: str | Path | None = None, fresh: bool = False, workers: int | None = None,
               scheduler: str | None = None, threads: int | None = None, views: bool = False,
               events: Callable[..., None] | None = None, allow_other_suite: bool = False) -> BudgetRun:
    """Run (or resume) the error budget of a suite's cases into ``output``.

    Parameters
    ----------
    spec : dict
        A suite (:func:`capssim.eval.benchmarks.suite.load_suite`): its scenes, noise levels and seeds.
    output : str or pathlib.Path
        The run's folder: ``budget.jsonl`` (one line per case), the captures' cache (``cache/``).
    methods : sequence of str, optional
        Method labels or names (default: the suite's methods; :data:`BUDGET_METHODS` are the nine of the
        results page); a name not in the suite runs with its defaults.
    scenes : sequence of str, optional
        Only these scenes of the suite.
    device, threads : keyword-only
        Torch device; compute threads of each worker.
    cache_dir, fresh : keyword-only
        The captures' cache (default ``output/cache``; a suite run's cache can be shared); redo every case.
    workers, scheduler : keyword-only
        A local Dask cluster of that many processes, or the one at that address (default: this process).
    views : bool, keyword-only
        Also compute the second views at the ceiling (:func:`~.ladder.run_ladder`; the converged view
        costs four ceiling runs).
    events : callable, optional
        ``events(kind, **info)``: ``start`` (``total``), ``done`` (``label``, ``status``), ``note``, ``skip``,
        ``error`` (``message``).
    allow_other_suite : bool, keyword-only
        Hand over an ``output`` whose ``budget.jsonl`` another suite owns (its records are moved to
        ``budget.<other-suite>.jsonl``); else a second suite into one folder is refused with one line.
        The run holds the folder's lock throughout (a second run on it is refused).

    Returns
    -------
    BudgetRun
    """
    t0 = time.perf_counter()
    entries = budget_methods(spec, list(methods) if methods else None)
    emit = events or (lambda kind, **info: None)
    plan_scenes, scene_by_name, _ = plan(spec, methods=None, scenes=list(scenes) if scenes else None, emit=emit)
    dev = str(resolve_device(device))
    task = CaseTask(budget_task, BUDGET_OUTPUT, options={"views": bool(views)}, record={"device": dev},
                    identity={"code": code_fingerprint(*RECONSTRUCTION_CODE, *SCORING_CODE, *BUDGET_CODE),
                              "views": bool(views)})
    outcome = run_cases(spec, output, task, plan_scenes=plan_scenes, plan_methods=entries, scene_by_name=scene_by_name,
                        device=device, cache_dir=cache_dir, fresh=fresh, workers=workers, scheduler=scheduler,
                        threads=threads, events=emit, allow_other_suite=allow_other_suite)
    return BudgetRun(spec=spec, output=Path(output), results_path=outcome.results_path, records=outcome.records,
                     wall_time_s=time.perf_counter() - t0, execution=outcome.execution, notes=outcome.notes)


def load_budget(spec: dict, output: str | Path, *, methods=None, scenes=None) -> BudgetRun:
    """The stored records of a budget run (``output/budget.jsonl``), nothing run: for rewriting its reports.

    ``methods`` (labels) and ``scenes`` keep only those cases; the records are those of whatever code
    wrote them (their ``case_id`` hashes it). :class:`~capssim.errors.InputError` if there is no record.
    """
    path = Path(output) / RESULTS_NAME
    records = [r for r in read_results(path).values() if r.get("suite", spec["name"]) == spec["name"]
               and (not methods or r.get("method") in methods) and (not scenes or r.get("scene") in scenes)]
    if not records:
        raise InputError("--report-only", str(path), "a budget.jsonl with this suite's cases",
                         f"Run `capssim bench budget {spec['name']} -o {output}` first.")
    return BudgetRun(spec=spec, output=Path(output), results_path=path, records=records,
                     execution={"kind": "stored"})


__all__ = ["BUDGET_METHODS", "BudgetRun", "budget_methods", "budget_task", "check_budget", "load_budget", "run_budget"]
