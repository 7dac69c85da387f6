"""Imperfect rigs in a benchmark suite: the rig of a scene entry, its geometry and its calibration.

A suite scene may carry ``rig: {preset: realistic, seed: N, geometry_seed: M, ...overrides}``
(the keys of :meth:`capssim.camera.rig.RigModel.with_overrides`, plus ``polarizer_angles`` for the
calibration sweep). Its capture is then simulated (or rendered) through that rig, with aperture
homographies drawn from ``geometry_seed`` (the same for the scene and for the rig's calibration
captures), and the capture folder gets ``calibration.json``: what ``capssim calibrate`` measured
from the rig's calibration captures (flat field, polarizer sweep, geometry target, star), made
with the suite's noise and cached by content hash under ``CACHE/calibrations/<sha256>``.

Methods choose their model with ``calibration``: ``ideal`` (none, today's model), ``capture``
(the measured ``calibration.json``) or ``truth`` (the capture's true rig in ``meta.json``).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.rig import RigModel
from capssim.dataset.calibration_captures import make_calibration_captures, seeded_aperture_homographies
from capssim.errors import InputError
from capssim.files.imageio import atomic_write_json
from capssim.reconstruct.calibration import calibrate_captures

from .provenance import code_fingerprint, content_hash

log = logging.getLogger(__name__)

#: what a method entry's ``calibration`` may say
METHOD_CALIBRATIONS = ("ideal", "capture", "truth")
#: the keys of a scene's ``rig`` entry
RIG_KEYS = ("preset", "seed", "geometry_seed", "angle_offsets_deg", "extinction_ratio", "gain",
            "vignetting_corner", "psf_sigmas_hr_px", "polarizer_angles")
#: the file a rig scene's capture folder holds its measured calibration in
CALIBRATION_FILE = "calibration.json"
CALIBRATION_CODE = ("capssim", "reconstruct/calibration", "scenes")


def check_rig_spec(spec, scene_name: str) -> None:
    """Refuse a scene's ``rig`` entry with unknown keys or values the rig model refuses."""
    if not isinstance(spec, dict):
        raise InputError(f"suite scene {scene_name!r} rig", repr(spec)[:80], f"a mapping with keys among {RIG_KEYS}")
    unknown = set(spec) - set(RIG_KEYS)
    if unknown:
        raise InputError(f"suite scene {scene_name!r} rig", f"keys {sorted(unknown)}", f"keys among {RIG_KEYS}")
    RigModel.from_spec(spec)


def rig_geometry(spec: dict, hr_shape) -> ArrayGeometry:
    """The rig's aperture homographies at ``hr_shape``: the default pose ranges, drawn from ``geometry_seed``."""
    return ArrayGeometry(seeded_aperture_homographies(int(spec.get("geometry_seed", 0)), hr_shape), tuple(hr_shape))


def calibration_for(cache_dir: Path, spec: dict, hr_shape, sensor, noise: dict, seed: int) -> tuple[Path, dict]:
    """``calibration.json`` of the rig ``spec`` at ``hr_shape`` (built, or found in the cache), and its record.

    The calibration captures are simulated through the true rig with ``sensor`` (the suite's
    noise) and seed ``seed + 1000`` (noise independent of the scene's); ``capssim calibrate``
    measures them.
    """
    ident = {"rig": spec, "hr_shape": list(hr_shape), "noise": noise, "seed": seed,
             "code": code_fingerprint(*CALIBRATION_CODE)}
    folder = Path(cache_dir) / "calibrations" / content_hash(ident)[:20]
    result = folder / CALIBRATION_FILE
    info_path = folder / "bench-calibration.json"
    if result.is_file() and info_path.is_file():
        return result, dict(json.loads(info_path.read_text()), cached=True)
    if folder.exists():
        shutil.rmtree(folder)
    t0 = time.perf_counter()
    rig, geometry = RigModel.from_spec(spec), rig_geometry(spec, hr_shape)
    make_calibration_captures(folder / "captures", rig=rig, size=int(hr_shape[0]), sensor=sensor,
                              polarizer_angles=int(spec.get("polarizer_angles", 12)), seed=seed + 1000,
                              aperture_homographies=geometry.aperture_homographies)
    made = time.perf_counter() - t0
    captures = sorted(p for p in (folder / "captures").iterdir() if (p / "meta.json").is_file())
    calibrate_captures(captures, result)
    info = {"captures_time_s": made, "calibrate_time_s": time.perf_counter() - t0 - made,
            "n_captures": len(captures)}
    atomic_write_json(info_path, info)
    return result, dict(info, cached=False)


def attach_calibration(capture_path: Path, calibration: Path) -> None:
    """Copy ``calibration`` into the capture folder as :data:`CALIBRATION_FILE` (atomically)."""
    data = json.loads(Path(calibration).read_text())
    atomic_write_json(Path(capture_path) / CALIBRATION_FILE, data)


__all__ = ["CALIBRATION_FILE", "METHOD_CALIBRATIONS", "RIG_KEYS", "attach_calibration", "calibration_for",
           "check_rig_spec", "rig_geometry"]
