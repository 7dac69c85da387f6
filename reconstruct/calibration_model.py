"""The calibration a CAPS reconstruction models the array with (issue "Real rigs").

``calibration`` (``capssim reconstruct --calibration``) says which model of the array a method
uses:

* ``None`` (the default): the capture's own ``meta.json["calibration_file"]`` when it names one,
  else the ideal array;
* ``"ideal"`` / ``"none"``: the ideal array (perfect polarizers, identical cameras, one PSF);
* ``"truth"``: the capture's true rig (``meta.json["rig"]``, simulated or rendered captures) and
  its true homographies;
* a path: a ``capssim-rig`` file (``capssim calibrate``'s output), whose geometry, when it has
  one, replaces the registration.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.rig import RIG_FORMAT_VERSION, RigModel, read_rig_json
from capssim.captures.capture import Capture
from capssim.errors import InputError

IDEAL_NAMES = ("ideal", "none")


@dataclass
class CalibrationModel:
    """``rig`` (the analyzer, gain, vignetting and PSFs), ``geometry`` (or ``None``: register) and a record."""

    rig: RigModel
    geometry: ArrayGeometry | None
    record: dict


def resolve_calibration(capture: Capture, calibration) -> CalibrationModel | None:
    """The :class:`CalibrationModel` that ``calibration`` names for ``capture`` (module docstring), or ``None``."""
    if calibration is None:
        named = capture.meta.get("calibration_file")
        if not named or capture.path is None:
            return None
        calibration = str(Path(capture.path) / named)
    if isinstance(calibration, str) and calibration.lower() in IDEAL_NAMES:
        return None
    if capture.cfa != "RGGB":  # the calibrated analyzer and flat field are per RGGB site
        raise InputError("--calibration", f"{calibration} for a capture with cfa {capture.cfa}",
                         "an RGGB capture (calibrated array models assume the RGGB sites)",
                         "Reconstruct with --calibration ideal.")
    if isinstance(calibration, str) and calibration.lower() == "truth":
        rig = capture.rig
        if rig is None:
            raise InputError("--calibration", "truth", "a capture with a true rig (meta.json rig)",
                             "Simulate or render it with --rig, or give a calibration file.")
        return CalibrationModel(rig, capture.geometry, {"source": "truth (meta.json rig and homographies)"})
    loaded = read_rig_json(calibration, argument="--calibration")
    geometry = loaded.geometry
    if geometry is not None and tuple(geometry.hr_shape) != tuple(capture.hr_shape):
        raise InputError("--calibration", f"{calibration}: geometry for {geometry.hr_shape[0]}x{geometry.hr_shape[1]}",
                         f"the capture's HR size {capture.hr_shape[0]}x{capture.hr_shape[1]}",
                         "Calibrate with captures of the same size (capssim calibration-captures --size).")
    return CalibrationModel(loaded.rig, geometry, {"source": str(calibration), "calibrated": list(loaded.calibrated),
                                                   "format_version": RIG_FORMAT_VERSION})


__all__ = ["CalibrationModel", "IDEAL_NAMES", "resolve_calibration"]
