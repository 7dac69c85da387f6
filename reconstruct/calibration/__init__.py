"""``capssim calibrate``: measure an imperfect camera array from calibration captures.

One estimator per module, each with its reference:

* :mod:`~capssim.reconstruct.calibration.flat_field`: gain and vignetting (flat field);
* :mod:`~capssim.reconstruct.calibration.malus`: polarizer angles and extinction ratios (Malus's law);
* :mod:`~capssim.reconstruct.calibration.geometry_fit`: aperture homographies (planar target);
* :mod:`~capssim.reconstruct.calibration.psf_fit`: per-aperture PSF width (Siemens star);
* :mod:`~capssim.reconstruct.calibration.calibrate`: all of them from a set of captures, into a
  ``capssim-rig`` file (:func:`capssim.camera.rig.write_rig_json`).
"""

from .calibrate import calibrate_captures, load_calibration_set

__all__ = ["calibrate_captures", "load_calibration_set"]
