"""The benchmark suite runner: scenes x noise levels x seeds x methods from a suite file.

A suite (``eval/suites/NAME.yaml`` or any YAML path) names ``scenes`` (sources ``render``, ``shared-gt``, ``gt``,
``synthetic``; optionally ``fallback`` and ``psf_sigma_hr_px``), ``noise`` levels (the sensor keys of the camera
set-up), ``seeds`` and ``methods`` (names or variants); the guide docs/guides/benchmarks.md gives every key.

Every case is ``(scene, noise, seed, method)``: one capture task per (scene, noise, seed), then one task per case
(:mod:`capssim.eval.benchmarks.captures`, :mod:`capssim.eval.benchmarks.cases`; scored by
:class:`capssim.eval.evaluate.CaptureScorer`), in this process or in parallel on Dask (``executors``), by the case
runner that ``capssim bench budget`` shares (:mod:`capssim.eval.benchmarks.runner`; the suite's task is
:func:`~capssim.eval.benchmarks.cases.method_task`).

``results.jsonl`` (:mod:`capssim.eval.benchmarks.results`) gets each case's line as it finishes, rewritten in plan
order at the end. Run again, a suite does only the missing cases: an ``ok`` case with the same case hash (capture,
method, options, device, reconstruction and scoring code fingerprints) is not redone. A result depends on its case
only (seeded noise and poses; every worker uses an in-process run's thread count), so Dask gives the same numbers.
Times and peak memory (:class:`~capssim.eval.benchmarks.provenance.PeakMemory`) are measured in the process that
runs the method, named by ``worker`` (``host:pid``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from capssim.errors import UnknownNameError
from capssim.reconstruct.registry import resolve_device

from .captures import expand_render_scenes
from .cases import method_task
from .executors import check_execution
from .output_claim import SUITE_OUTPUT
from .provenance import code_fingerprint, environment
from .runner import CaseTask, case_key, run_cases
from .suite_schema import SCENE_SOURCES, SUITES_DIR, available_suites, check_scene_memory, load_suite

log = logging.getLogger(__name__)

__all__ = ["SCENE_SOURCES", "SUITES_DIR", "BenchRun", "available_suites", "case_key", "load_suite", "plan",
           "run_suite"]

#: the source files whose change re-runs a case (cached captures are kept)
RECONSTRUCTION_CODE = ("reconstruct",)
SCORING_CODE = ("eval/metrics.py", "eval/mtf.py", "eval/star.py", "eval/evaluate.py", "eval/uncertainty_scores.py",
                "eval/benchmarks/suite.py",
                "eval/benchmarks/cases.py", "eval/benchmarks/runner.py")


# -- results -------------------------------------------------------------------------------------
@dataclass
class BenchRun:
    spec: dict
    output: Path
    results_path: Path
    records: list[dict]  # this plan's records, in plan order
    environment: dict
    notes: list[str] = field(default_factory=list)
    wall_time_s: float = 0.0
    #: where the cases ran: ``{kind: in-process|dask, workers, compute_threads}``
    execution: dict = field(default_factory=dict)

    @property
    def n_errors(self) -> int:
        return sum(r["status"] == "error" for r in self.records)

    def ok_records(self) -> list[dict]:
        return [r for r in self.records if r["status"] == "ok"]


# -- the run -------------------------------------------------------------------------------------
def plan(spec: dict, *, methods: list[str] | None, scenes: list[str] | None, emit: Callable[..., None]):
    """``(scenes to run, every scene by name, method entries)`` of a suite, restricted to a subset; a scene
    too large for the memory limit is refused here (:func:`~.suite_schema.check_scene_memory`)."""
    method_entries = spec["methods"]
    if methods:
        known = {m["label"] for m in method_entries} | {m["name"] for m in method_entries}
        unknown = sorted(set(methods) - known)
        if unknown:
            raise UnknownNameError("suite method", unknown[0], sorted(known))
        method_entries = [m for m in method_entries if m["label"] in methods or m["name"] in methods]
    spec_scenes = expand_render_scenes(spec["scenes"], emit)
    scene_by_name = {s["name"]: s for s in spec_scenes}
    fallback_targets = {s["fallback"] for s in spec_scenes if s.get("fallback")}
    plan_scenes = [s for s in spec_scenes if s["name"] not in fallback_targets]
    if scenes:
        unknown = sorted(set(scenes) - set(scene_by_name))
        if unknown:
            raise UnknownNameError("suite scene", unknown[0], sorted(scene_by_name))
        plan_scenes = [scene_by_name[n] for n in scenes]
    check_scene_memory(spec, plan_scenes)  # the resource guard, before any work
    return plan_scenes, scene_by_name, method_entries


def run_suite(spec: dict, output: str | Path, *, methods: list[str] | None = None, scenes: list[str] | None = None,
              device: str = "cpu", cache_dir: str | Path | None = None, fresh: bool = False,
              workers: int | None = None, scheduler: str | None = None, threads: int | None = None,
              events: Callable[..., None] | None = None, allow_other_suite: bool = False) -> BenchRun:
    """Run (or resume) a suite into ``output`` (module docstring).

    Parameters
    ----------
    spec, output : dict, path
        A suite from :func:`load_suite`; the run's folder (``results.jsonl``).
    methods, scenes : list of str, optional
        Only these method labels / scene names (default: all).
    device : str
    cache_dir : path, optional
        The captures' cache (default ``output/cache``).
    fresh : bool
        Redo every case, also those already in ``results.jsonl``.
    workers, scheduler : optional
        A local Dask cluster of that many processes, or the one at that address (neither, or ``workers=0``: here).
    threads : int, optional
        Compute threads of each worker (default: :func:`capssim.runtime.threads.resolve_threads`'s).
    events : callable, optional
        ``events(kind, **info)``: ``start`` (``total``), ``case`` (``label``), ``done``, ``skip``, ``note``, ``error``.
    allow_other_suite : bool
        Hand over an ``output`` that another suite owns (:mod:`~.output_claim`; else an :class:`InputError`).
        The run holds the folder's lock throughout (a second run on it is refused).

    Returns
    -------
    BenchRun
        ``records`` (plan order), ``results_path``, ``wall_time_s``, ``n_errors``, ``ok_records()``.
    """
    emit = events or (lambda kind, **info: None)
    t_start = time.perf_counter()
    plan_scenes, scene_by_name, plan_methods = plan(spec, methods=methods, scenes=scenes, emit=emit)
    check_execution(workers=workers, scheduler=scheduler)  # before results.jsonl is touched
    env = environment(str(resolve_device(device)))
    task = CaseTask(method_task, SUITE_OUTPUT, record={"environment": env},
                    identity={"recon": code_fingerprint(*RECONSTRUCTION_CODE),
                              "scoring": code_fingerprint(*SCORING_CODE)})
    outcome = run_cases(spec, output, task, plan_scenes=plan_scenes, plan_methods=plan_methods,
                        scene_by_name=scene_by_name, device=device, cache_dir=cache_dir, fresh=fresh, workers=workers,
                        scheduler=scheduler, threads=threads, events=emit, allow_other_suite=allow_other_suite)
    return BenchRun(spec=spec, output=Path(output), results_path=outcome.results_path, records=outcome.records,
                    environment=env, notes=outcome.notes, wall_time_s=time.perf_counter() - t_start,
                    execution=outcome.execution)
