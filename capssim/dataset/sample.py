"""Making one sample (runs on a Dask worker): capture -> folder (temp name, renamed) -> checksums.

A sample is a function of its spec (:meth:`DatasetConfig.sample_spec`) only, so regenerating it
on any worker gives the same bytes: the TIFFs are written without dates (``write_tiff``), and
``meta.json`` holds no wall times (rendered captures use ``record_timing=False``; timings go
to the manifest instead).
"""

from __future__ import annotations

import functools
import logging
import math
import os
import socket
import sys
import time
from pathlib import Path

import numpy as np
import torch

from capssim.camera.camera_setup import CameraSetup
from capssim.captures.capture import write_capture
from capssim.dataset.augment import rotate_flip_twelve, scale_colours
from capssim.dataset.config import rig_model
from capssim.dataset.config_specs import COLOUR_AUGMENTS, SETUP_KEYS_IN_DATASETS
from capssim.errors import InputError
from capssim.files.imageio import file_sha256, read_gt_scene
from capssim.render import render_capture
from capssim.render.pipeline import check_render
from capssim.runtime.threads import set_threads
from capssim.simulate import PoseRanges, simulate_capture

log = logging.getLogger(__name__)

#: thread variables of libraries beyond those :func:`capssim.runtime.threads.set_threads` exports
EXTRA_THREAD_ENV_VARS = ("NUMEXPR_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "DRJIT_NUM_THREADS")
_render_threads: int | None = None


def limit_threads(n: int) -> None:
    """Limit this process's compute threads (OpenMP/BLAS, torch, Dr.Jit/Mitsuba) to ``n``.

    Called once per Dask worker so that workers x threads does not exceed the cores.
    """
    global _render_threads
    n = set_threads(max(1, int(n)))  # torch, OpenCV, OpenMP/MKL/OpenBLAS variables
    for var in EXTRA_THREAD_ENV_VARS:
        os.environ[var] = str(n)
    try:
        torch.set_num_interop_threads(n)
    except RuntimeError:  # only allowed before any inter-op work; harmless otherwise
        pass
    _render_threads = n
    if "drjit" in sys.modules:
        sys.modules["drjit"].set_thread_count(n)


def _apply_render_threads() -> None:
    if _render_threads is not None:
        import drjit

        if drjit.thread_count() != _render_threads:
            drjit.set_thread_count(_render_threads)


@functools.lru_cache(maxsize=4)
def _read_gt_cached(path: str):
    gt, info = read_gt_scene(path)
    gt.setflags(write=False)
    return gt, info


def _check_crop_size(source: dict, h: int, w: int) -> None:
    size = source.get("size")
    if size is not None and size > min(h, w):
        raise InputError(f"size of source {source.get('name')!r}", size,
                         f"at most the ground-truth size {h}x{w} of {source.get('path')}",
                         "Lower size, or use size: null for the whole image.")


def crop_ground_truth(full: np.ndarray, source: dict) -> tuple[np.ndarray, dict]:
    """Crop (centred or at the drawn position) and augment a GT image for a sample.

    ``source`` holds ``size`` (None: whole image, trimmed to a multiple of 4 by simulate),
    ``crop_position`` (``center``/``random``), ``crop_uv`` (two numbers in [0, 1) that
    place a random crop), ``rot90`` and ``flip``, and where set ``gain_red``, ``gain_blue`` and ``exposure``
    (:func:`~capssim.dataset.augment.scale_colours`). Returns the image and what was done.
    """
    h, w = full.shape[1:]
    size = source.get("size")
    info: dict = {"source_height": int(h), "source_width": int(w)}
    if size is not None:
        _check_crop_size(source, h, w)
        if source.get("crop_position", "center") == "random":
            u, v = source["crop_uv"]
            top = min(int(math.floor(u * (h - size + 1))), h - size)
            left = min(int(math.floor(v * (w - size + 1))), w - size)
        else:
            top, left = (h - size) // 2, (w - size) // 2
        full = full[:, top:top + size, left:left + size]
        info.update(crop=int(size), crop_offset_rowcol=[int(top), int(left)])
    rot90, flip = int(source.get("rot90", 0)), bool(source.get("flip", False))
    gt = rotate_flip_twelve(full, rot90=rot90, flip=flip)
    info.update(rot90=rot90, flip=flip)
    colour = {name: float(source[name]) for name in COLOUR_AUGMENTS if name in source}
    if colour:
        gt, applied = scale_colours(gt, **colour)
        info.update(colour, exposure_applied=applied)
    return np.array(gt, dtype=np.float32, copy=True), info


def checksum_folder(folder: Path) -> dict:
    """``{relative/path: {"sha256": hex, "bytes": n}}`` of every file under ``folder``, sorted."""
    folder = Path(folder)
    out = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        out[path.relative_to(folder).as_posix()] = {"sha256": file_sha256(path), "bytes": path.stat().st_size}
    return out


def fsync_folder(folder: Path) -> None:
    """Flush every file of ``folder``, the folder and its parent to disk."""
    for path in sorted(Path(folder).rglob("*")):
        if path.is_file():
            fd = os.open(path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
    for d in (Path(folder), Path(folder).parent):
        fd = os.open(d, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def sample_setup(params: dict) -> CameraSetup:
    """The :class:`~capssim.camera.camera_setup.CameraSetup` of a sample's drawn parameters
    (:meth:`DatasetConfig.sample_spec`): its set-up keys, as the config spells them; a key drawn as
    ``None`` takes the set-up's default. Errors name the key, as in ``defaults.rig.gain``."""
    mapping = {k: params[k] for k in SETUP_KEYS_IN_DATASETS if params.get(k) is not None}
    if mapping.get("rig"):
        rig_model(mapping["rig"])  # refuses bad values, naming the config key
    return CameraSetup.from_mapping(mapping, where="sample")


def build_capture(spec: dict):
    """The :class:`~capssim.captures.capture.Capture` of a sample spec, and a timing dict (seconds)."""
    params = spec["params"]
    src = params["source"]
    setup = sample_setup(params)
    dataset_meta = {"name": spec["dataset"], "index": spec["index"], "master_seed": spec["master_seed"],
                    "params": params}
    timing: dict = {}
    if src["type"] == "gt":
        t = time.perf_counter()
        full, info = _read_gt_cached(spec["resolved"]["gt_path"])
        gt, crop_info = crop_ground_truth(full, src)
        timing["load_s"] = time.perf_counter() - t
        source = {"type": info["type"], "path": src["path"], "bit_depth": info.get("bit_depth"), **crop_info}
        if "files" in info:
            source["files"] = info["files"]
        t = time.perf_counter()
        capture = simulate_capture(gt, setup, seed=spec["seed"], pose_ranges=PoseRanges(**params["pose"]),
                                   source=source, extra_meta={"dataset": dataset_meta})
        timing["simulate_s"] = time.perf_counter() - t
    else:
        _apply_render_threads()
        t = time.perf_counter()
        capture = render_capture(src["scene"], **_render_options(spec, setup))
        timing["render_s"] = time.perf_counter() - t
        capture.meta["dataset"] = dataset_meta
    return capture, timing


def _render_options(spec: dict, setup: CameraSetup) -> dict:
    """The keyword options of :func:`~capssim.render.render_capture` for a rendered-scene sample."""
    src = spec["params"]["source"]
    return dict(size=src["size"], spp=src["spp"], seed=render_seed(spec["seed"]), setup=setup,
                variant=src["variant"], scene_params=src["scene_params"] or None,
                geometry_params=src["geometry_params"] or None, target_noise=src["target_noise"],
                record_timing=False)


@functools.lru_cache(maxsize=None)
def _gt_shape(path: str) -> tuple[int, int]:
    return tuple(_read_gt_cached(path)[0].shape[1:])


def check_sample(spec: dict) -> None:
    """Check sample ``spec`` as completely as making it would, without rendering or simulating.

    Raises the :class:`~capssim.errors.InputError` that :func:`generate_sample` would raise
    for it (a crop larger than the ground truth, scene parameters the scene refuses, a render
    larger than the machine holds, ...). ``capssim dataset --dry-run`` calls it for every sample.
    """
    params = spec["params"]
    src = params["source"]
    setup = sample_setup(params)
    if src["type"] == "gt":
        _check_crop_size(src, *_gt_shape(spec["resolved"]["gt_path"]))
        PoseRanges(**params["pose"])
        rig = setup.rig
        hr_shape = (src["size"], src["size"]) if src.get("size") else _gt_shape(spec["resolved"]["gt_path"])
        setup.psf.check_extent(hr_shape, option="psf_sigma_hr_px" if setup.psf.type == "gaussian" else "psf")
        for n, aperture_psf in enumerate((rig.psf_objects() if rig is not None else None) or []):
            aperture_psf.check_extent(hr_shape, option=f"rig psf_sigmas_hr_px[{n}]", memory=False)
    else:
        check_render(src["scene"], **_render_options(spec, setup))


#: bytes a sample's files take per HR pixel, at most: gt.tiff (12 float32), caps_raw.tiff and dofp_raw.tiff
#: (float32 without a sensor model, else uint16)
SAMPLE_BYTES_PER_HR_PIXEL = 12 * 4 + 4 + 4
#: meta.json and the file-system overhead of one sample folder, about
SAMPLE_BYTES_OVERHEAD = 64 * 1024


def sample_bytes_estimate(spec: dict) -> int:
    """Disk bytes sample ``spec`` takes, at most (its HR side from the drawn size, or the whole ground truth)."""
    src = spec["params"]["source"]
    size = src.get("size")
    if size is None and src["type"] == "gt":
        height, width = _gt_shape(spec["resolved"]["gt_path"])
    else:
        height = width = int(size)
    return height * width * SAMPLE_BYTES_PER_HR_PIXEL + SAMPLE_BYTES_OVERHEAD


def render_seed(seed: int) -> int:
    """The 32-bit seed given to the renderer (the low bits of the sample's 63-bit seed)."""
    return int(seed) & 0xFFFFFFFF


def generate_sample(spec: dict, samples_dir: str) -> dict:
    """Make sample ``spec`` under ``samples_dir/NAME`` and return its manifest record (without
    ``finished_at``). The folder is built under a temporary name and renamed when complete;
    an existing folder of that name (an unlisted leftover) is replaced."""
    t0 = time.perf_counter()
    capture, timing = build_capture(spec)
    t = time.perf_counter()
    folder = Path(samples_dir) / spec["name"]
    write_capture(folder, capture, overwrite=True)
    fsync_folder(folder)
    timing["write_s"] = time.perf_counter() - t
    t = time.perf_counter()
    files = checksum_folder(folder)
    timing["checksum_s"] = time.perf_counter() - t
    timing["total_s"] = time.perf_counter() - t0
    return {"index": spec["index"], "name": spec["name"], "seed": spec["seed"],
            "source": spec["params"]["source"]["name"], "params": spec["params"], "files": files,
            "timing": {k: round(v, 6) for k, v in timing.items()},
            "worker": f"{socket.gethostname()}:{os.getpid()}"}
