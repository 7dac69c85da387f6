"""Physical validity of a camera array, checked when a rig or calibration file (or a ``meta.json`` rig) loads.

* the flat field ``gain_n V_n(u, v)`` is > 0 everywhere on the frame (:func:`check_vignetting`: the
  vignetting polynomial sampled on a 65 x 65 grid over the frame, corners included, must stay within
  [:data:`MIN_FLAT_FIELD`, :data:`MAX_FLAT_FIELD`]); a negative or zero map would make raw frames negative
  or black, a huge one (a gain of 1e300) frames of inf;
* every extinction ratio is > 1 (checked by :class:`capssim.camera.rig.RigModel`);
* the geometry is finite and invertible (:func:`check_homographies`: each 3x3 homography's condition
  number below :data:`MAX_CONDITION`, and its horizon ``h31 x + h32 y + h33 = 0`` outside the HR grid).

:data:`RIG_FILE_SPEC` is the schema of a ``capssim-rig`` file (``capssim calibrate``'s output and
``--rig FILE``); the ``rig`` block's values are checked by :meth:`capssim.camera.rig.RigModel.from_dict`.
Every problem is one line naming the file and the key.
"""

from __future__ import annotations

import numpy as np

from capssim.camera.rig_parts import normalised_raw_coordinates, vignetting_design
from capssim.errors import InputError
from capssim.files.schema import AnyMapping, Integer, Mapping, Nullable, Sequence, String

#: the least relative response the flat field may reach anywhere on the frame (gain has the same floor)
MIN_FLAT_FIELD = 1e-3
#: the largest relative response (gain has the same ceiling): 1000x the nominal response is no camera of the
#: array; past it the raw frames overflow to inf and the reconstruction diverges without naming the cause
MAX_FLAT_FIELD = 1e3
#: the largest condition number of a homography accepted as invertible
MAX_CONDITION = 1e12
#: the grid (per side) the vignetting polynomial is sampled on
FLAT_FIELD_GRID = 65


class _Free(AnyMapping):
    """Any JSON value (``rig`` values are checked by RigModel, homographies by :func:`check_homographies`)."""

    description = "any value"

    def __init__(self):
        super().__init__("any value")

    def check(self, value, path):
        return value


RIG_FILE_SPEC = Mapping({
    "format": String(), "version": Integer(),
    "rig": AnyMapping("a mapping of rig quantities (angle_offsets_deg, extinction_ratio, gain, vignetting, psf)"),
    "geometry": Nullable(Mapping({"hr_height": Integer(minimum=4, multiple_of=4),
                                  "hr_width": Integer(minimum=4, multiple_of=4), "aperture_homographies": _Free()},
                                 required=("hr_height", "hr_width", "aperture_homographies"),
                                 what="a mapping with hr_height, hr_width and aperture_homographies (4x3x3)")),
    "calibrated": Nullable(Sequence(String(), what="quantity names")),
    "uncertainty": Nullable(AnyMapping("a mapping of uncertainties")),
    "residuals": Nullable(AnyMapping("a mapping of residuals")),
    "source": Nullable(AnyMapping("a mapping (provenance)")),
}, required=("format", "version", "rig"), what="a capssim-rig file")


def check_vignetting(gain: np.ndarray, vignetting: np.ndarray, *, where: str = "rig vignetting") -> None:
    """Refuse a flat field ``gain_n V_n`` that is not > 0 everywhere on the frame.

    Parameters
    ----------
    gain : numpy.ndarray
        ``(4,)`` response at the frame centre.
    vignetting : numpy.ndarray
        ``(4, 15)`` polynomial coefficients (:data:`capssim.camera.rig_parts.VIGNETTING_MONOMIALS`).
    where : str
        The key named in the message.

    Raises
    ------
    InputError
        Naming the aperture, the lowest value and where (normalised coordinates ``u, v`` in [-1, 1]).
    """
    u, v = normalised_raw_coordinates((FLAT_FIELD_GRID, FLAT_FIELD_GRID))
    maps = (vignetting_design(u, v) @ np.asarray(vignetting, dtype=np.float64).T) * np.asarray(gain)[None, None, :]
    highest = float(maps.max())
    if np.isfinite(highest) and highest > MAX_FLAT_FIELD:
        _refuse_flat_field(where, maps, u, v, int(np.argmax(maps)), highest,
                           f"<= {MAX_FLAT_FIELD:g} over the whole frame (a response relative to the nominal 1)")
    worst = float(maps.min())
    if not np.isfinite(worst) or worst < MIN_FLAT_FIELD:
        _refuse_flat_field(where, maps, u, v, int(np.nanargmin(maps)), worst,
                           f">= {MIN_FLAT_FIELD:g} over the whole frame (a relative response; the constant term 1 "
                           "is no vignetting)")


def _refuse_flat_field(where: str, maps: np.ndarray, u: np.ndarray, v: np.ndarray, flat_index: int, value: float,
                       bound: str) -> None:
    """Raise the :class:`InputError` of a flat field out of its bound at ``maps``' flat index ``flat_index``."""
    row, col, n = np.unravel_index(flat_index, maps.shape)
    raise InputError(where, f"aperture {n}'s flat field reaching {value:.3g} at (u, v) = "
                            f"({u[row, col]:.2f}, {v[row, col]:.2f})",
                     f"coefficients whose flat field stays {bound}",
                     "Fit the vignetting again, or remove it for a flat frame.")


def check_homographies(homographies, hr_shape, *, where: str, horizon: bool = True) -> None:
    """Refuse homographies that are not finite and invertible, or whose horizon crosses the HR grid.

    Parameters
    ----------
    homographies : array_like
        ``(N, 3, 3)`` HR reference -> target pixel (x=col, y=row).
    hr_shape : tuple of int
        ``(2H, 2W)``, the grid they act on.
    where : str
        The file and key named in the message.
    horizon : bool
        Also refuse a horizon across the grid (a capture's stored warps are checked for it only
        where they are used: ``--true-warps``).

    Raises
    ------
    InputError
        One line naming ``where[n]`` and the problem.
    """
    h = np.asarray(homographies, dtype=np.float64)
    hh, ww = (int(s) for s in hr_shape)
    corners = np.array([[0, 0, 1], [ww - 1, 0, 1], [0, hh - 1, 1], [ww - 1, hh - 1, 1]], dtype=np.float64)
    for n, mat in enumerate(h):
        if not np.all(np.isfinite(mat)):
            raise InputError(f"{where}[{n}]", "non-finite values", "a finite 3x3 matrix")
        cond = float(np.linalg.cond(mat))
        if not np.isfinite(cond) or cond > MAX_CONDITION:
            raise InputError(f"{where}[{n}]", f"a singular matrix (condition number {cond:.3g})",
                             f"an invertible homography (condition number <= {MAX_CONDITION:g})",
                             "Calibrate the geometry again.")
        den = corners @ mat[2]
        if horizon and not (np.all(den > 0) or np.all(den < 0)):
            raise InputError(f"{where}[{n}]", f"a horizon crossing the {hh}x{ww} grid (denominator "
                                              f"{den.min():.3g} .. {den.max():.3g} at the corners)",
                             "a homography that keeps the whole grid in front of the camera",
                             "Calibrate the geometry again.")
