"""One capture folder reconstructed whole or in tiles, written when it finishes, skipped when already done.

:func:`reconstruct_frame` is the unit of work of ``capssim reconstruct`` on a folder of captures (and of
one capture with ``--tile``/``--memory-gb``): it reads the capture, runs the method untiled, or in tiles
when asked (:func:`~capssim.reconstruct.tiles.run.reconstruct_tiled`, with its finished tiles kept in
``recon/.parts-METHOD/`` until the frame is written), and writes ``recon/METHOD.{tiff,json}``
atomically. The record holds a ``job`` key (the raw frames, method, options and flags); a frame whose
record has the same key is finished and :func:`frame_is_finished` says so, so a rerun after a kill does
only what is missing.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

from capssim.captures.capture import read_capture, write_reconstruction
from capssim.errors import InputError
from capssim.runtime.resources import image_header_shape

from ..pipeline.options import wants_ground_truth
from ..registry import get_method, reconstruct
from .memory import fits, memory_budget
from .run import Runner, reconstruct_tiled, serial_runner

log = logging.getLogger(__name__)

__all__ = ["capture_folders", "frame_is_finished", "frame_job_key", "reconstruct_frame"]


def capture_folders(folder: str | Path) -> list[Path] | None:
    """The capture folders directly inside ``folder`` (sorted), or ``None`` when ``folder`` is one capture."""
    folder = Path(folder)
    if (folder / "meta.json").is_file() or not folder.is_dir():
        return None
    found = sorted(p for p in folder.iterdir() if p.is_dir() and (p / "meta.json").is_file())
    if not found:
        raise InputError("CAPTURE", str(folder), "a capture folder (with meta.json) or a folder of capture folders",
                         "Simulate one with 'capssim simulate GT -o FOLDER'.")
    return found


def frame_job_key(path: str | Path, method: str, settings: dict) -> str:
    """SHA-256 of a frame's job: its raw file(s) and meta.json (size, time), the method and every setting."""
    path = Path(path)
    stamp = []
    for name in ("meta.json", "caps_raw.tiff", "dofp_raw.tiff"):
        f = path / name
        if f.is_file():
            st = f.stat()
            stamp.append([name, st.st_size, st.st_mtime_ns])
    text = json.dumps([stamp, method, {k: str(v) for k, v in sorted(settings.items())}], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def frame_is_finished(path: str | Path, method: str, key: str) -> bool:
    """True when ``recon/METHOD.json`` and ``.tiff`` exist, the record's ``job`` is ``key`` and the TIFF's header
    says a ``(12, 2H, 2W)`` image of the capture's size (an empty or truncated TIFF is done again)."""
    recon = Path(path) / "recon"
    record, tiff = recon / f"{method}.json", recon / f"{method}.tiff"
    if not (record.is_file() and tiff.is_file()):
        return False
    try:
        if json.loads(record.read_text()).get("job") != key:
            return False
        geometry = json.loads((Path(path) / "meta.json").read_text())["geometry"]
        expected = (12, int(geometry["hr_height"]), int(geometry["hr_width"]))
    except (OSError, ValueError, AttributeError, KeyError, TypeError):
        return False
    shape = image_header_shape(tiff)
    if shape != expected:
        log.warning("%s: %s is not a finished %s image (header %s); reconstructing it again", path, tiff.name,
                    "x".join(map(str, expected)), "unreadable" if shape is None else "x".join(map(str, shape)))
        return False
    return True


def reconstruct_frame(path: str | Path, method: str, *, tile: int | None = None, memory_gb: float | None = None,
                      workers: int = 1, runner: Runner = serial_runner, progress=None, **kwargs) -> dict:
    """Reconstruct the capture at ``path`` and write ``recon/METHOD.{tiff,json}``; the record.

    Parameters
    ----------
    path : path
        A capture folder.
    method : str
        A method name.
    tile, memory_gb : optional
        Tiles of at most ``tile`` HR pixels, or the largest that fit ``memory_gb`` GiB (default: the machine's
        memory limit); a frame that fits runs untiled, and DoFP methods always do.
    workers, runner : optional
        Tiles run side by side (for the memory budget) and the runner that runs them (serial, or Dask's).
    progress : callable, optional
        ``progress(done, total, message)``.
    **kwargs
        Options of :func:`capssim.reconstruct.reconstruct` and the method's (``-p``).

    Returns
    -------
    dict
        The record written, with ``job`` (:func:`frame_job_key`).
    """
    path = Path(path)
    key = frame_job_key(path, method, {**kwargs, "tile": tile, "memory_gb": memory_gb})
    capture = read_capture(path, load_gt=wants_ground_truth(kwargs))  # -p track_psnr=true: PSNR per iteration
    result = None
    parts = path / "recon" / f".parts-{method}"
    if get_method(method).input_kind != "caps" and (tile is not None or memory_gb is not None):
        log.warning("%s: --tile and --memory-gb apply to CAPS-input methods only; this DoFP method runs untiled",
                    method)
    elif get_method(method).input_kind == "caps":  # untiled (None) unless asked or past the memory budget
        if not kwargs.get("uncertainty"):
            result = reconstruct_tiled(capture, method, tile=tile, memory_gb=memory_gb, workers=workers,
                                       runner=runner, parts=parts, progress=progress, **kwargs)
        elif tile is not None or not fits(capture.hr_shape, memory_budget(memory_gb)[0]):
            raise InputError("--uncertainty", f"{kwargs['uncertainty']} replicates on a frame run in tiles",
                             "a frame reconstructed untiled (error bars are not made tile by tile)",
                             "Drop --tile, give the run more memory (--memory-gb) or reconstruct a crop of the frame.")
    if result is None:
        result = reconstruct(capture, method, progress=progress, **kwargs)
    out, record = result
    record["job"] = key
    write_reconstruction(path, method, out.image, record, companions=out.companions())
    shutil.rmtree(parts, ignore_errors=True)
    return record
