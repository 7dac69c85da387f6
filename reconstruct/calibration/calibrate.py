"""A camera array's calibration from a set of calibration captures (docs: guides/calibration.md).

:func:`calibrate_captures` reads the captures (each with a ``meta.json["calibration"]`` entry),
groups them by target and runs each estimator on what it needs:

========== ======================================== ===================================
target      measures                                 needs
========== ======================================== ===================================
flat        gain, vignetting (:mod:`.flat_field`)    --
polarizer   angles, extinction ratios (:mod:`.malus`) a flat field; >= 3 distinct angles
geometry    aperture homographies (:mod:`.geometry`)  (a flat field, if any)
star        per-aperture PSF width (:mod:`.psf`)       geometry (or the star's own registration), gt.tiff
========== ======================================== ===================================

Quantities whose captures are missing keep their ideal values and are not listed in the file's
``calibrated``. The result is a ``capssim-rig`` file with the uncertainty of every number and the
fit residuals.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from capssim.camera.psf import PSF
from capssim.camera.rig import RigFile, RigModel, write_rig_json
from capssim.captures.capture import Capture, read_capture
from capssim.errors import InputError

from .flat_field import MAX_SATURATED_FRACTION, fit_flat_field
from .geometry_fit import fit_geometry
from .malus import fit_malus
from .psf_fit import fit_psf_sigmas

log = logging.getLogger(__name__)

TARGETS = ("flat", "polarizer", "geometry", "star")


def load_calibration_set(paths) -> dict[str, list[Capture]]:
    """Read calibration captures (folders, or folders of them) and group them by target."""
    folders: list[Path] = []
    for p in paths:
        p = Path(p)
        if (p / "meta.json").is_file():
            folders.append(p)
        elif p.is_dir() and any((c / "meta.json").is_file() for c in p.iterdir() if c.is_dir()):
            folders += sorted(c for c in p.iterdir() if (c / "meta.json").is_file())
        else:
            raise InputError("CAPTURES", str(p), "capture folders (with meta.json) or a folder of them",
                             "Make a set with `capssim calibration-captures -o OUT`.")
    groups: dict[str, list[Capture]] = {t: [] for t in TARGETS}
    seen: dict[str, Path] = {}
    for f in folders:
        cap = read_capture(f, load_gt=True)
        digest = hashlib.sha256(np.ascontiguousarray(cap.caps_raw).tobytes()).hexdigest()
        if digest in seen:  # the same folder twice (or a copy): counting it twice would understate the uncertainty
            log.warning("CAPTURES: %s is the same capture as %s (identical raw frames); counted once", f, seen[digest])
            continue
        seen[digest] = f
        if cap.cfa != "RGGB":
            raise InputError("CAPTURES", f"{f}: cfa {cap.cfa}", "RGGB calibration captures (the estimators "
                             "read the RGGB sites)", "Calibrate with an RGGB camera array.")
        entry = cap.meta.get("calibration")
        if not isinstance(entry, dict) or entry.get("target") not in TARGETS:
            raise InputError("CAPTURES", f"{f}: meta.json calibration = {entry!r}",
                             f"a calibration entry with target in {TARGETS}", "See docs: guides/calibration.md.")
        groups[entry["target"]].append(cap)
    shapes = {c.raw_shape for g in groups.values() for c in g}
    if len(shapes) > 1:
        raise InputError("CAPTURES", f"raw sizes {sorted(shapes)}", "one size for every calibration capture")
    if not any(groups.values()):
        raise InputError("CAPTURES", "no captures", "at least a flat field")
    _warn_other_cameras(groups)
    return groups


#: what names the camera a calibration capture was taken with (``meta.json`` keys)
CAMERA_KEYS = ("rig", "sensor", "dofp_layout")


def _camera(cap: Capture) -> dict:
    """The camera of a calibration capture: its ``meta.json`` rig (the true array of a simulated set), sensor and
    layout, and the rig of the set it belongs to (``index.json`` beside it, when there is one)."""
    camera = {key: cap.meta.get(key) for key in CAMERA_KEYS}
    index = Path(cap.path).parent / "index.json" if cap.path is not None else None
    if index is not None and index.is_file():
        try:
            camera["set rig"] = json.loads(index.read_text()).get("rig")
        except (OSError, ValueError, AttributeError):
            pass
    return camera


def _warn_other_cameras(groups: dict) -> None:
    """One warning (with the count) when captures were taken with another camera than the flat field (or, without
    one, than the first capture): the flat's gains and vignetting would calibrate a rig that took none of them."""
    captures = [c for g in groups.values() for c in g]
    reference = (groups["flat"] or captures)[0]
    ref = _camera(reference)
    others = []
    for cap in captures:
        other = _camera(cap)
        differ = [key for key in ref if key in other and other[key] != ref[key]]
        if cap is not reference and differ:
            others.append((cap, differ))
    if others:
        first, differ = others[0]
        log.warning("CAPTURES: %d of %d captures were taken with another camera than %s (first: %s; %s differ): "
                    "calibrated as one rig, but a flat field from another rig gives gains and vignetting that are "
                    "not this rig's; calibrate each rig from its own captures", len(others), len(captures),
                    reference.path, first.path, ", ".join(differ))


def _flat(groups) -> tuple:
    caps = groups["flat"]
    if not caps:
        return None, None
    for c in caps:
        frac = float(np.mean(c.caps_saturated()))
        if frac > MAX_SATURATED_FRACTION:
            raise InputError("CAPTURES", f"flat field {c.path}: {100 * frac:.3g} % saturated pixels",
                             f"at most {100 * MAX_SATURATED_FRACTION:g} %", "Lower the exposure or the light level.")
    levels = {float(c.meta["calibration"].get("level") or 0) for c in caps}
    level = levels.pop() if len(levels) == 1 else 0.0
    absolute = level > 0
    fit = fit_flat_field(np.stack([c.caps_float() for c in caps]), level if absolute else 1.0)
    if not absolute:  # real rigs: the light level is unknown, gains are relative to their mean
        fit.coefficients /= fit.gain.mean()
        fit.gain_std /= fit.gain.mean()
        fit.gain /= fit.gain.mean()
    return fit, absolute


def _sweep(groups, flat_fit, raw_shape):
    caps = groups["polarizer"]
    if not caps:
        return None
    if flat_fit is None:
        raise InputError("CAPTURES", "a polarizer sweep without a flat field", "a flat-field capture too",
                         "The sweep is divided by the flat field before Malus's law is fitted.")
    phi = [float(c.meta["calibration"].get("polarizer_deg", np.nan)) for c in caps]
    if len({round(p % 180.0, 6) for p in phi if np.isfinite(p)}) < 3:
        raise InputError("CAPTURES", f"a polarizer sweep at {sorted(phi)} deg",
                         "at least 3 distinct polarizer angles (12 recommended)",
                         "Malus's law has 3 unknowns per aperture and colour.")
    levels = [float(c.meta["calibration"].get("level") or 1.0) for c in caps]
    return fit_malus(np.stack([c.caps_float() for c in caps]), phi, levels, flat_fit.maps(raw_shape),
                     flat_fit.noise_sigma)


def calibrate_captures(paths, output, *, source: dict | None = None) -> RigFile:
    """Calibrate a rig from calibration captures and write the ``capssim-rig`` file ``output``.

    Parameters
    ----------
    paths : list of str or pathlib.Path
        Calibration sets or capture folders (flat field, polarizer sweep, geometry target, star;
        :func:`~capssim.dataset.calibration_captures.make_calibration_captures`); each present target
        calibrates its quantities.
    output : str or pathlib.Path
        The ``capssim-rig`` JSON file to write.
    source : dict, optional
        Provenance stored in the file.

    Returns
    -------
    RigFile
        ``rig`` (a :class:`~capssim.camera.rig.RigModel`), ``calibrated`` (the measured quantities),
        ``geometry``, ``uncertainty`` and ``residuals``.
    """
    t0 = time.perf_counter()
    groups = load_calibration_set(paths)
    any_cap = next(c for g in groups.values() for c in g)
    raw_shape, hr_shape = any_cap.raw_shape, any_cap.hr_shape
    rig, calibrated, unc, res = RigModel.ideal(), [], {}, {}
    flat_fit, absolute = _flat(groups)
    if flat_fit is not None:
        rig = replace(rig, gain=flat_fit.gain, vignetting=flat_fit.vignetting)
        calibrated += ["gain", "vignetting"]
        unc["gain"] = flat_fit.gain_std.tolist()
        res["flat_field"] = {"relative_rms": flat_fit.residual_rms.tolist(), "noise_sigma": flat_fit.noise_sigma,
                             "gain_reference": "absolute (flat level from meta.json)" if absolute
                             else "relative (mean gain 1: the flat's light level is unknown)"}
    malus = _sweep(groups, flat_fit, raw_shape)
    if malus is not None:
        rig = replace(rig, angle_offsets_deg=malus.angle_offsets_deg, extinction_ratio=malus.extinction_ratio)
        calibrated += ["angle_offsets_deg", "extinction_ratio"]
        unc.update({"angle_offsets_deg": malus.angle_std.tolist(), "extinction_ratio": malus.er_std.tolist(),
                    "theta_deg_per_colour": malus.theta_std.tolist()})
        res["malus"] = {"theta_deg_per_colour": malus.theta_deg.tolist(), "rms": malus.rms.tolist(),
                        "phi_deg": malus.samples[0].tolist(), "means": malus.samples[1].tolist(),
                        "used": malus.samples[2].tolist()}
    flat_maps = flat_fit.maps(raw_shape) if flat_fit is not None else None
    geometry = None
    if groups["geometry"]:
        cap = groups["geometry"][0]
        geometry, res["geometry"] = fit_geometry(cap.caps_float(), cap.caps_saturated(), flat_maps, hr_shape)
        calibrated.append("geometry")
    if groups["star"]:
        rig, geometry = _star(groups["star"][0], rig, geometry, flat_maps, flat_fit, hr_shape, unc, res)
        calibrated.append("psf")
    res["time_s"] = time.perf_counter() - t0
    src = {"captures": [str(c.path) for g in groups.values() for c in g], **(source or {})}
    write_rig_json(output, rig, geometry=geometry, calibrated=calibrated, uncertainty=unc, residuals=res, source=src)
    log.info("calibrated %s from %d captures in %.1f s", ", ".join(calibrated), len(src["captures"]), res["time_s"])
    return RigFile(rig, geometry, tuple(calibrated), unc, res, src, Path(output))


def _star(cap: Capture, rig: RigModel, geometry, flat_maps, flat_fit, hr_shape, unc: dict, res: dict):
    if cap.gt is None:
        raise InputError("CAPTURES", f"star capture {cap.path} without gt.tiff",
                         "the star's 12-channel ground truth (gt.tiff) on the HR grid",
                         "Render or simulate the star target, or write its pattern as gt.tiff.")
    if geometry is None:
        geometry, res["geometry"] = fit_geometry(cap.caps_float(), cap.caps_saturated(), flat_maps, hr_shape)
    noise = flat_fit.noise_sigma if flat_fit is not None else 0.01
    sigmas, stds, record = fit_psf_sigmas(cap.gt, cap.caps_float(), geometry, rig, noise_sigma=noise,
                                          physical_warp=cap.meta.get("kind") != "simulated")
    unc["psf_sigma_hr_px"] = stds.tolist()
    res["psf"] = record
    rig = replace(rig, psf=tuple(PSF.gaussian(float(s)).to_spec() for s in sigmas))
    return rig, geometry


__all__ = ["TARGETS", "calibrate_captures", "load_calibration_set"]
