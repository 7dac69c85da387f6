"""Tiled reconstruction of one frame: the same warps and operator per tile, blended without seams.

:func:`reconstruct_tiled` cuts the frame into tiles (:mod:`.geometry`; the size given, or the largest that
fits the memory budget, :mod:`.memory`), registers the whole frame once (or takes its true warps), crops
each tile's capture (:mod:`.crop`), reconstructs it with the method as usual (``true_warps``: the re-based
whole-frame warps), blends the tiles (:mod:`.blend`) and projects the frame onto physical intensities once.

What the paper adapts is global already: the ADMM penalties follow the fixed schedule of eq. 27 (iteration
count only), ``c1``, ``c2`` and CAGF's ``nu`` are constants, and ``caps`` estimates no noise level; the
NLSTR thresholds are per coefficient (local). A method that adapts options to the whole frame (``caps-plus``'s
iteration count and polarization filter, chosen on the frame's central window by its selection layer,
:mod:`capssim.reconstruct.selection`) declares them (``frame_options`` of its registration) and they
are fixed once, before the frame is cut. So every tile solves the whole frame's problem restricted
to its window. Finished tiles can be kept in a parts folder (``parts``) and are skipped on a rerun.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from capssim.captures.capture import Capture
from capssim.errors import InputError
from capssim.files.imageio import atomic_write_bytes, atomic_write_json
from capssim.stokes.physical_validity import project_to_physical

from ..calibration_model import resolve_calibration
from ..model.observation_model import method_geometry
from ..registry import finite_or_null, get_method, reconstruct, resolve_device, unobserved_record
from ..run_context import MethodOutput, RunContext, StageTimer
from .blend import TileBlender
from .crop import crop_capture, translation
from .geometry import Tile, TileLayout
from .margins import (
    check_cores_hold_margin,
    check_margin_options,
    check_tiling,
    choose_layout,
    margin_parts,
    tile_margin,
    warp_reach,
)
from .memory import MIN_REGISTRATION_SIDE, memory_budget, registration_bytes

__all__ = ["check_cores_hold_margin", "check_margin_options", "check_tiling", "choose_layout", "frame_warps", "margin_parts",
           "registration_window", "reconstruct_tile", "reconstruct_tiled", "tile_margin", "warp_reach"]

#: ``runner(function, jobs) -> iterable of (index, result)`` in any order: serial by default, Dask in .distributed
Runner = Callable[[Callable, list], Iterable[tuple[int, object]]]


def serial_runner(function: Callable, jobs: list) -> Iterable[tuple[int, object]]:
    """Run ``function(*job)`` for each job here, in order."""
    for index, job in enumerate(jobs):
        yield index, function(*job)


def frame_warps(capture: Capture, *, device, true_warps: bool, registration: str, reuse_registration: bool,
                calibration, budget_bytes: float | None = None) -> tuple[np.ndarray, dict]:
    """The whole frame's aperture homographies ``(4, 3, 3)`` (true, or registered once and stored) and record.

    With ``budget_bytes`` (the run's memory budget) a frame whose registration would not fit is registered on
    the largest central window that does (:func:`registration_window`)."""
    if resolve_calibration(capture, calibration) is not None:
        raise InputError("--calibration", str(calibration or capture.meta.get("calibration_file")),
                         "the ideal array for a tiled run (its flat fields are not cropped per tile yet)",
                         "Reconstruct untiled (leave --tile and --memory-gb out), or use --calibration ideal.")
    context = RunContext(device=resolve_device(device), timer=StageTimer(), true_warps=true_warps,
                         registration=registration, reuse_registration=reuse_registration)
    window = None if true_warps or budget_bytes is None else registration_window(capture.hr_shape, budget_bytes)
    if window is not None:
        return _registered_on_window(capture, context, window)
    images, saturated = capture.lr_images()
    geometry, record = method_geometry(capture, context, images=images, saturated=saturated)
    return geometry.aperture_homographies, record


#: the share of the budget a registration window is sized to (its memory model is a fit, within ~10 %)
REGISTRATION_BUDGET_SHARE = 0.8


def registration_window(hr_shape, budget_bytes: float) -> tuple[int, int, int, int] | None:
    """The centred window ``(top, left, bottom, right)`` (HR pixels, multiples of 16) to register on when the
    whole frame's registration (:func:`~.memory.registration_bytes`) does not fit ``budget_bytes``; ``None`` when
    it fits. Homographies are global, so a large central window gives the frame's warps."""
    rows, cols = (int(v) for v in hr_shape)
    if registration_bytes((rows, cols)) <= budget_bytes:
        return None
    budget_bytes = REGISTRATION_BUDGET_SHARE * budget_bytes  # the model is a fit: keep a margin below the budget
    scale = math.sqrt(max(0.0, budget_bytes - registration_bytes((0, 0))) / max(1.0, registration_bytes((rows, cols))
                                                                                - registration_bytes((0, 0))))
    h = max(MIN_REGISTRATION_SIDE, int(rows * scale) // 16 * 16)
    w = max(MIN_REGISTRATION_SIDE, int(cols * scale) // 16 * 16)
    h, w = min(h, rows), min(w, cols)
    top, left = (rows - h) // 2 // 4 * 4, (cols - w) // 2 // 4 * 4
    return top, left, top + h, left + w


def _registered_on_window(capture: Capture, context: RunContext, window) -> tuple[np.ndarray, dict]:
    """Register the apertures on ``window`` only (the same crop of every aperture), then express the warps on
    the whole frame: ``H_n = T(o_n) H'_n T(-corner)``."""
    top, left, _, _ = window
    identity = np.stack([np.eye(3)] * 4)
    cropped = crop_capture(capture, Tile((0, 0), tuple(window), tuple(window)), identity)
    images, saturated = cropped.lr_images()
    geometry, record = method_geometry(cropped, replace(context, reuse_registration=False), images=images,
                                       saturated=saturated)
    offsets = cropped.meta["tile"]["aperture_offsets_hr"]
    homs = np.stack([translation(ox, oy) @ h @ translation(-left, -top)
                     for (oy, ox), h in zip(offsets, np.asarray(geometry.aperture_homographies, dtype=np.float64))])
    record = {**record, "window": list(window),
              "note": "registered on a central window: the whole frame's registration exceeds the memory budget"}
    return homs, record


def reconstruct_tile(capture: Capture, method: str, device: str, options: dict) -> dict:
    """One tile's reconstruction (no physical projection): ``image``, ``unobserved`` and its record."""
    out, record = reconstruct(capture, method, device=device, true_warps=True, physical_projection=False,
                              calibration="ideal", **options)
    unobserved = None if out.unobserved is None else np.asarray(out.unobserved, dtype=bool)
    keep = {k: record[k] for k in ("wall_time_s", "stages_s", "params", "history") if k in record}
    return {"image": np.asarray(out.image, dtype=np.float32), "unobserved": unobserved, "record": keep}


class PartStore:
    """Finished tiles in a folder, one ``NAME.npz`` each (written atomically), valid for one job ``key``."""

    def __init__(self, folder: str | Path | None, key: str):
        self.folder = None if folder is None else Path(folder)
        self.key = key
        if self.folder is not None:
            stamp = self.folder / "job.json"
            if stamp.is_file():
                try:
                    same = json.loads(stamp.read_text()).get("key") == key
                except (OSError, ValueError):
                    same = False
                if not same:  # another job's parts: never mix them
                    for old in self.folder.glob("*.npz"):
                        old.unlink()
            atomic_write_json(stamp, {"key": key})

    def load(self, name: str) -> dict | None:
        path = None if self.folder is None else self.folder / f"{name}.npz"
        if path is None or not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                mask = data["unobserved"] if "unobserved" in data.files else None
                return {"image": data["image"], "unobserved": mask, "record": json.loads(str(data["record"]))}
        except (OSError, ValueError, KeyError):
            return None

    def save(self, name: str, part: dict) -> None:
        if self.folder is None:
            return
        import io

        buffer = io.BytesIO()
        arrays = {"image": part["image"], "record": np.array(json.dumps(part["record"]))}
        if part["unobserved"] is not None:
            arrays["unobserved"] = part["unobserved"]
        np.savez(buffer, **arrays)
        atomic_write_bytes(self.folder / f"{name}.npz", buffer.getvalue())


def job_key(capture: Capture, method: str, layout: TileLayout, homographies: np.ndarray, options: dict,
            device: str) -> str:
    """SHA-256 of what a tile's result depends on (raw frames, warps, layout, method, options, device)."""
    digest = hashlib.sha256(np.ascontiguousarray(capture.caps_raw).tobytes())
    digest.update(np.asarray(homographies, dtype=np.float64).tobytes())
    digest.update(json.dumps([method, layout.to_dict(), {k: str(v) for k, v in sorted(options.items())},
                              str(device), capture.meta.get("sensor"), capture.meta.get("psf")],
                             sort_keys=True, default=str).encode())
    return digest.hexdigest()


def reconstruct_tiled(capture: Capture, method: str, *, tile: int | None = None, memory_gb: float | None = None,
                      workers: int = 1, margin: int | None = None, device: str = "cpu", true_warps: bool = False,
                      registration: str | None = None, reuse_registration: bool = True, calibration=None,
                      physical_projection: bool = True, progress: Callable[[int, int, str], None] | None = None,
                      parts: str | Path | None = None, runner: Runner = serial_runner, **options
                      ) -> tuple[MethodOutput, dict] | None:
    """Reconstruct ``capture`` with ``method`` in tiles; ``None`` when it should run untiled.

    Parameters
    ----------
    capture : Capture
        A CAPS capture, raw ``(4, H, W)``.
    method : str
        A CAPS-input method (``caps``, ``caps-iccp``, ``caps-naive``, ...).
    tile, memory_gb, workers, margin : optional
        Core side (HR pixels); memory budget (GiB; default the machine's limit); tiles run side by side;
        margin (HR pixels; default :func:`tile_margin`). See :func:`choose_layout`.
    device, true_warps, registration, reuse_registration, calibration, physical_projection : optional
        As :func:`capssim.reconstruct.reconstruct` (registration None: the method's own; calibration: the ideal
        array only).
    progress : callable, optional
        ``progress(done, total, message)`` per finished tile.
    parts : path, optional
        Folder for finished tiles (resume after a kill); ``None`` keeps them in memory.
    runner : callable
        ``runner(function, jobs)`` yielding ``(index, result)`` as tiles finish (serial, or a Dask client's).
    **options
        The method's options (``-p``).

    Returns
    -------
    (MethodOutput, dict) or None
        ``image`` ``(12, 2H, 2W)`` float32 and the record (``tiles``: the layout and each tile's time).
    """
    spec = get_method(method)
    if spec.input_kind != "caps":
        raise InputError("--tile", f"method {method}", "a CAPS-input method (DoFP methods run untiled)",
                         "Leave --tile and --memory-gb out for DoFP methods.")
    registration = spec.registration if registration is None else registration
    if not check_tiling(capture, options, tile=tile, memory_gb=memory_gb, workers=workers, margin=margin):
        return None  # the whole frame fits: the untiled run
    budget, _ = memory_budget(memory_gb)
    t0 = time.perf_counter()
    homographies, reg_record = frame_warps(capture, device=device, true_warps=true_warps, registration=registration,
                                           reuse_registration=reuse_registration, calibration=calibration,
                                           budget_bytes=budget)
    t_reg = time.perf_counter() - t0
    layout = choose_layout(capture, options, aperture_homographies=homographies, tile=tile, memory_gb=memory_gb,
                           workers=workers, margin=margin)
    if layout is None:
        return None
    # what the method adapts to the whole frame is fixed once, for every tile (not when the frame runs untiled)
    frame = ({} if spec.frame_options is None else
             spec.frame_options(capture, options, homographies=homographies, device=device))
    options = {**frame, **options}
    store = PartStore(parts, job_key(capture, method, layout, homographies, options, str(device)))
    blender, records = _run_tiles(capture, method, layout, homographies, store, str(device), options, runner,
                                  progress)
    image, unobserved = blender.result(), blender.unobserved
    stages = {"registration": t_reg}
    for rec in records.values():
        for name, seconds in rec.get("stages_s", {}).items():
            stages[name] = stages.get(name, 0.0) + seconds
    projection = None
    if physical_projection:
        t1 = time.perf_counter()
        image, projection = project_to_physical(image, unobserved=unobserved)
        stages["physical_projection"] = time.perf_counter() - t1
    first = records[layout.tiles[0].name]
    record = _record(method, options, device, true_warps, first, stages, time.perf_counter() - t0, reg_record,
                     projection, layout, records)
    record["frame_options"] = frame  # the options above that the method derived from the whole frame
    unobserved_rec = unobserved_record(method, unobserved)
    if unobserved_rec is not None:
        record["unobserved"] = unobserved_rec
    return (MethodOutput(image=image, params=first.get("params", {}), extra={}, unobserved=unobserved),
            finite_or_null(record))


def _run_tiles(capture, method, layout, homographies, store, device, options, runner, progress):
    """Every tile of ``layout``, from ``store`` or ``runner``; the filled :class:`TileBlender` and their records."""
    blender = TileBlender(layout, 12)
    done, records, todo = 0, {}, []
    for tile_ in layout.tiles:
        part = store.load(tile_.name)
        if part is None:
            todo.append(tile_)
            continue
        blender.add(tile_, part["image"], part["unobserved"])
        records[tile_.name], done = {**part["record"], "resumed": True}, done + 1
    jobs = [(crop_capture(capture, t, homographies), method, device, dict(options)) for t in todo]
    for index, part in runner(reconstruct_tile, jobs):
        store.save(todo[index].name, part)  # written as it finishes: a rerun after a kill skips it
        blender.add(todo[index], part["image"], part["unobserved"])
        records[todo[index].name], done = part["record"], done + 1
        if progress is not None:
            progress(done, len(layout.tiles), f"tile {done}/{len(layout.tiles)}")
    return blender, records


def _record(method, options, device, true_warps, first, stages, wall, reg_record, projection, layout, records):
    """The ``recon/METHOD.json`` record of a tiled run (the untiled run's fields, plus ``tiles``)."""
    spec = get_method(method)
    tiles = layout.to_dict()
    for entry in tiles["tiles"]:
        rec = records[entry["name"]]
        entry.update({"wall_time_s": rec.get("wall_time_s"), "resumed": bool(rec.get("resumed", False)),
                      "rematched_at": [h.get("iteration") for h in rec.get("history", []) if h.get("rematched")]})
    return {"method": method, "description": spec.description, "reference": spec.reference, "input": spec.input_kind,
            "device": str(resolve_device(device)), "true_warps": true_warps,
            "options": dict(options), "params": first.get("params", {}), "wall_time_s": wall, "stages_s": stages,
            "history": first.get("history", []),
            "physical_projection": None if projection is None else projection.to_dict(),
            "calibration": None, "registration": reg_record, "tiles": tiles}
