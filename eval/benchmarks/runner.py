"""The one case runner: a suite's cases, each a capture and a method, whatever is done per case.

``capssim bench suite`` (reconstruct and score, :func:`~.cases.method_task`) and ``capssim bench budget``
(the ladder of oracles, :func:`capssim.eval.error_budget.runner.budget_task`) run the same cases the same
way; only the per-case task differs, and it is the runner's argument (:class:`CaseTask`). The runner owns
the rest:

* **the output folder** (:func:`~.output_claim.claim_output`): its lock for the whole run and the suite
  that owns it, in the task's own owner file (``bench-suite.json``, ``bench-budget.json``);
* **the plan**: one capture task per (scene, noise, seed) group, then one case task per method entry,
  in plan order (group x methods + method);
* **the cache-write order**: a capture task that may write what an earlier one writes (a fallback scene's
  capture, the noise-free render shared by a rendered scene's noise levels) waits for it;
* **the registration order**: a camera-array method that estimates the warps waits for the first case
  on the same capture that registers it the same way, and reuses its stored warps;
* **the case hash** (``case_id``): the capture's content key, the method entry, the device, the
  convention and the task's ``identity`` (code fingerprints, options), a plug-in method's package and
  version (its record's ``plugin``), and the bytes of any file an option names (a ``weights`` file); a
  case with an ``ok`` record of the same hash in the results file is not run again;
* **the results log** (:class:`~.results.ResultsLog`): each case's line appended as it finishes, the
  file rewritten in plan order at the end; **notes** (a fallback scene used, notes a task returns in
  ``notes_for_run``), and freeing the captures this process keeps.

A task is a module-level function (picklable, for Dask) ``fn(rec, method, capture_path, capture_key,
capture_info, *, device, convention, **options) -> rec`` that never raises: it returns ``rec`` completed
with ``status`` (``ok``, ``skipped``, ``error`` with ``reason``).
"""

from __future__ import annotations

import datetime as _dt
import time
import traceback
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from capssim.reconstruct.registry import available_methods, default_registration, resolve_device

from ..metrics import get_convention
from .cases import capture_task, forget_captures
from .executors import check_execution, open_executor
from .output_claim import SUITE_OUTPUT, OutputKind, claim_output
from .provenance import content_hash, option_file_hashes
from .results import ResultsLog

__all__ = ["CaseRun", "CaseTask", "RunOutcome", "case_key", "run_cases"]


def case_key(scene: str, noise: str, seed: int, method_label: str) -> str:
    """Readable, stable identity of a case in baselines: ``scene/noise/seedN/method``."""
    return f"{scene}/{noise}/seed{seed}/{method_label}"


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _cache_writes(chain: list[dict], noise: dict, seed: int) -> list[tuple]:
    """What a capture task of ``chain`` may write in the cache: its scenes' captures, and their
    noise-free renders (shared by the noise levels of a rendered scene)."""
    writes = [("capture", c["name"], noise["name"], seed) for c in chain]
    return writes + [("render", c.get("scene", c["name"]), seed) for c in chain if c["source"] == "render"]


@dataclass(frozen=True)
class CaseTask:
    """What a run does per case, and the output it owns (module docstring).

    Attributes
    ----------
    fn : callable
        The per-case task, a module-level function (module docstring gives its signature).
    output : OutputKind
        The results file and owner file of the run's folder (:data:`~.output_claim.SUITE_OUTPUT`, ...).
    identity : dict
        Further content of the case hash (code fingerprints, options that change a result).
    options : dict
        Further keyword arguments of ``fn`` (picklable).
    record : dict
        Fields every record of the run carries after ``seed`` (e.g. the environment).
    capture_fn : callable
        The per-group capture task, a module-level function with :func:`~.cases.capture_task`'s signature and
        outcome (default: that one; a design map builds each cell's capture with its own, :mod:`capssim.eval.maps`).
    """

    fn: Callable[..., dict]
    output: OutputKind = SUITE_OUTPUT
    identity: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)
    record: dict = field(default_factory=dict)
    capture_fn: Callable[..., dict] = capture_task


@dataclass
class RunOutcome:
    """A finished run: ``records`` in plan order, ``notes``, where it ran, its results file and wall time."""

    records: list[dict]
    notes: list[str]
    execution: dict
    results_path: Path
    wall_time_s: float


class CaseRun:
    """The state of one run: the plan's groups and records, the results log, notes, labels."""

    def __init__(self, spec: dict, output: Path, task: CaseTask, *, device: str, cache: Path, fresh: bool,
                 emit: Callable[..., None]):
        self.spec, self.task, self.emit, self.cache = spec, task, emit, cache
        self.results = ResultsLog(Path(output) / task.output.results_name, fresh=fresh)
        self.device = str(resolve_device(device))
        self.convention = get_convention(spec.get("convention", "capssim")).name
        self.registered = available_methods()
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
        self.emit("done", label=rec.get("key", ""), status=rec.get("status"))

    def base(self, noise: dict, seed: int) -> dict:
        return {"suite": self.spec["name"], "noise": noise["name"], "seed": seed, **self.task.record,
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
            handle = executor.submit(self.task.capture_fn, str(self.cache), self.run_id, chain, noise, seed, tag=tag,
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
        return (self.registered[method["name"]].input_kind == "caps" and not method.get("true_warps")
                and method.get("calibration", "ideal") == "ideal")

    def plugin(self, method: dict) -> dict | None:
        """The package and version of a plug-in method (:mod:`capssim.reconstruct.plugins`); None: built in."""
        spec = self.registered.get(method["name"])
        return None if spec is None or spec.plugin is None else spec.plugin.record()

    def case_id(self, entry, method: dict) -> str:
        """The case hash (module docstring); a plug-in's package version is part of it."""
        plugin, files = self.plugin(method), option_file_hashes(method.get("options"))
        return content_hash({"capture": entry.key, "method": method, "device": self.device,
                             "convention": self.convention, **self.task.identity,
                             **({"plugin": plugin} if plugin else {}),
                             **({"option_files": files} if files else {})})[:20]

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
            cid = self.case_id(entry, m)
            rec = dict(self.base(noise, seed), scene=scene["name"], requested_scene=requested["name"],
                       method=m["label"], method_name=m["name"], key=key, case_id=cid, capture=str(entry.path),
                       capture_key=entry.key, scene_source=scene["source"])
            if self.plugin(m):
                rec["plugin"] = self.plugin(m)
            previous = self.results.done(cid)
            if previous is not None:
                self.finish_case(index, previous, new=False)
            elif m["name"] not in self.registered:
                self.skip_unregistered(index, rec, m)
            else:
                self.pending[index] = rec
                self.labels[("case", index)] = key
                mode = m.get("registration") or default_registration(m["name"])
                registrar = registering.get(mode) if self.registers(m) else None
                handle = executor.submit(self.task.fn, rec, m, str(entry.path), entry.key, entry.info,
                                         device=self.device, convention=self.convention, **self.task.options,
                                         tag=("case", index), case=True,
                                         after=[registrar] if registrar is not None else [], name=key)
                if self.registers(m):
                    registering.setdefault(mode, handle)

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

    def run(self, plan_scenes: list[dict], plan_methods: list[dict], scene_by_name: dict, *, workers, scheduler,
            threads) -> dict:
        """Run the plan's groups x methods on the executor; the results file rewritten in plan order.
        Returns where the cases ran."""
        self.methods = plan_methods
        self.groups = [(scene, noise, int(seed)) for scene in plan_scenes for noise in self.spec["noise"]
                       for seed in self.spec["seeds"]]
        self.emit("start", total=len(self.groups) * len(self.methods))
        started = lambda tag: self.emit("case", label=self.labels[tag])  # noqa: E731
        try:
            with open_executor(workers=workers, scheduler=scheduler, threads=threads, started=started) as executor:
                execution = {"kind": executor.kind, "workers": getattr(executor, "workers", None),
                             "compute_threads": getattr(executor, "compute_threads", None)}
                self.execute(executor, scene_by_name)
        finally:
            forget_captures()
        self.results.finish([self.records[i] for i in sorted(self.records)])
        return execution


def run_cases(spec: dict, output: str | Path, task: CaseTask, *, plan_scenes: list[dict], plan_methods: list[dict],
              scene_by_name: dict, device: str = "cpu", cache_dir: str | Path | None = None, fresh: bool = False,
              workers: int | None = None, scheduler: str | None = None, threads: int | None = None,
              events: Callable[..., None] | None = None, allow_other_suite: bool = False) -> RunOutcome:
    """Run (or resume) ``task`` on every case of a plan into ``output``, holding the folder throughout.

    Parameters
    ----------
    spec : dict
        A suite (:func:`~.suite_schema.load_suite`): its name, noise levels and seeds.
    output : str or pathlib.Path
        The run's folder: the task's results file, the captures' cache (``cache/``).
    task : CaseTask
        What is done per case, and the files it owns.
    plan_scenes, plan_methods, scene_by_name : keyword-only
        The plan (:func:`~.suite.plan`): scenes to run, method entries, every scene by name (fallbacks).
    device, cache_dir, fresh, workers, scheduler, threads : keyword-only
        Torch device; the captures' cache (default ``output/cache``); redo the planned cases; a local Dask
        cluster of that many processes or the one at that address (default: this process); compute threads.
    events : callable, optional
        ``events(kind, **info)``: ``start`` (``total``), ``case`` (``label``), ``done`` (``label``,
        ``status``), ``note``, ``skip``, ``error`` (``message``).
    allow_other_suite : bool, keyword-only
        Take over a folder another suite owns (:func:`~.output_claim.claim_output`).

    Returns
    -------
    RunOutcome
    """
    emit = events or (lambda kind, **info: None)
    t_start = time.perf_counter()
    check_execution(workers=workers, scheduler=scheduler)  # before the results file is touched
    output = Path(output)
    with claim_output(output, spec, allow_other_suite=allow_other_suite, kind=task.output) as claim_notes:
        run = CaseRun(spec, output, task, device=device, cache=Path(cache_dir) if cache_dir else output / "cache",
                      fresh=fresh, emit=emit)
        for message in claim_notes:
            run.note(message)
        execution = run.run(plan_scenes, plan_methods, scene_by_name, workers=workers, scheduler=scheduler,
                            threads=threads)
    return RunOutcome(records=[run.records[i] for i in sorted(run.records)], notes=run.notes, execution=execution,
                      results_path=run.results.path, wall_time_s=time.perf_counter() - t_start)
