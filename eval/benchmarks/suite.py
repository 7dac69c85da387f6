"""The benchmark suite runner: scenes x noise levels x seeds x methods from a suite file.

A suite (``eval/suites/NAME.yaml`` or any YAML path; the scoring guide's "Benchmarks") names:

* ``scenes``: each ``{name, source, ...}`` with ``source`` one of
  ``render`` (``capssim.render.render_capture``: ``scene``, ``size``, ``spp``, ``scene_params``),
  ``shared-gt`` (a ground truth under ``../shared/data``: ``path``, ``crop``),
  ``gt`` (a ground-truth folder or 12-channel TIFF anywhere: ``path``, ``crop``),
  ``synthetic`` (:mod:`capssim.eval.synthetic`: ``generator``, ``size``, ``cycles``);
  optionally ``fallback: OTHER_SCENE_NAME`` (a scene of the same file used, and reported,
  when this one's data or renderer is unavailable) and ``psf_sigma`` (HR px, default 0.5);
* ``noise``: ``{name, model: none|gaussian|poisson-gaussian, sigma, preset}``;
* ``seeds``: list of integers (poses, noise and render seeds);
* ``methods``: names, or ``{name, label, options, true_warps, registration}`` for variants
  (``registration``: a :data:`capssim.reconstruct.registration_parameters.REGISTRATION_MODES` name).

Every case is ``(scene, noise, seed, method)``; its capture comes from
:mod:`capssim.eval.benchmarks.captures` and its scores from the one scoring path,
:class:`capssim.eval.evaluate.CaptureScorer`. ``results.jsonl`` holds one JSON line per case and
is rewritten atomically after every case: an interrupted run resumes where it stopped (cases
already ``ok`` with the same case hash are not redone; the hash covers capture, method, options,
device and fingerprints of the reconstruction and scoring code). Peak memory is that of
:class:`~capssim.eval.benchmarks.provenance.PeakMemory` during the method (``peak_rss_mb``, and
``peak_rss_delta_mb`` above the level before it; on CUDA also ``cuda_peak_mb``).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import yaml

from capssim.capture import read_capture, write_reconstruction
from capssim.errors import InputError, UnknownNameError
from capssim.eval.benchmarks.captures import CaptureFactory, Unavailable, expand_render_scenes
from capssim.eval.benchmarks.provenance import PeakMemory, code_fingerprint, content_hash, environment, json_default
from capssim.eval.evaluate import CaptureScorer, mtf_summary
from capssim.eval.metrics import get_convention
from capssim.imageio import atomic_write_text
from capssim.reconstruct.registration_parameters import registration_parameters
from capssim.reconstruct.registry import available_methods, reconstruct, resolve_device

log = logging.getLogger(__name__)

SUITES_DIR = Path(__file__).resolve().parents[1] / "suites"
SCENE_SOURCES = ("render", "shared-gt", "gt", "synthetic")
#: the source files whose change re-runs a case (cached captures are kept)
RECONSTRUCTION_CODE = ("reconstruct",)
SCORING_CODE = ("eval/metrics.py", "eval/mtf.py", "eval/star.py", "eval/evaluate.py", "eval/benchmarks/suite.py")


# -- suites --------------------------------------------------------------------------------------
def available_suites() -> list[str]:
    return sorted(p.stem for p in SUITES_DIR.glob("*.yaml"))


def _method_entries(methods: list) -> list[dict]:
    entries = []
    for m in methods:
        entry = {"name": m} if isinstance(m, str) else dict(m)
        if "name" not in entry:
            raise InputError("suite methods", repr(m),
                             "a method name or {name, label, options, true_warps, registration}")
        entry.setdefault("label", entry["name"])
        entry.setdefault("options", {})
        entry.setdefault("true_warps", False)
        entry.setdefault("registration", "local-correlation")
        registration_parameters(entry["registration"])  # UnknownNameError lists the modes
        entries.append(entry)
    if len({m["label"] for m in entries}) != len(entries):
        raise InputError("suite methods", [m["label"] for m in entries], "unique labels (give variants a 'label')")
    return entries


def _check_scenes(scenes: list) -> None:
    names = set()
    for sc in scenes:
        if not isinstance(sc, dict) or "name" not in sc or sc.get("source") not in SCENE_SOURCES:
            raise InputError("suite scenes", repr(sc)[:120], f"{{name, source}} with source in {SCENE_SOURCES}")
        if sc["name"] in names:
            raise InputError("suite scenes", sc["name"], "unique scene names")
        names.add(sc["name"])
    for sc in scenes:
        if sc.get("fallback") and sc["fallback"] not in names:
            raise InputError("suite scenes", f"fallback {sc['fallback']!r} of {sc['name']!r}", "a scene of this suite")


def load_suite(name_or_path: str | Path) -> dict:
    """Read and validate a suite: a name in ``eval/suites`` or a path to a YAML file."""
    path = Path(name_or_path)
    if not (path.suffix in (".yaml", ".yml") and path.is_file()):
        if str(name_or_path) not in available_suites():
            raise UnknownNameError("suite", str(name_or_path), available_suites())
        path = SUITES_DIR / f"{name_or_path}.yaml"
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise InputError("suite", f"invalid YAML in {path} ({exc})", "a suite file (docs: scoring guide)") from exc
    if not isinstance(spec, dict):
        raise InputError("suite", str(path), "a YAML mapping with scenes, noise, seeds and methods")
    spec = dict(spec)
    spec.setdefault("name", path.stem)
    spec["path"] = str(path)
    spec["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    spec.setdefault("convention", "capssim")
    spec.setdefault("seeds", [0])
    spec.setdefault("noise", [{"name": "clean", "model": "none"}])
    for key in ("scenes", "methods"):
        if not spec.get(key):
            raise InputError("suite", f"{path} without '{key}'", f"a non-empty '{key}' list")
    _check_scenes(spec["scenes"])
    spec["methods"] = _method_entries(spec["methods"])
    for nz in spec["noise"]:
        if not isinstance(nz, dict) or "name" not in nz or "model" not in nz:
            raise InputError("suite noise", repr(nz), "{name, model: none|gaussian|poisson-gaussian, sigma, preset}")
    return spec


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

    @property
    def n_errors(self) -> int:
        return sum(r["status"] == "error" for r in self.records)

    def ok_records(self) -> list[dict]:
        return [r for r in self.records if r["status"] == "ok"]


def case_key(scene: str, noise: str, seed: int, method_label: str) -> str:
    """Readable, stable identity of a case in baselines: ``scene/noise/seedN/method``."""
    return f"{scene}/{noise}/seed{seed}/{method_label}"


def _load_results(path: Path) -> dict[str, dict]:
    done: dict[str, dict] = {}
    if not path.is_file():
        return done
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            log.warning("ignoring a corrupt line of %s", path)
            continue
        if isinstance(rec, dict) and "case_id" in rec:
            done[rec["case_id"]] = rec
    return done


def _write_results(path: Path, records: list[dict]) -> None:
    atomic_write_text(path, "".join(json.dumps(r, default=json_default) + "\n" for r in records))


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


# -- the run -------------------------------------------------------------------------------------
def plan(spec: dict, *, methods: list[str] | None, scenes: list[str] | None, emit: Callable[..., None]):
    """``(scenes to run, every scene by name, method entries)`` of a suite, restricted to a subset."""
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
    return plan_scenes, scene_by_name, method_entries


class _SuiteRun:
    """The state of one run: records so far, the previous run's records, notes, the capture factory."""

    def __init__(self, spec: dict, output: Path, *, device: str, cache: Path, fresh: bool, emit: Callable[..., None]):
        self.spec, self.emit = spec, emit
        self.results_path = output / "results.jsonl"
        self.device = str(resolve_device(device))
        self.env = environment(self.device)
        self.convention = get_convention(spec.get("convention", "capssim")).name
        self.registered = available_methods()
        self.recon_code = code_fingerprint(*RECONSTRUCTION_CODE)
        self.scoring_code = code_fingerprint(*SCORING_CODE)
        self.previous = {} if fresh else _load_results(self.results_path)
        self.factory = CaptureFactory(cache, emit)
        self.notes: list[str] = []
        self.records: list[dict] = []
        self.announced: set[str] = set()

    def flush(self) -> None:
        keep = {r["case_id"] for r in self.records}
        extra = [r for cid, r in self.previous.items() if cid not in keep and r.get("status") == "ok"]
        _write_results(self.results_path, self.records + extra)

    def note(self, message: str) -> None:
        if message not in self.notes:
            self.notes.append(message)
            self.emit("note", message=message)

    def capture(self, scene: dict, noise: dict, seed: int, scene_by_name: dict):
        """``(entry or None, scene used, skip reason, failure)`` of a case: the scene's capture or its fallback's."""
        skip_reason, failure = None, None
        chain = [scene] + ([scene_by_name[scene["fallback"]]] if scene.get("fallback") else [])
        for candidate in chain:
            try:
                self.emit("case", label=f"{candidate['name']}/{noise['name']}/seed{seed}: capture")
                entry = self.factory.get(candidate, noise, seed)
                if candidate is not scene:
                    self.note(f"{scene['name']} unavailable ({skip_reason}); used {candidate['name']} instead")
                return entry, candidate, None, None
            except Unavailable as exc:
                msg = f"{candidate['name']}: {exc}"
                skip_reason = msg if skip_reason is None else f"{skip_reason}; {msg}"
                self.emit("skip", message=f"skipped {msg}")
            except Exception as exc:  # building the capture failed: every case of it fails
                failure = (f"capture {candidate['name']}/{noise['name']}/seed{seed}: "
                           f"{type(exc).__name__}: {exc}", traceback.format_exc(limit=8))
                self.emit("error", message=f"error: {failure[0]}")
                break
        return None, scene, skip_reason, failure

    def record_unavailable(self, base: dict, scene: dict, noise: dict, seed: int, methods: list[dict],
                           skip_reason: str | None, failure: tuple[str, str] | None) -> None:
        for m in methods:
            rec = dict(base, scene=scene["name"], method=m["label"], method_name=m["name"],
                       key=case_key(scene["name"], noise["name"], seed, m["label"]),
                       case_id=content_hash([scene["name"], noise, seed, m, "unavailable"])[:20])
            if failure is not None:
                rec.update(status="error", reason=failure[0], traceback=failure[1])
            else:
                rec.update(status="skipped", skip_kind="data", reason=skip_reason)
            self.records.append(rec)
            self.emit("done")
        self.flush()

    def run_methods(self, base: dict, entry, scene: dict, requested: dict, noise: dict, seed: int,
                    methods: list[dict]) -> None:
        """Every method on one capture; the capture is read and its ground truth measured once."""
        scorer = None
        for m in methods:
            key = case_key(scene["name"], noise["name"], seed, m["label"])
            cid = content_hash({"capture": entry.key, "method": m, "device": self.device, "recon": self.recon_code,
                                "scoring": self.scoring_code, "convention": self.convention})[:20]
            rec = dict(base, scene=scene["name"], requested_scene=requested["name"], method=m["label"],
                       method_name=m["name"], key=key, case_id=cid, capture=str(entry.path),
                       capture_key=entry.key, scene_source=scene["source"])
            if cid in self.previous and self.previous[cid].get("status") == "ok":
                self.records.append(self.previous[cid])
                self.emit("done")
                continue
            if m["name"] not in self.registered:
                self.skip_unregistered(rec, m)
                continue
            self.emit("case", label=key)
            try:
                if scorer is None:
                    capture = read_capture(entry.path, require_gt=True)
                    scorer = CaptureScorer(capture, convention=self.convention)
                    if scorer.measure_ground_truth() is None and scorer.mtf_error is not None:
                        # the scene is scored, only without its MTF
                        message = f"{scene['name']}: ground-truth MTF not measured ({scorer.mtf_error})"
                        self.notes.append(message)
                        self.emit("note", message=message)
                self.run_case(rec, m, capture, scorer, entry)
            except Unavailable as exc:
                rec.update(status="skipped", skip_kind="data", reason=str(exc))
                self.emit("skip", message=f"skipped {key}: {exc}")
            except Exception as exc:  # a failing method must not stop the benchmark
                rec.update(status="error", reason=f"{type(exc).__name__}: {exc}",
                           traceback=traceback.format_exc(limit=8))
                self.emit("error", message=f"error in {key}: {type(exc).__name__}: {exc}")
            rec["finished"] = _now()
            self.records.append(rec)
            self.flush()
            self.emit("done")

    def skip_unregistered(self, rec: dict, method: dict) -> None:
        rec.update(status="skipped", skip_kind="method",
                   reason=f"method {method['name']!r} is not registered (available: "
                          f"{', '.join(self.registered) or 'none'})")
        if method["name"] not in self.announced:
            self.announced.add(method["name"])
            self.emit("skip", message=f"skipping every case of {method['label']}: {rec['reason']}")
        self.records.append(rec)
        self.flush()
        self.emit("done")

    def run_case(self, rec: dict, method: dict, capture, scorer: CaptureScorer, entry) -> None:
        """Reconstruct, write the reconstruction next to the capture, score; fills ``rec``."""
        if self.registered[method["name"]].input_kind == "dofp" and capture.dofp_raw is None:
            raise Unavailable("this capture has no DoFP frame")
        with PeakMemory(device=self.device) as mem:
            out, record = reconstruct(capture, method["name"], device=self.device, true_warps=bool(method["true_warps"]),
                                      registration=method["registration"], **method["options"])
        write_reconstruction(entry.path, method["label"], out.image, record)
        scored = scorer.score(out.image)
        rec.update(status="ok", metrics=scored.flat(), notes=scored.metrics["notes"],
                   metric_settings=scored.metrics["settings"],
                   wall_time_s=record["wall_time_s"], stages_s=record["stages_s"],
                   peak_rss_mb=mem.peak_mb, peak_rss_delta_mb=mem.peak_mb - mem.start_mb,
                   cuda_peak_mb=mem.cuda_peak_mb, params=record.get("params"),
                   registration=record.get("registration"), capture_info=entry.info,
                   recon=str(entry.path / "recon" / f"{method['label']}.tiff"))
        if scorer.gt_mtf is not None:
            rec["gt_mtf"] = mtf_summary(scorer.gt_mtf)["mean"]
            rec["star"] = scorer.star
            if scored.mtf is not None:
                rec["mtf"] = scored.mtf["mean"]
            else:
                rec["mtf_error"] = scored.mtf_error


def run_suite(spec: dict, output: str | Path, *, methods: list[str] | None = None, scenes: list[str] | None = None,
              device: str = "cpu", cache_dir: str | Path | None = None, fresh: bool = False,
              events: Callable[..., None] | None = None) -> BenchRun:
    """Run (or resume) a suite into ``output``; see the module docstring.

    ``events(kind, **info)`` is told ``start`` (``total``), ``case`` (``label``), ``done``,
    ``skip``, ``note`` and ``error`` (``message``): the command line draws its progress from them.
    """
    emit = events or (lambda kind, **info: None)
    t_start = time.perf_counter()
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    run = _SuiteRun(spec, output, device=device, cache=Path(cache_dir) if cache_dir else output / "cache",
                    fresh=fresh, emit=emit)
    plan_scenes, scene_by_name, method_entries = plan(spec, methods=methods, scenes=scenes, emit=emit)
    emit("start", total=len(plan_scenes) * len(spec["noise"]) * len(spec["seeds"]) * len(method_entries))
    for scene in plan_scenes:
        for noise in spec["noise"]:
            for seed in map(int, spec["seeds"]):
                base = {"suite": spec["name"], "noise": noise["name"], "seed": seed, "environment": run.env,
                        "convention": run.convention}
                entry, used, skip_reason, failure = run.capture(scene, noise, seed, scene_by_name)
                if entry is None:
                    run.record_unavailable(base, scene, noise, seed, method_entries, skip_reason, failure)
                else:
                    run.run_methods(base, entry, used, scene, noise, seed, method_entries)
    run.flush()
    return BenchRun(spec=spec, output=output, results_path=run.results_path, records=run.records,
                    environment=run.env, notes=run.notes, wall_time_s=time.perf_counter() - t_start)
