"""The two kinds of task of a suite run, the same in this process and on a Dask worker.

* :func:`capture_task`: the capture of one (scene, noise, seed), the scene's or its fallback's,
  built or found in the cache (:class:`~capssim.eval.benchmarks.captures.CaptureFactory`);
* :func:`method_task`: one case, one method on one capture: reconstruct, write the
  reconstruction next to the capture, score. Wall time, stage times and peak memory are
  measured here, in the process that runs the method.

Both are module-level functions of plain arguments (picklable), and their results depend on
their arguments only: the capture's noise comes from its seed, not from the order in which a
worker meets the cases. A worker keeps its last two captures and scorers (:func:`_scorer`), so
the ground truth's MTF is measured once per capture and worker. Neither raises for a failing case:
the failure is in the returned outcome or record.
"""

from __future__ import annotations

import datetime as _dt
import functools
import os
import platform
import traceback
from pathlib import Path
from typing import Callable

from capssim.captures.capture import read_capture, write_reconstruction
from capssim.reconstruct.registry import available_methods, reconstruct

from ..evaluate import CaptureScorer, mtf_summary
from .captures import CaptureFactory, Unavailable
from .provenance import PeakMemory, environment


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


@functools.lru_cache(maxsize=2)
def _factory(cache_dir: str, run_id: str, factory_class: type = CaptureFactory) -> CaptureFactory:
    """One factory per run and process: its fingerprints of the code and the data are the run's."""
    return factory_class(Path(cache_dir), lambda kind, **info: None)


@functools.lru_cache(maxsize=2)
def _environment(device: str) -> dict:
    return environment(device)


def capture_task(cache_dir: str, run_id: str, chain: list[dict], noise: dict, seed: int,
                 events: Callable[..., None] | None = None, *, factory_class: type = CaptureFactory) -> dict:
    """The capture of the first available scene of ``chain`` (a scene, then its fallback); ``run_id``
    names the run (a worker serving several runs fingerprints the data of each); ``factory_class``: the
    :class:`~capssim.eval.benchmarks.captures.CaptureFactory` (sub)class that builds it.

    Returns ``{entry, scene, skip_reason, failure, events}``: ``entry`` the
    :class:`~capssim.eval.benchmarks.captures.CaptureEntry` (None if no scene was available or the
    build failed), ``scene`` the scene used, ``skip_reason`` why the scenes were unavailable,
    ``failure`` ``(message, traceback)`` of a build that raised, ``events`` the progress events
    ``(kind, info)`` for the caller to show (told to ``events`` at once instead, when given).
    """
    told: list[tuple[str, dict]] = []

    def emit(kind: str, **info) -> None:
        if events is None:
            told.append((kind, info))
        else:
            events(kind, **info)

    factory = _factory(str(cache_dir), run_id, factory_class)
    factory.events = emit
    skip_reason = failure = None
    for candidate in chain:
        try:
            entry = factory.get(candidate, noise, seed)
            return {"entry": entry, "scene": candidate, "skip_reason": skip_reason, "failure": None, "events": told}
        except Unavailable as exc:
            msg = f"{candidate['name']}: {exc}"
            skip_reason = msg if skip_reason is None else f"{skip_reason}; {msg}"
            emit("skip", message=f"skipped {msg}")
        except Exception as exc:  # building the capture failed: every case of it fails
            failure = (f"capture {candidate['name']}/{noise['name']}/seed{seed}: {type(exc).__name__}: {exc}",
                       traceback.format_exc(limit=8))
            emit("error", message=f"error: {failure[0]}")
            break
    return {"entry": None, "scene": chain[0], "skip_reason": skip_reason, "failure": failure, "events": told}


@functools.lru_cache(maxsize=2)
def _scorer(capture_path: str, capture_key: str, convention: str):
    """``(capture, scorer)`` of a capture, its ground truth measured once (``capture_key``: its content hash)."""
    capture = read_capture(capture_path, require_gt=True)
    scorer = CaptureScorer(capture, convention=convention)
    scorer.measure_ground_truth()
    return capture, scorer


def forget_captures() -> None:
    """Drop the captures, scorers and factories this process keeps (after a run in this process)."""
    _scorer.cache_clear()
    _factory.cache_clear()


def method_task(rec: dict, method: dict, capture_path: str, capture_key: str, capture_info: dict, *,
                device: str, convention: str, prepare: Callable | None = None) -> dict:
    """Run the case ``rec`` (a record holding its identity): ``method`` on the capture at ``capture_path``;
    ``prepare(capture, method, capture_info) -> (capture, method)``, a module-level function, changes both
    before the run (a design map's perturbed warps, :mod:`capssim.eval.maps.cells`).

    Returns the record completed: ``status`` ``ok`` (metrics, ``wall_time_s``, ``stages_s``,
    ``peak_rss_mb``...), ``skipped`` or ``error`` (``reason``, ``traceback``); ``environment``
    and ``worker`` (``host:pid``) of the process that ran it; ``notes_for_run``: notes for the
    run's report (popped by the caller).
    """
    rec = dict(rec, environment=_environment(device), worker=f"{platform.node()}:{os.getpid()}")
    try:
        capture, scorer = _scorer(str(capture_path), capture_key, convention)
        if scorer.gt_mtf is None and scorer.mtf_error is not None:  # the scene is scored, only without its MTF
            rec["notes_for_run"] = [f"{rec['scene']}: ground-truth MTF not measured ({scorer.mtf_error})"]
        if prepare is not None:
            capture, method = prepare(capture, method, capture_info)
        _run_method(rec, method, capture, scorer, capture_path, capture_info, device=device)
    except Unavailable as exc:
        rec.update(status="skipped", skip_kind="data", reason=str(exc))
    except Exception as exc:  # a failing method must not stop the benchmark
        rec.update(status="error", reason=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc(limit=8))
    rec["finished"] = _now()
    return rec


def method_calibration(method: dict) -> str | None:
    """The ``calibration`` argument of a suite method (:mod:`capssim.eval.benchmarks.rigs`): ``ideal`` (the
    default) ignores a capture's calibration file, ``capture`` uses it, ``truth`` the capture's true rig."""
    return {"ideal": "ideal", "capture": None, "truth": "truth"}[method.get("calibration", "ideal")]


def reused_registration_s(record: dict) -> float:
    """The registration time a method saved by reusing a capture's stored warps (0 when it computed them).

    A suite's ``wall_time_s`` adds it back, so every method that estimates warps is timed with its
    registration whatever ran before it on the same capture.
    """
    registration = record.get("registration") or {}
    if registration.get("store") != "reused":
        return 0.0
    return float(registration.get("time_s") or 0.0)


def _run_method(rec: dict, method: dict, capture, scorer: CaptureScorer, capture_path: str, capture_info: dict, *,
                device: str) -> None:
    """Reconstruct, write the reconstruction next to the capture, score; fills ``rec``."""
    if available_methods()[method["name"]].input_kind == "dofp" and capture.dofp_raw is None:
        raise Unavailable("this capture has no DoFP frame")
    with PeakMemory(device=device) as mem:
        out, record = reconstruct(capture, method["name"], device=device, true_warps=bool(method["true_warps"]),
                                  registration=method["registration"], calibration=method_calibration(method),
                                  uncertainty=method.get("uncertainty") or 0, **method["options"])
    write_reconstruction(capture_path, method["label"], out.image, record, companions=out.companions())
    scored = scorer.score(out.image)
    rec.update(status="ok", metrics=scored.flat(), notes=scored.metrics["notes"],
               metric_settings=scored.metrics["settings"],
               wall_time_s=record["wall_time_s"] + reused_registration_s(record), stages_s=record["stages_s"],
               reused_registration_s=reused_registration_s(record), peak_rss_mb=mem.peak_mb, peak_rss_delta_mb=mem.peak_mb - mem.start_mb,
               cuda_peak_mb=mem.cuda_peak_mb, params=record.get("params"), calibration=record.get("calibration"),
               registration=record.get("registration"), capture_info=capture_info,
               recon=str(Path(capture_path) / "recon" / f"{method['label']}.tiff"))
    if out.uncertainty is not None:  # the suite asked for error bars: scored like capssim evaluate scores them
        scores = scorer.score_uncertainty(out.image, out.uncertainty).to_dict(with_curves=False)
        rec["uncertainty"] = {**scores, "calibration": record["uncertainty"]["calibration"].get("name"),
                              "replicates": record["uncertainty"]["replicates"],
                              "time_s": record["uncertainty"]["time_s"]}
    if scorer.gt_mtf is not None:
        rec["gt_mtf"] = mtf_summary(scorer.gt_mtf)["mean"]
        rec["star"] = scorer.star
        if scored.mtf is not None:
            rec["mtf"] = scored.mtf["mean"]
        else:
            rec["mtf_error"] = scored.mtf_error
