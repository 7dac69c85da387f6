"""The error budget of every case of a suite: one task per capture, one per (capture, method).

The captures are the suite's own (:func:`~capssim.eval.benchmarks.cases.capture_task`, the same
cache and seeds as ``capssim bench suite``); each case's ladder (:func:`~.ladder.run_ladder`) runs in
one task, in this process or on Dask (:func:`~capssim.eval.benchmarks.executors.open_executor`).
``budget.jsonl`` gets each case's line as soon as it finishes; a run started again does only the
cases missing or changed (the case hash covers the capture, the method, the device, the views and
fingerprints of the reconstruction, scoring and budget code).
"""

from __future__ import annotations

import time
import traceback
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from capssim.capture import read_capture
from capssim.errors import InputError, UnknownNameError
from capssim.reconstruct.registry import available_methods, resolve_device

from ..benchmarks.cases import capture_task, forget_captures
from ..benchmarks.executors import check_execution, open_executor
from ..benchmarks.provenance import code_fingerprint, content_hash
from ..benchmarks.results import ResultsLog, read_results
from ..benchmarks.suite import RECONSTRUCTION_CODE, SCORING_CODE, case_key, plan
from ..evaluate import CaptureScorer
from ..metrics import get_convention
from .ladder import run_ladder

#: the methods of the results page (issue 32): the paper's method, its cascade ablation, the
#: camera-array baseline, the best classical and the learned DoFP method, and capssim's caps-plus and its
#: prior-choice ablation caps-plus-cv
BUDGET_METHODS = ("caps", "caps-iccp", "caps-naive", "dofp-igri2", "cpdnet", "caps-plus", "caps-plus-cv")
#: the code whose change redoes a case (the report, plots and command do not change a number)
BUDGET_CODE = ("eval/error_budget/ladder.py", "eval/error_budget/oracles.py")
RESULTS_NAME = "budget.jsonl"


@dataclass
class BudgetRun:
    """A finished budget run: ``records`` in plan order (scene x noise x seed x method)."""

    spec: dict
    output: Path
    results_path: Path
    records: list[dict]
    wall_time_s: float = 0.0
    execution: dict = field(default_factory=dict)

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
            entries.append({"name": name, "label": name, "options": {}, "registration": "local-correlation",
                            "true_warps": False})
        else:
            raise UnknownNameError("--method", name, sorted(registered))
    if len({e["label"] for e in entries}) != len(entries):
        raise InputError("--method", list(names), "each method once")
    return entries


def budget_task(rec: dict, method: dict, capture_path: str, *, device: str, convention: str, views: bool) -> dict:
    """The ladder of one case (``rec`` holds its identity); never raises: a failure is in the record."""
    rec = dict(rec)
    t0 = time.perf_counter()
    try:
        capture = read_capture(capture_path, require_gt=True)
        if available_methods()[method["name"]].input_kind == "dofp" and capture.dofp_raw is None:
            rec.update(status="skipped", reason="this capture has no DoFP frame")
            return rec
        scorer = CaptureScorer(capture, convention=convention)
        rec.update(status="ok", **run_ladder(capture, method, scorer, device=device, views=views))
    except Exception as exc:  # one failing case must not stop the budget
        rec.update(status="error", reason=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc(limit=8))
    rec["wall_time_s"] = time.perf_counter() - t0
    return rec


class _BudgetRun:
    def __init__(self, spec: dict, output: Path, methods: list[dict], *, device: str, cache: Path, fresh: bool,
                 views: bool, emit: Callable[..., None]):
        self.spec, self.methods, self.cache, self.views, self.emit = spec, methods, cache, views, emit
        self.device = str(resolve_device(device))
        self.convention = get_convention(spec.get("convention", "capssim")).name
        self.results = ResultsLog(output / RESULTS_NAME, fresh=fresh)
        self.code = code_fingerprint(*RECONSTRUCTION_CODE, *SCORING_CODE, *BUDGET_CODE)
        self.run_id = uuid.uuid4().hex
        self.groups: list[tuple[dict, dict, int]] = []
        self.records: dict[int, dict] = {}

    def finish(self, index: int, rec: dict, *, new: bool = True) -> None:
        self.records[index] = rec
        if new:
            self.results.append(rec)
        self.emit("done", label=rec["key"], status=rec["status"])

    def base(self, g: int, m: dict, scene_name: str) -> dict:
        _, noise, seed = self.groups[g]
        return {"suite": self.spec["name"], "scene": scene_name, "noise": noise["name"], "seed": seed,
                "method": m["label"], "method_name": m["name"], "convention": self.convention,
                "device": self.device, "key": case_key(scene_name, noise["name"], seed, m["label"])}

    def on_capture(self, executor, g: int, outcome: dict | None, error: BaseException | None) -> None:
        scene = self.groups[g][0]
        entry = None if outcome is None or error is not None else outcome["entry"]
        if entry is None:
            reason = (f"{type(error).__name__}: {error}" if error is not None
                      else (outcome["failure"] or (outcome["skip_reason"], ""))[0])
            status = "skipped" if error is None and outcome["failure"] is None else "error"
            for j, m in enumerate(self.methods):
                rec = dict(self.base(g, m, scene["name"]), status=status, reason=reason,
                           case_id=content_hash([scene["name"], self.groups[g][1:], m, "unavailable"])[:20])
                self.finish(g * len(self.methods) + j, rec)
            return
        used = outcome["scene"]["name"]
        for j, m in enumerate(self.methods):
            cid = content_hash({"capture": entry.key, "method": m, "device": self.device, "code": self.code,
                                "views": self.views, "convention": self.convention})[:20]
            rec = dict(self.base(g, m, used), case_id=cid, capture=str(entry.path), capture_key=entry.key,
                       scene_source=outcome["scene"]["source"], requested_scene=scene["name"])
            previous = self.results.done(cid)
            if previous is not None:
                self.finish(g * len(self.methods) + j, previous, new=False)
                continue
            executor.submit(budget_task, rec, m, str(entry.path), device=self.device, convention=self.convention,
                            views=self.views, tag=("case", g * len(self.methods) + j), case=True, name=rec["key"])

    def execute(self, executor, scene_by_name: dict) -> None:
        for g, (scene, noise, seed) in enumerate(self.groups):
            chain = [scene] + ([scene_by_name[scene["fallback"]]] if scene.get("fallback") else [])
            executor.submit(capture_task, str(self.cache), self.run_id, chain, noise, seed, tag=("capture", g),
                            name=f"capture-{scene['name']}-{noise['name']}-{seed}")
        for (kind, index), result, error in executor.completed():
            if kind == "capture":
                self.on_capture(executor, index, result, error)
            else:
                if error is not None:
                    result = {"key": f"case {index}", "status": "error", "reason": f"{type(error).__name__}: {error}",
                              "case_id": f"lost-{index}"}
                self.finish(index, result)


def run_budget(spec: dict, output: str | Path, *, methods=None, scenes=None, device: str = "cpu",
               cache_dir: str | Path | None = None, fresh: bool = False, workers: int | None = None,
               scheduler: str | None = None, threads: int | None = None, views: bool = False,
               events: Callable[..., None] | None = None) -> BudgetRun:
    """Run (or resume) the error budget of a suite's cases into ``output``.

    Parameters
    ----------
    spec : dict
        A suite (:func:`capssim.eval.benchmarks.suite.load_suite`): its scenes, noise levels and seeds.
    output : str or pathlib.Path
        The run's folder: ``budget.jsonl`` (one line per case), the captures' cache (``cache/``).
    methods : sequence of str, optional
        Method labels or names (default: the suite's methods; :data:`BUDGET_METHODS` are the eight of the
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
        ``events(kind, **info)``: ``start`` (``total``), ``done`` (``label``, ``status``).

    Returns
    -------
    BudgetRun
    """
    emit = events or (lambda kind, **info: None)
    t0 = time.perf_counter()
    entries = budget_methods(spec, list(methods) if methods else None)
    plan_scenes, scene_by_name, _ = plan(spec, methods=None, scenes=list(scenes) if scenes else None, emit=emit)
    check_execution(workers=workers, scheduler=scheduler)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    run = _BudgetRun(spec, output, entries, device=device, cache=Path(cache_dir) if cache_dir else output / "cache",
                     fresh=fresh, views=views, emit=emit)
    run.groups = [(s, n, int(seed)) for s in plan_scenes for n in spec["noise"] for seed in spec["seeds"]]
    emit("start", total=len(run.groups) * len(entries))
    try:
        with open_executor(workers=workers, scheduler=scheduler, threads=threads) as executor:
            execution = {"kind": executor.kind, "workers": getattr(executor, "workers", None)}
            run.execute(executor, scene_by_name)
    finally:
        forget_captures()
    records = [run.records[i] for i in sorted(run.records)]
    run.results.finish(records)
    return BudgetRun(spec=spec, output=output, results_path=run.results.path, records=records,
                     wall_time_s=time.perf_counter() - t0, execution=execution)


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


__all__ = ["BUDGET_METHODS", "BudgetRun", "budget_methods", "budget_task", "load_budget", "run_budget"]
