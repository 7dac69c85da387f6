"""Calibration captures of a camera array, simulated or rendered (docs: guides/calibration.md).

A calibration capture is an ordinary capture folder whose ``meta.json`` holds
``"calibration": {"target": ..., "level": L, ...}``; :func:`make_calibration_captures` writes one
set, all through the same rig and the same aperture homographies:

* ``flat``: uniform unpolarized light, every channel ``L`` (gain and vignetting);
* ``polarizer-<phi>deg`` (``K >= 3``): uniform light through an ideal linear polarizer at ``phi``,
  channel ``I(a) = L (1 + cos 2(a - phi))`` (polarizer angles and extinction ratios, Malus's law);
  with ``frames > 1`` each uniform target is captured ``frames`` times (``flat-frame01`` ...), with
  independent noise, as a person averages frames on a real rig;
* ``geometry``: a planar target textured at every scale (the aperture homographies);
* ``star``: a sinusoidal Siemens star with ``cycles`` and ``center_rowcol`` (the PSF).

Simulated captures go through :func:`capssim.simulate.simulate_capture`, rendered ones through
:func:`capssim.render.render_capture` (the ``calibration-sheet``, ``textured`` and
``siemens-star`` scenes, planar warp path); both apply the rig with the one camera model.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.camera_setup import CameraSetup, as_setup
from capssim.camera.homography import random_aperture_homographies
from capssim.camera.rig import RigModel, write_rig_json
from capssim.camera.sensor import Sensor
from capssim.captures.capture import Capture, write_capture
from capssim.errors import InputError
from capssim.files.imageio import atomic_write_json, check_output_free
from capssim.render import render_capture
from capssim.simulate import simulate_capture

TARGETS = ("flat", "polarizer", "geometry", "star")
#: light levels of the uniform targets (each channel; S0 = 2 level): bright, never saturating
FLAT_LEVEL, POLARIZER_LEVEL = 0.4, 0.45
#: spokes of the star target
STAR_CYCLES = 36
#: the sweep's first angle, so that no sample sits exactly on a nominal polarizer angle
SWEEP_OFFSET_DEG = 3.75
MIN_POLARIZER_ANGLES = 3
#: most frames per uniform target: capture seeds are ``1000 seed + index``, so a set holds < 1000 captures
MAX_FRAMES = 5


def seeded_aperture_homographies(seed: int, hr_shape) -> np.ndarray:
    """``(4, 3, 3)``: the default pose ranges' aperture homographies, drawn reproducibly from ``seed``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 2201]))
    homographies, _ = random_aperture_homographies(rng, tuple(hr_shape))
    return homographies


def sweep_angles(count: int) -> list[float]:
    """``count`` polarizer angles (degrees), evenly over [0, 180), starting at :data:`SWEEP_OFFSET_DEG`."""
    if not (isinstance(count, (int, np.integer)) and MIN_POLARIZER_ANGLES <= count <= 180):
        raise InputError("polarizer_angles", count, f"an integer in [{MIN_POLARIZER_ANGLES}, 180]",
                         "Malus's law has 3 unknowns per aperture and colour; 12 angles are the default.")
    return [SWEEP_OFFSET_DEG + 180.0 * j / count for j in range(int(count))]


def polarized_field(size: int, level: float, polarizer_deg: float, *, dolp: float = 1.0) -> np.ndarray:
    """``(12, S, S)``: uniform light of level ``level`` through a polarizer at ``polarizer_deg`` (DoLP ``dolp``)."""
    angles = np.repeat([0.0, 45.0, 90.0, 135.0], 3)
    values = level * (1.0 + dolp * np.cos(np.radians(2.0 * (angles - polarizer_deg))))
    return np.broadcast_to(values[:, None, None], (12, size, size)).astype(np.float32).copy()


def texture_target(size: int, seed: int) -> np.ndarray:
    """``(12, S, S)`` unpolarized, neutral texture with detail at every scale (for registration), on [0.1, 0.7]."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    field = sum(gaussian_filter(rng.standard_normal((size, size)), s) * s for s in (0.7, 1.5, 3.0, 6.0, 12.0))
    field = (field - field.min()) / max(float(np.ptp(field)), 1e-12)
    return np.broadcast_to((0.1 + 0.6 * field)[None], (12, size, size)).astype(np.float32).copy()


def star_target(size: int, cycles: int = STAR_CYCLES) -> tuple[np.ndarray, list[float]]:
    """``(12, S, S)`` unpolarized sinusoidal Siemens star (mean 0.35, contrast 0.8) and its centre (row, col)."""
    centre = [(size - 1) / 2.0, (size - 1) / 2.0]
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    phi = np.arctan2(-(yy - centre[0]), xx - centre[1])
    r = np.hypot(yy - centre[0], xx - centre[1])
    star = np.where(r <= 0.48 * size, 0.35 * (1.0 + 0.8 * np.cos(cycles * phi)), 0.35)
    return np.broadcast_to(star[None], (12, size, size)).astype(np.float32).copy(), centre


def _frames(name: str, entry: dict, frames: int) -> list[tuple[str, dict]]:
    """``frames`` captures of one uniform target: ``name``, then ``name-frame01`` ... (each with ``"frame": j``)."""
    return [(name if j == 0 else f"{name}-frame{j:02d}", {**entry, "frame": j} if frames > 1 else dict(entry))
            for j in range(frames)]


def _entries(size: int, polarizer_angles: int, frames: int = 1) -> list[tuple[str, dict]]:
    """``(folder name, calibration entry)`` of every capture of one set."""
    if not (isinstance(frames, (int, np.integer)) and 1 <= frames <= MAX_FRAMES):
        raise InputError("frames", frames, f"an integer in [1, {MAX_FRAMES}] (captures per uniform target)",
                         "calibrate averages the frames of a target; more than a few add little at sigma 0.01.")
    out = _frames("flat", {"target": "flat", "level": FLAT_LEVEL}, int(frames))
    for phi in sweep_angles(polarizer_angles):
        out += _frames(f"polarizer-{phi:06.2f}deg",
                       {"target": "polarizer", "level": POLARIZER_LEVEL, "polarizer_deg": phi}, int(frames))
    out.append(("geometry", {"target": "geometry"}))
    out.append(("star", {"target": "star", "cycles": STAR_CYCLES}))
    return out


def _check_homographies(homographies) -> np.ndarray:
    """``(4, 3, 3)`` finite, invertible aperture homographies (HR reference -> aperture, x=col, y=row)."""
    h = np.asarray(homographies, dtype=np.float64)
    if h.shape != (4, 3, 3) or not np.all(np.isfinite(h)) or np.any(np.abs(np.linalg.det(h)) < 1e-12):
        raise InputError("aperture_homographies", f"array of shape {h.shape}",
                         "(4, 3, 3) finite, invertible homographies (HR reference -> aperture, x=col, y=row)",
                         "Pass a rig file's geometry, or leave it out for a seeded random draw.")
    return h


def _remove_stale_captures(out: Path, keep: set[str]) -> None:
    """With ``overwrite``: delete the capture folders that ``out/index.json`` of an earlier set lists
    and this set does not write (``calibrate OUT`` reads every capture folder under ``OUT``)."""
    try:
        old = json.loads((out / "index.json").read_text())
        names = [c["folder"] for c in old.get("captures", [])]
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return
    for name in names:
        folder = out / str(name)
        if str(name) not in keep and folder.parent == out and (folder / "meta.json").is_file():
            shutil.rmtree(folder)


def _simulated(entry: dict, size: int, setup: CameraSetup, homographies: np.ndarray, seed: int) -> Capture:
    target = entry["target"]
    if target in ("flat", "polarizer"):
        gt = polarized_field(size, entry["level"], entry.get("polarizer_deg", 0.0),
                             dolp=0.0 if target == "flat" else 1.0)
    elif target == "geometry":
        gt = texture_target(size, seed)
    else:
        gt, entry["center_rowcol"] = star_target(size, entry["cycles"])
    return simulate_capture(gt, setup, seed=seed, aperture_homographies=homographies,
                            source={"type": "calibration target", "target": target},
                            extra_meta={"calibration": entry})


def _rendered(entry: dict, size: int, setup: CameraSetup, homographies: np.ndarray, seed: int,
              spp: int | None) -> Capture:
    target = entry["target"]
    options = dict(size=size, spp=spp, seed=seed, setup=setup, aperture_homographies=homographies,
                   planar="on", record_timing=False)
    if target in ("flat", "polarizer"):
        params = {"level": entry["level"], "dolp": 0.0 if target == "flat" else 1.0,
                  "polarizer_deg": entry.get("polarizer_deg", 0.0)}
        capture = render_capture("calibration-sheet", scene_params=params, **options)
    elif target == "geometry":
        # the colour slide without its polarizing film: every aperture sees the same intensities
        capture = render_capture("textured", scene_params={"dolp_min": 0.0, "dolp_max": 0.0}, **options)
    else:
        capture = render_capture("siemens-star", scene_params={"cycles": entry["cycles"]}, **options)
        star = capture.meta.get("scene", {}).get("star") or {}
        if star.get("center_rowcol") is not None:
            entry["center_rowcol"] = star["center_rowcol"]
    capture.meta["calibration"] = entry
    return capture


def make_calibration_captures(out_dir, *, setup: CameraSetup | None = None, rig: RigModel | None = None,
                              sensor: Sensor | None = None, size: int = 256, renderer: str = "simulate", polarizer_angles: int = 12, seed: int = 0,
                              aperture_homographies: np.ndarray | None = None, frames: int = 1,
                              spp: int | None = 64, overwrite: bool = False) -> dict:
    """Write one calibration set of a rig under ``out_dir`` (module docstring: flat, polarizer sweep, geometry, star).

    Parameters
    ----------
    out_dir : str or pathlib.Path
        The folder of the set; one capture folder per target inside.
    setup : CameraSetup, optional
        The camera set-up of every capture (None: the default set-up, an ideal array).
    rig : RigModel, optional
        The rig, replacing the set-up's.
    sensor : Sensor, optional
        The sensor, replacing the set-up's.
    size : int
        HR pixels of the captures the calibration is for (the homographies depend on it).
    renderer : str
        ``simulate`` (:func:`~capssim.simulate.simulate_capture`) or ``mitsuba``.
    polarizer_angles : int
        Number K of sweep angles ``phi`` of the ideal polarizer, evenly over 180 deg.
    seed : int
        Seed of the noise and, unless given, of the homographies.
    aperture_homographies : numpy.ndarray, optional
        ``(4, 3, 3)`` HR reference -> aperture, shared by every capture (default: a draw of the
        default pose ranges from ``seed``).
    frames : int
        Captures of each uniform target (flat, every sweep angle), with independent noise.
    spp : int, optional
        Samples per HR pixel (``mitsuba``).
    overwrite : bool
        Replace an existing set.

    Returns
    -------
    dict
        The index, also written to ``out_dir/index.json``: ``captures`` (``folder``, ``target``, ...),
        ``renderer``, ``size``. ``out_dir/rig.json`` holds the true rig and homographies.
    """
    if renderer not in ("simulate", "mitsuba"):
        raise InputError("renderer", repr(renderer), "simulate or mitsuba")
    if not (isinstance(size, (int, np.integer)) and 32 <= size <= 4096 and size % 4 == 0):
        raise InputError("size", size, "a multiple of 4 in [32, 4096] (HR pixels)")
    entries = _entries(int(size), polarizer_angles, frames)
    out = check_output_free(out_dir, overwrite=overwrite, argument="OUTPUT")
    if aperture_homographies is None:
        aperture_homographies = seeded_aperture_homographies(seed, (size, size))
    aperture_homographies = _check_homographies(aperture_homographies)
    if overwrite:
        _remove_stale_captures(Path(out), {name for name, _ in entries})
    setup = as_setup(setup if sensor is None else as_setup(setup).replace(sensor=sensor), rig=rig)
    rig = setup.rig if setup.rig is not None else RigModel.ideal()
    index = {"format": "capssim-calibration-set", "version": 1, "renderer": renderer, "size": int(size),
             "rig": rig.to_dict(), "captures": []}
    for j, (name, entry) in enumerate(entries):
        capture_seed = int(seed) * 1000 + j
        if renderer == "simulate":
            capture = _simulated(dict(entry), size, setup, aperture_homographies, capture_seed)
        else:
            capture = _rendered(dict(entry), size, setup, aperture_homographies, capture_seed, spp)
        write_capture(Path(out) / name, capture, overwrite=overwrite)
        index["captures"].append({"folder": name, **capture.meta["calibration"]})
    atomic_write_json(Path(out) / "index.json", index)
    # the true rig and homographies, as a capssim-rig file: `capssim simulate --rig OUT/rig.json` captures
    # scenes through the same array
    write_rig_json(Path(out) / "rig.json", rig, geometry=ArrayGeometry(aperture_homographies, (size, size)),
                   calibrated=("truth",), source={"calibration_set": str(out)})
    return index


__all__ = ["seeded_aperture_homographies", "FLAT_LEVEL", "MAX_FRAMES", "POLARIZER_LEVEL", "STAR_CYCLES", "TARGETS", "make_calibration_captures",
           "polarized_field", "star_target", "sweep_angles", "texture_target"]

