"""``--uncertainty N``: the error bars of one reconstruction (the bootstrap of :mod:`.bootstrap`, the calibration of
:mod:`.conformal`, the intervals of :mod:`.intervals`), as the dispatcher runs them after the method.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from capssim.errors import InputError

from .bootstrap import MAX_REGISTRATION_JITTER_HR_PX, WARM_ITERATIONS, capture_bootstrap, check_replicates
from .conformal import NOMINAL, calibration_scales
from .intervals import bootstrap_spreads, uncertainty_maps
from .maps import UncertaintyMaps, stokes_layout

__all__ = ["UNCERTAINTY_OPTIONS", "check_uncertainty_options", "reconstruction_uncertainty"]

#: the keywords of :func:`reconstruction_uncertainty` a caller may set (``uncertainty_options``), with their defaults
UNCERTAINTY_OPTIONS = {"seed": 0, "equivariant": False, "warm_iterations": WARM_ITERATIONS,
                       "registration_jitter_hr_px": None, "calibration": None}


def check_uncertainty_options(replicates, options: dict | None) -> tuple[int, dict]:
    """The replicate count and the options over their defaults; :class:`InputError` for an unknown one."""
    count = check_replicates(replicates)
    options = dict(options or {})
    unknown = sorted(set(options) - set(UNCERTAINTY_OPTIONS))
    if unknown:
        raise InputError("uncertainty options", ", ".join(unknown), "some of " + ", ".join(UNCERTAINTY_OPTIONS))
    if int(options.get("warm_iterations", WARM_ITERATIONS)) < 1:
        raise InputError("uncertainty option warm_iterations", options["warm_iterations"], "an integer >= 1")
    jitter = options.get("registration_jitter_hr_px")
    if jitter is not None and not (np.isfinite(float(jitter)) and 0 <= float(jitter) <= MAX_REGISTRATION_JITTER_HR_PX):
        raise InputError("uncertainty option registration_jitter_hr_px", jitter,
                         f"a number in [0, {MAX_REGISTRATION_JITTER_HR_PX:g}] (HR pixels)")
    return count, {**UNCERTAINTY_OPTIONS, **options}


def reconstruction_uncertainty(capture, method: str, image: np.ndarray, record: dict, *, replicates: int,
                               run: Callable, run_options: dict, **options) -> UncertaintyMaps:
    """The calibrated error bars of ``method``'s reconstruction ``image`` ``(12, 2H, 2W)`` of ``capture``.

    ``record`` is the reconstruction's (its options, registration, resolved choices, history); ``run`` the
    dispatcher and ``run_options`` its keywords as the reconstruction used them; ``options``: those of
    :data:`UNCERTAINTY_OPTIONS`. The maps' record holds the bootstrap's settings, its time and the calibration.
    """
    count, options = check_uncertainty_options(replicates, options)
    t0 = time.perf_counter()
    scales, calibration = calibration_scales(method, capture.sensor, calibration=options["calibration"])
    moments, info = capture_bootstrap(
        capture, method, image, record, replicates=count, seed=int(options["seed"]),
        equivariant=bool(options["equivariant"]), warm_iterations=int(options["warm_iterations"]),
        registration_jitter_hr_px=options["registration_jitter_hr_px"], run=run, **run_options)
    maps = uncertainty_maps(image, bootstrap_spreads(moments), scales)
    maps.record = {"method": "parametric bootstrap, split-conformal calibration", "nominal_coverage": NOMINAL,
                   **info, "calibration": calibration, "stokes_layout": stokes_layout(),
                   "files": {"std": "recon/METHOD.std.tiff (12, 2H, 2W)",
                             "interval90": "recon/METHOD.interval90.tiff (2 [lower, upper], 12, 2H, 2W)",
                             "stokes": "recon/METHOD.stokes-uncertainty.tiff (27, 2H, 2W): stokes_layout"},
                   "time_s": time.perf_counter() - t0}
    return maps
