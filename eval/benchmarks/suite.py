"""The benchmark suite runner: scenes x noise levels x seeds x methods from a suite file.

A suite (``eval/suites/NAME.yaml`` or any YAML path) names ``scenes`` (sources ``render``, ``shared-gt``, ``gt``,
``synthetic``; optionally ``fallback`` and ``psf_sigma_hr_px``), ``noise`` levels (the sensor keys of the camera
set-up), ``seeds`` and ``methods`` (names or variants); the guide docs/guides/benchmarks.md gives every key.

Every case is ``(scene, noise, seed, method)``: one capture task per (scene, noise, seed), then one task per case
(:mod:`capssim.eval.benchmarks.captures`, :mod:`capssim.eval.benchmarks.cases`; scored by
:class:`capssim.eval.evaluate.CaptureScorer`), in this process or in parallel on Dask (``executors``).

``results.jsonl`` (:mod:`capssim.eval.benchmarks.results`) gets each case's line as it finishes, rewritten in plan
order at the end. Run again, a suite does only the missing cases: an ``ok`` case with the same case hash (capture,
method, options, device, reconstruction and scoring code fingerprints) is not redone. A result depends on its case
only (seeded noise and poses; every worker uses an in-process run's thread count), so Dask gives the same numbers.
Times and peak memory (:class:`~capssim.eval.benchmarks.provenance.PeakMemory`) are measured in the process that
runs the method, named by ``worker`` (``host:pid``).
"""

from __future__ import annotations

import datetime as _dt
import logging
import time
import traceback
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from capssim.errors import UnknownNameError
from capssim.reconstruct.registry import available_methods, resolve_device

from ..metrics import get_convention
from .captures import expand_render_scenes
from .cases import capture_task, forget_captures, method_task
from .executors import check_execution, open_executor
from .output_claim import claim_output
from .provenance import code_fingerprint, content_hash, environment
from .results import ResultsLog
from .suite_schema import SCENE_SOURCES, SUITES_DIR, available_suites, check_scene_memory, load_suite

log = logging.getLogger(__name__)

__all__ = ["SCENE_SOURCES", "SUITES_DIR", "BenchRun", "available_suites", "case_key", "load_suite", "plan",
           "run_suite"]

#: the source files whose change re-runs a case (cached captures are kept)
RECONSTRUCTION_CODE = ("reconstruct",)
SCORING_CODE = ("eval/metrics.py", "eval/mtf.py", "eval/star.py", "eval/evaluate.py", "eval/benchmarks/suite.py",
                "eval/benchmarks/cases.py")


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


def case_key(scene: str, noise: str, seed: int, method_label: str) -> str:
    """Readable, stable identity of a case in baselines: ``scene/noise/seedN/method``."""
    return f"{scene}/{noise}/seed{seed}/{method_label}"


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


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


def _cache_writes(chain: list[dict], noise: dict, seed: int) -> list[tuple]:
    """What a capture task of ``chain`` may write in the cache: its scenes' captures, and their
    noise-free renders (shared by the noise levels of a rendered scene)."""
    writes = [("capture", c["name"], noise["name"], seed) for c in chain]
    return writes + [("render", c.get("scene", c["name"]), seed) for c in chain if c["source"] == "render"]


class _SuiteRun:
    """The state of one run: the plan's groups and records, the results log, notes, labels."""

    def __init__(self, spec: dict, output: Path, *, device: str, cache: Path, fresh: bool, emit: Callable[..., None]):
        self.spec, self.emit, self.cache = spec, emit, cache
        self.results = ResultsLog(output / "results.jsonl", fresh=fresh)
        self.device = str(resolve_device(device))
        self.env = environment(self.device)
        self.convention = get_convention(spec.get("convention", "capssim")).name
        self.registered = available_methods()
        self.recon_code = code_fingerprint(*RECONSTRUCTION_CODE)
        self.scoring_code = code_fingerprint(*SCORING_CODE)
        self.run_id = uuid.uuid4().hex
        self.groups: list[tuple[dict, dict, int]] = []  # (scene, noise, seed) in plan order
        self.methods: list[dict] = []
        self.records: dict[int, dict] = {}  # plan index (group x methods + method) -> record
        self.pending: dict[int, dict] = {}  # plan index -> the record of a running case
        self.labels: dict[object, str] = {}
        self.notes: list[str] = []
        self.announced: set[str] = set()

    def note(self, message: str) -> None:
        if message not in self.notes:
            self.notes.append(message)
            self.emit("note", message=message)

    def finish_case(self, index: int, rec: dict, *, new: bool = True) -> None:
        self.records[index] = rec
        if new:
            self.results.append(rec)
        self.emit("done")

    def base(self, noise: dict, seed: int) -> dict:
        return {"suite": self.spec["name"], "noise": noise["name"], "seed": seed, "environment": self.env,
                "convention": self.convention}

    def submit_captures(self, executor, scene_by_name: dict) -> None:
        """One capture task per group; one that may write what an earlier one writes waits for it."""
        writers: dict[tuple, object] = {}
        for g, (scene, noise, seed) in enumerate(self.groups):
            chain = [scene] + ([scene_by_name[scene["fallback"]]] if scene.get("fallback") else [])
            writes = _cache_writes(chain, noise, seed)
            after = list({id(writers[w]): writers[w] for w in writes if w in writers}.values())
            tag = ("capture", g)
            self.labels[tag] = f"{scene['name']}/{noise['name']}/seed{seed}: capture"
            handle = executor.submit(capture_task, str(self.cache), self.run_id, chain, noise, seed, tag=tag,
                                     after=after, name=f"capture-{scene['name']}-{noise['name']}-{seed}",
                                     events=self.emit if executor.live_events else None)
            writers.update((w, handle) for w in writes)

    def on_capture(self, executor, g: int, outcome: dict | None, error: BaseException | None) -> None:
        scene, noise, seed = self.groups[g]
        if error is not None:  # the task itself did not finish (its worker died)
            outcome = {"entry": None, "scene": scene, "skip_reason": None, "events": [],
                       "failure": (f"capture {scene['name']}/{noise['name']}/seed{seed}: {type(error).__name__}: "
                                   f"{error}", "".join(traceback.format_exception(error, limit=8)))}
            self.emit("error", message=f"error: {outcome['failure'][0]}")
        for kind, info in outcome["events"]:
            self.emit(kind, **info)
        used = outcome["scene"]
        if outcome["entry"] is None:
            self.record_unavailable(g, outcome["skip_reason"], outcome["failure"])
            return
        if used["name"] != scene["name"]:
            self.note(f"{scene['name']} unavailable ({outcome['skip_reason']}); used {used['name']} instead")
        self.submit_cases(executor, g, outcome["entry"], used)

    def record_unavailable(self, g: int, skip_reason: str | None, failure: tuple[str, str] | None) -> None:
        scene, noise, seed = self.groups[g]
        for j, m in enumerate(self.methods):
            rec = dict(self.base(noise, seed), scene=scene["name"], method=m["label"], method_name=m["name"],
                       key=case_key(scene["name"], noise["name"], seed, m["label"]),
                       case_id=content_hash([scene["name"], noise, seed, m, "unavailable"])[:20])
            if failure is not None:
                rec.update(status="error", reason=failure[0], traceback=failure[1])
            else:
                rec.update(status="skipped", skip_kind="data", reason=skip_reason)
            self.finish_case(g * len(self.methods) + j, rec)

    def registers(self, method: dict) -> bool:
        """Whether ``method`` estimates the warps (and stores them with the capture for the next method)."""
        return (self.registered[method["name"]].input_kind == "caps" and not method["true_warps"]
                and method.get("calibration", "ideal") == "ideal")

    def submit_cases(self, executor, g: int, entry, scene: dict) -> None:
        """Every method on the capture of group ``g``: those done in an earlier run are taken from it.

        A method that registers the capture waits for the first one registering it the same way,
        and reuses its stored warps, as in a run in this process (no registration done twice).
        """
        requested, noise, seed = self.groups[g]
        registering: dict[str, object] = {}  # registration mode -> the first case that registers so
        for j, m in enumerate(self.methods):
            index = g * len(self.methods) + j
            key = case_key(scene["name"], noise["name"], seed, m["label"])
            cid = content_hash({"capture": entry.key, "method": m, "device": self.device, "recon": self.recon_code,
                                "scoring": self.scoring_code, "convention": self.convention})[:20]
            rec = dict(self.base(noise, seed), scene=scene["name"], requested_scene=requested["name"],
                       method=m["label"], method_name=m["name"], key=key, case_id=cid, capture=str(entry.path),
                       capture_key=entry.key, scene_source=scene["source"])
            previous = self.results.done(cid)
            if previous is not None:
                self.finish_case(index, previous, new=False)
            elif m["name"] not in self.registered:
                self.skip_unregistered(index, rec, m)
            else:
                self.pending[index] = rec
                self.labels[("case", index)] = key
                registrar = registering.get(m["registration"]) if self.registers(m) else None
                handle = executor.submit(method_task, rec, m, str(entry.path), entry.key, entry.info,
                                         device=self.device, convention=self.convention, tag=("case", index),
                                         case=True, after=[registrar] if registrar is not None else [], name=key)
                if self.registers(m):
                    registering.setdefault(m["registration"], handle)

    def on_case(self, index: int, rec: dict | None, error: BaseException | None) -> None:
        if error is not None:  # the task itself did not finish (its worker died)
            rec = dict(self.pending[index], status="error", reason=f"{type(error).__name__}: {error}",
                       traceback="".join(traceback.format_exception(error, limit=8)), finished=_now())
        del self.pending[index]
        for message in rec.pop("notes_for_run", []):
            self.note(message)
        if rec["status"] == "error":
            self.emit("error", message=f"error in {rec['key']}: {rec['reason']}")
        elif rec["status"] == "skipped":
            self.emit("skip", message=f"skipped {rec['key']}: {rec['reason']}")
        self.finish_case(index, rec)

    def skip_unregistered(self, index: int, rec: dict, method: dict) -> None:
        rec.update(status="skipped", skip_kind="method",
                   reason=f"method {method['name']!r} is not registered (available: "
                          f"{', '.join(self.registered) or 'none'})")
        if method["name"] not in self.announced:
            self.announced.add(method["name"])
            self.emit("skip", message=f"skipping every case of {method['label']}: {rec['reason']}")
        self.finish_case(index, rec)

    def execute(self, executor, scene_by_name: dict) -> None:
        self.submit_captures(executor, scene_by_name)
        for (kind, index), result, error in executor.completed():
            if not executor.live_events:  # the progress display shows the latest finished task
                self.emit("case", label=f"finished {self.labels[kind, index]}")
            if kind == "capture":
                self.on_capture(executor, index, result, error)
            else:
                self.on_case(index, result, error)


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
        Compute threads of each worker (default: :func:`capssim.threads.resolve_threads`'s).
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
    output = Path(output)
    with claim_output(output, spec, allow_other_suite=allow_other_suite) as claim_notes:
        run = _SuiteRun(spec, output, device=device, cache=Path(cache_dir) if cache_dir else output / "cache",
                        fresh=fresh, emit=emit)
        for message in claim_notes:
            run.note(message)
        execution = _execute(run, spec, plan_scenes, plan_methods, scene_by_name, workers=workers,
                             scheduler=scheduler, threads=threads)
    records = [run.records[i] for i in sorted(run.records)]
    return BenchRun(spec=spec, output=output, results_path=run.results.path, records=records,
                    environment=run.env, notes=run.notes, wall_time_s=time.perf_counter() - t_start,
                    execution=execution)


def _execute(run: _SuiteRun, spec: dict, plan_scenes: list[dict], plan_methods: list[dict], scene_by_name: dict,
             *, workers, scheduler, threads) -> dict:
    """Run the plan's groups x methods on the executor; ``results.jsonl`` rewritten in plan order. Returns
    where the cases ran."""
    emit = run.emit
    run.methods = plan_methods
    run.groups = [(scene, noise, int(seed)) for scene in plan_scenes for noise in spec["noise"]
                  for seed in spec["seeds"]]
    emit("start", total=len(run.groups) * len(run.methods))
    started = lambda tag: emit("case", label=run.labels[tag])  # noqa: E731
    try:
        with open_executor(workers=workers, scheduler=scheduler, threads=threads, started=started) as executor:
            execution = {"kind": executor.kind, "workers": getattr(executor, "workers", None),
                         "compute_threads": getattr(executor, "compute_threads", None)}
            run.execute(executor, scene_by_name)
    finally:
        forget_captures()
    run.results.finish([run.records[i] for i in sorted(run.records)])
    return execution
