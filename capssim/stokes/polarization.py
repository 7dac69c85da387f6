"""Stokes parameters, DoLP and AoP (paper eq. 1-3), for numpy arrays and torch tensors.

Conventions (docs: guides/captures.md, "Conventions"):

* ``S0 = (I0 + I45 + I90 + I135) / 2``, ``S1 = I0 - I90``, ``S2 = I45 - I135``.
* ``I(a) = (S0 + S1 cos 2a + S2 sin 2a) / 2`` (Malus's law for an ideal analyzer).
* ``DoLP = sqrt(S1^2 + S2^2) / S0``: pixels with ``S0 <= min_s0`` get ``fill``; the result
  is clipped to [0, 1] unless ``clip=False``.
* ``AoP = 0.5 atan2(S2, S1)`` in degrees, wrapped to ``[0, 180)``. 0 deg is the +col axis;
  positive angles turn towards -row (up on the display).

NaN inputs propagate to NaN outputs at the same pixels only.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from capssim.conventions import N_CHANNELS, POLARIZER_ANGLES_DEG
from capssim.errors import InputError

ArrayLike = np.ndarray | torch.Tensor


def _xp(x):
    return torch if isinstance(x, torch.Tensor) else np


def _move_axis_first(x, axis: int):
    return torch.movedim(x, axis, 0) if isinstance(x, torch.Tensor) else np.moveaxis(x, axis, 0)


def _stack(parts, axis: int):
    if isinstance(parts[0], torch.Tensor):
        return torch.stack(parts, dim=axis)
    return np.stack(parts, axis=axis)


def stokes_from_intensities(intensities: ArrayLike, *, axis: int = 0) -> ArrayLike:
    """``(S0, S1, S2)`` from the four analyzer images ``I0, I45, I90, I135`` along ``axis``.

    Shape ``(..., 4, ...) -> (..., 3, ...)``, same array type.
    """
    if intensities.shape[axis] != 4:
        raise InputError("intensities", f"shape {tuple(intensities.shape)} (axis {axis} has {intensities.shape[axis]})",
                         "4 analyzer images (0, 45, 90, 135 deg) along axis")
    i0, i45, i90, i135 = _move_axis_first(intensities, axis)
    return _stack([(i0 + i45 + i90 + i135) / 2, i0 - i90, i45 - i135], axis)


def intensities_from_stokes(stokes: ArrayLike, *, angles_deg: Sequence[float] = POLARIZER_ANGLES_DEG,
                            axis: int = 0) -> ArrayLike:
    """Malus's law: ``I(a) = (S0 + S1 cos 2a + S2 sin 2a) / 2`` for each angle in ``angles_deg``.

    ``stokes`` has ``S0, S1, S2`` (S3 ignored if present) along ``axis``; the result has
    ``len(angles_deg)`` images there.
    """
    if stokes.shape[axis] not in (3, 4):
        raise InputError("stokes", f"shape {tuple(stokes.shape)}", "S0, S1, S2 (and optionally S3) along axis")
    s = _move_axis_first(stokes, axis)
    out = []
    for a in angles_deg:
        t = np.deg2rad(2.0 * float(a))
        out.append((s[0] + s[1] * float(np.cos(t)) + s[2] * float(np.sin(t))) / 2)
    return _stack(out, axis)


def split_12(image12: ArrayLike) -> ArrayLike:
    """``(12, ...)`` -> ``(4, 3, ...)``: polarizer angle, then colour (channel ``c = 3p + k``)."""
    if image12.shape[0] != N_CHANNELS:
        raise InputError("image12", f"shape {tuple(image12.shape)}", "12 channels on axis 0 (c = 3*p + k)")
    return image12.reshape(4, 3, *image12.shape[1:])


def stokes_from_12(image12: ArrayLike) -> ArrayLike:
    """``(12, H, W)`` -> Stokes per colour ``(3 [S0,S1,S2], 3 [R,G,B], H, W)``."""
    return stokes_from_intensities(split_12(image12), axis=0)


def twelve_from_stokes(stokes_rgb: ArrayLike) -> ArrayLike:
    """``(3 [S0,S1,S2], 3 [R,G,B], H, W)`` -> ``(12, H, W)`` through Malus's law."""
    inten = intensities_from_stokes(stokes_rgb, axis=0)  # (4, 3, H, W)
    return inten.reshape(N_CHANNELS, *inten.shape[2:])


def dolp(stokes: ArrayLike, *, axis: int = 0, min_s0: float = 1e-6, fill: float = 0.0,
         clip: bool = True) -> ArrayLike:
    """Degree of linear polarization from ``S0, S1, S2`` along ``axis``.

    Pixels with ``S0 <= min_s0`` (dark, or negative from noise) get ``fill`` (use
    ``float('nan')`` to mark them). NaN inputs give NaN.
    """
    xp = _xp(stokes)
    s0, s1, s2 = _move_axis_first(stokes, axis)[:3]
    mag = xp.sqrt(s1 * s1 + s2 * s2)
    dark = s0 <= min_s0
    safe_s0 = xp.where(dark, xp.ones_like(s0), s0)
    value = mag / safe_s0
    if clip:
        value = xp.clip(value, 0.0, 1.0) if xp is np else torch.clamp(value, 0.0, 1.0)
    value = xp.where(dark, xp.full_like(value, fill), value)
    nan = xp.isnan(s0) | xp.isnan(s1) | xp.isnan(s2)
    return xp.where(nan, xp.full_like(value, float("nan")), value)


def aop_deg(stokes: ArrayLike, *, axis: int = 0, min_s0: float | None = None, fill: float = 0.0) -> ArrayLike:
    """Angle of linear polarization ``0.5 atan2(S2, S1)`` in degrees, wrapped to ``[0, 180)``.

    With ``min_s0`` set, pixels with ``S0 <= min_s0`` get ``fill``. Where ``S1 = S2 = 0``
    the angle is undefined and reads 0.
    """
    xp = _xp(stokes)
    parts = _move_axis_first(stokes, axis)
    s1, s2 = parts[1] + 0.0, parts[2] + 0.0  # +0.0 turns -0.0 into 0.0 so atan2(0, 0) = 0
    angle = 0.5 * xp.rad2deg(xp.arctan2(s2, s1)) if xp is np else 0.5 * torch.rad2deg(torch.atan2(s2, s1))
    angle = angle % 180.0
    angle = xp.where(angle >= 180.0, angle - 180.0, angle)  # guards -0.0 % 180 rounding to 180
    if min_s0 is not None:
        angle = xp.where(parts[0] <= min_s0, xp.full_like(angle, fill), angle)
    return angle


def angle_difference_deg(a: ArrayLike, b: ArrayLike) -> ArrayLike:
    """Wrap-aware AoP difference in ``[-90, 90)`` degrees (AoP has period 180)."""
    d = (a - b + 90.0) % 180.0 - 90.0
    return d


def dark_mask(stokes: ArrayLike, *, axis: int = 0, min_s0: float) -> ArrayLike:
    """True where ``S0 <= min_s0`` (or NaN): pixels whose DoLP/AoP should not be trusted."""
    xp = _xp(stokes)
    s0 = _move_axis_first(stokes, axis)[0]
    return (s0 <= min_s0) | xp.isnan(s0)
