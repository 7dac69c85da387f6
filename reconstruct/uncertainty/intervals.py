"""From the bootstrap's spread and the calibration's scales to the error bars of :mod:`.maps`.

For each group ``g`` (the 12 channels, S0, DoLP, AoP) with bootstrap spread ``s`` and calibrated scale ``q_g``
(:mod:`.conformal`): the 90 % interval is ``centre +- q_g max(s, floor_g)`` around the *reconstruction's own* value
(not the replicates' mean), and the written standard deviation is ``q_g / 1.645 max(s, floor_g)``, so that
``centre +- 1.645 std`` is the same interval. Intensities and S0 are bounded below by 0 and DoLP to [0, 1] (the
truth lies there, so the clip changes no coverage). The AoP's spread is circular: with ``R`` the length of the
replicates' mean unit vector of the doubled angle, ``s = deg(sqrt(-2 ln R)) / 2`` (Mardia and Jupp, "Directional
Statistics", 2000, eq. 2.3.11); its half-width is at most 90 degrees (the whole half-circle).
"""

from __future__ import annotations

import numpy as np

from capssim.stokes.polarization import aop_deg, dolp, stokes_from_12

from .bootstrap import MIN_S0, BootstrapMoments
from .conformal import FLOORS, Z90
from .maps import UncertaintyMaps

__all__ = ["bootstrap_spreads", "uncertainty_maps"]


def bootstrap_spreads(moments: BootstrapMoments) -> dict[str, np.ndarray]:
    """The raw spread of each group: ``12ch`` ``(12, H, W)``, ``S0``/``DoLP``/``AoP`` ``(3, H, W)`` (AoP in
    degrees, circular; module docstring)."""
    length = np.hypot(moments.mean("cos2aop"), moments.mean("sin2aop"))
    aop_std = np.rad2deg(np.sqrt(-2.0 * np.log(np.clip(length, 1e-12, 1.0)))) / 2.0
    return {"12ch": moments.std("channels"), "S0": moments.std("S0"), "DoLP": moments.std("DoLP"), "AoP": aop_std}


def uncertainty_maps(estimate: np.ndarray, spreads: dict[str, np.ndarray], scales: dict[str, float]) -> UncertaintyMaps:
    """The error bars of the reconstruction ``estimate`` ``(12, H, W)`` (module docstring).

    Parameters
    ----------
    estimate : numpy.ndarray
        The reconstruction, ``(12, H, W)`` on [0, 1].
    spreads : dict
        :func:`bootstrap_spreads` of its bootstrap.
    scales : dict
        ``q`` per group (:func:`~capssim.reconstruct.uncertainty.conformal.calibration_scales`).
    """
    estimate = np.asarray(estimate, dtype=np.float64)
    half = {g: scales[g] * np.maximum(spreads[g], FLOORS[g]) for g in spreads}
    std12 = half["12ch"] / Z90
    interval = np.stack([np.clip(estimate - half["12ch"], 0.0, None), estimate + half["12ch"]])
    stokes = stokes_from_12(estimate)
    s0, dolp_hat, aop_hat = stokes[0], dolp(stokes, axis=0, min_s0=MIN_S0), aop_deg(stokes, axis=0)
    aop_half = np.minimum(half["AoP"], 90.0)
    aop_lower = np.mod(aop_hat - aop_half, 180.0)
    planes = [half["S0"] / Z90, np.clip(s0 - half["S0"], 0.0, None), s0 + half["S0"],
              half["DoLP"] / Z90, np.clip(dolp_hat - half["DoLP"], 0.0, 1.0), np.clip(dolp_hat + half["DoLP"], 0.0, 1.0),
              half["AoP"] / Z90, aop_lower, aop_lower + 2.0 * aop_half]
    return UncertaintyMaps(std=std12, interval90=interval, stokes=np.concatenate(planes, axis=0))
