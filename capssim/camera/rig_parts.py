"""The parts of an imperfect camera array, one at a time: a linear polarizer at any angle with a finite
extinction ratio, and the smooth vignetting map of a camera (:class:`capssim.camera.rig.RigModel` composes them).

Analyzer at an arbitrary angle (from the four stored angles). The 12-channel image holds
``I(a)`` at ``a`` in (0, 45, 90, 135); with ``S0 = (I0+I45+I90+I135)/2``, ``S1 = I0-I90``,
``S2 = I45-I135`` a polarizer at ``theta`` transmits ``s(theta) = (S0 + S1 cos 2theta +
S2 sin 2theta)/2``. capssim reads it as ``I(a) + s(theta) - s(a)`` with ``a`` the nearest stored
angle: exact for physically consistent images, and the stored channel itself at ``theta = a``.
With extinction ratio ``ER`` the polarizer reads ``(ER I(theta) + I(theta + 90)) / (ER + 1)``.

Vignetting: a 2-D polynomial of degree <= 4 (:data:`VIGNETTING_MONOMIALS`) in normalised raw
coordinates (:func:`normalised_raw_coordinates`, [-1, 1] with the frame centre at 0).
"""

from __future__ import annotations

import math

import numpy as np

from capssim.conventions import POLARIZER_ANGLES_DEG
from capssim.errors import InputError

#: ``(i, j)`` exponents of ``u^i v^j`` of the vignetting polynomial, by total degree then ``i`` descending
VIGNETTING_MONOMIALS = tuple((d - j, j) for d in range(5) for j in range(d + 1))
N_VIGNETTING_TERMS = len(VIGNETTING_MONOMIALS)


# -- the analyzer at arbitrary angles --------------------------------------------------------------
def _stokes_form(theta_deg: float) -> np.ndarray:
    """``(4,)`` coefficients over ``I(0, 45, 90, 135)`` of ``s(theta) = (S0 + S1 cos 2t + S2 sin 2t) / 2``."""
    c, s = math.cos(math.radians(2 * theta_deg)), math.sin(math.radians(2 * theta_deg))
    return np.array([0.25 + 0.5 * c, 0.25 + 0.5 * s, 0.25 - 0.5 * c, 0.25 - 0.5 * s])


def polarizer_reading(theta_deg: float) -> np.ndarray:
    """``(4,)`` coefficients over ``I(0, 45, 90, 135)`` of an ideal polarizer at ``theta_deg``.

    ``I(a) + s(theta) - s(a)`` with ``a`` the stored angle nearest to ``theta`` (module docstring).
    """
    nearest = int(round(theta_deg / 45.0)) * 45 % 180
    row = _stokes_form(theta_deg) - _stokes_form(nearest)
    row[POLARIZER_ANGLES_DEG.index(nearest)] += 1.0
    if abs(theta_deg - round(theta_deg / 45.0) * 45) < 1e-12:
        row = np.zeros(4)
        row[POLARIZER_ANGLES_DEG.index(nearest)] = 1.0
    return row


def analyzer_row(theta_deg: float, extinction_ratio: float) -> np.ndarray:
    """``(4,)``: a polarizer at ``theta_deg`` with ``T_max/T_min = extinction_ratio`` (inf: ideal)."""
    if math.isinf(extinction_ratio):
        return polarizer_reading(theta_deg)
    t_par, t_perp = extinction_ratio / (extinction_ratio + 1.0), 1.0 / (extinction_ratio + 1.0)
    return t_par * polarizer_reading(theta_deg) + t_perp * polarizer_reading(theta_deg + 90.0)


# -- vignetting polynomials --------------------------------------------------------------------------
def normalised_raw_coordinates(raw_shape) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` ``(H, W)`` each: raw columns and rows mapped to [-1, 1] (frame centre 0)."""
    h, w = (int(s) for s in raw_shape)
    u = (np.arange(w) - (w - 1) / 2.0) / max((w - 1) / 2.0, 0.5)
    v = (np.arange(h) - (h - 1) / 2.0) / max((h - 1) / 2.0, 0.5)
    return np.meshgrid(u, v, indexing="xy")


def vignetting_design(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``(*u.shape, 15)``: the monomials ``u^i v^j`` of :data:`VIGNETTING_MONOMIALS` at each point."""
    return np.stack([u ** i * v ** j for i, j in VIGNETTING_MONOMIALS], axis=-1)


def radial_vignetting(corner_falloff: float, *, centre_uv: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """``(15,)`` coefficients of ``V = (1 - f (0.6 r^2 + 0.4 r^4)) / V(0, 0)``, ``r`` = 1 at the corners.

    ``corner_falloff`` ``f`` in [0, 0.9]: 0.2 puts a centred map's corners at 80 %;
    ``centre_uv``: the optical centre in normalised raw coordinates (|u|, |v| <= 0.5).
    """
    if not (0.0 <= corner_falloff <= 0.9):
        raise InputError("vignetting", corner_falloff, "a corner fall-off in [0, 0.9] (0.2 = corners at 80 %)")
    if not all(abs(c) <= 0.5 for c in centre_uv):
        raise InputError("vignetting centre", centre_uv, "normalised coordinates within [-0.5, 0.5]")
    grid = np.linspace(-1.0, 1.0, 9)
    u, v = np.meshgrid(grid, grid, indexing="xy")
    r2 = ((u - centre_uv[0]) ** 2 + (v - centre_uv[1]) ** 2) / 2.0
    values = 1.0 - corner_falloff * (0.6 * r2 + 0.4 * r2 ** 2)
    centre = 1.0 - corner_falloff * (0.6 * (sum(c * c for c in centre_uv) / 2) + 0.4 * (sum(c * c for c in centre_uv) / 2) ** 2)
    coef, *_ = np.linalg.lstsq(vignetting_design(u, v).reshape(-1, N_VIGNETTING_TERMS), values.ravel() / centre,
                               rcond=None)
    return coef


def flat_vignetting() -> np.ndarray:
    """``(15,)`` coefficients of the flat map (1 everywhere): no vignetting."""
    coef = np.zeros(N_VIGNETTING_TERMS)
    coef[0] = 1.0
    return coef
