"""Which estimated aperture warps a camera array can have (:mod:`capssim.reconstruct.registration.estimate`).

An aperture warp ``H_n = R^-1 G_n R`` (HR reference -> aperture-HR, ``R``
:func:`capssim.camera.array_geometry.raw_matrix`) of an estimated raw-to-raw matrix ``G_n`` is *plausible* when its
rotation and isotropic scale are within :class:`~capssim.reconstruct.registration.parameters.RegistrationParameters`'
``max_rotation_deg`` and ``1 +- max_scale_error``; larger ones are false matches.
"""

from __future__ import annotations

import numpy as np

from capssim.camera.array_geometry import raw_matrix
from capssim.camera.homography import rotation_and_scale

from .engine import StackRegistration
from .parameters import RegistrationParameters

__all__ = ["aperture_warp", "implausible_apertures", "is_plausible"]


def aperture_warp(matrix: np.ndarray) -> np.ndarray | None:
    """The aperture warp ``H_n = R^-1 G_n R`` (normalized) of an estimated raw-to-raw matrix; None if degenerate."""
    rmat = raw_matrix()
    hn = np.linalg.inv(rmat) @ matrix @ rmat
    if not np.all(np.isfinite(hn)) or abs(np.linalg.det(hn[:2, :2])) < 1e-6:
        return None
    return hn / hn[2, 2]


def is_plausible(hn: np.ndarray, parameters: RegistrationParameters) -> bool:
    """Whether the rotation and scale of the aperture warp ``hn`` are within the parameters' limits."""
    rotation_deg, scale = rotation_and_scale(hn)
    return abs(rotation_deg) <= parameters.max_rotation_deg and abs(scale - 1.0) <= parameters.max_scale_error


def implausible_apertures(reg: StackRegistration, active: list[int], parameters: RegistrationParameters) -> list[int]:
    """The apertures of ``active`` whose estimated warp is degenerate or beyond the rotation and scale limits."""
    warps = [aperture_warp(m) for m in reg.matrices]
    return [n for hn, n in zip(warps, active) if hn is None or not is_plausible(hn, parameters)]
