"""Plane homographies: construction, decomposition, application and registration error.

All matrices act on ``(x=col, y=row, 1)`` with pixel centres on integers. The array's frames
(HR reference, aperture-HR, sub-image) and the derivation of the 16 sub-image homographies from
the 4 aperture homographies live in :mod:`capssim.camera.array_geometry`.
"""

from __future__ import annotations

import math

import numpy as np

from capssim.conventions import N_APERTURES
from capssim.errors import InputError


def similarity(shift_xy=(0.0, 0.0), rotation_deg: float = 0.0, scale: float = 1.0,
               center_xy=(0.0, 0.0)) -> np.ndarray:
    """Rotation by ``rotation_deg`` (counter-clockwise on the display, i.e. towards -row)
    and scale about ``center_xy``, then a shift; maps input -> output coordinates."""
    cx, cy = center_xy
    t = math.radians(rotation_deg)
    c, s = scale * math.cos(t), scale * math.sin(t)
    # y points down, so a display-CCW rotation is (x, y) -> (c x + s y, -s x + c y)
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    to_c = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    back = np.array([[1.0, 0.0, cx + shift_xy[0]], [0.0, 1.0, cy + shift_xy[1]], [0.0, 0.0, 1.0]])
    return back @ rot @ to_c


def rotation_and_scale(h) -> tuple[float, float]:
    """Rotation (deg, ``atan2(a10 - a01, a00 + a11)`` of the linear part ``a``: from +x towards +y,
    i.e. clockwise on the display) and isotropic scale ``sqrt(|det a|)`` of a ``(3, 3)`` homography."""
    a = np.asarray(h, dtype=np.float64)[:2, :2]
    return (float(math.degrees(math.atan2(a[1, 0] - a[0, 1], a[0, 0] + a[1, 1]))),
            float(math.sqrt(abs(np.linalg.det(a)))))


#: upper limits of the random pose ranges: rotation (degrees), relative scale error (exclusive)
POSE_LIMITS = {"rotation_max_deg": 45.0, "scale_max": 0.5}


def check_pose_ranges(hr_shape: tuple[int, int], *, shift_max_px: float, rotation_max_deg: float,
                      scale_max: float) -> None:
    """Refuse (:class:`~capssim.errors.InputError`) pose ranges outside the valid ones.

    ``shift_max_px`` in [0, min(H, W)) HR pixels, ``rotation_max_deg`` in [0, 45],
    ``scale_max`` in [0, 0.5).
    """
    side = min(int(v) for v in hr_shape)
    checks = (("shift_max_px", shift_max_px, 0 <= shift_max_px < side,
               f"a number in [0, {side:g}) HR pixels (less than the image's smaller side: the apertures must "
               "overlap)"),
              ("rotation_max_deg", rotation_max_deg, 0 <= rotation_max_deg <= POSE_LIMITS["rotation_max_deg"],
               "a number of degrees in [0, 45]"),
              ("scale_max", scale_max, 0 <= scale_max < POSE_LIMITS["scale_max"],
               "a relative scale error in [0, 0.5) (the scale 1 +- scale_max must stay positive)"))
    for arg, value, ok, valid in checks:
        if not (ok and math.isfinite(value)):
            raise InputError(arg, value, valid)


def random_aperture_homographies(rng: np.random.Generator, hr_shape: tuple[int, int], *,
                                 shift_max_px: float = 2.0, rotation_max_deg: float = 0.5,
                                 scale_max: float = 0.005) -> tuple[np.ndarray, list[dict]]:
    """Random similarity per aperture (uniform ranges), the reference aperture 0 = identity.

    ``shift_max_px`` is in HR pixels; rotation and scale act about the image centre.
    Valid ranges (:data:`POSE_LIMITS`): shift less than the image's smaller side (the
    apertures must overlap), rotation at most 45 degrees, scale error below 0.5 (the scale
    ``1 +- scale_max`` stays positive). Returns ``(4, 3, 3)`` HR reference -> aperture-HR,
    and the drawn parameters.
    """
    h, w = hr_shape
    check_pose_ranges((h, w), shift_max_px=shift_max_px, rotation_max_deg=rotation_max_deg, scale_max=scale_max)
    center = ((w - 1) / 2.0, (h - 1) / 2.0)
    mats, params = [np.eye(3)], [{"shift_xy_px": [0.0, 0.0], "rotation_deg": 0.0, "scale": 1.0}]
    for _ in range(1, N_APERTURES):
        shift = rng.uniform(-shift_max_px, shift_max_px, size=2)
        rot = float(rng.uniform(-rotation_max_deg, rotation_max_deg))
        scale = 1.0 + float(rng.uniform(-scale_max, scale_max))
        mats.append(similarity(shift, rot, scale, center))
        params.append({"shift_xy_px": [float(shift[0]), float(shift[1])], "rotation_deg": rot, "scale": scale})
    return np.stack(mats), params


def apply_homography(h, xy: np.ndarray) -> np.ndarray:
    """Map points ``(..., 2)`` of ``(x, y)`` through ``h``."""
    xy = np.asarray(xy, dtype=np.float64)
    pts = np.concatenate([xy, np.ones((*xy.shape[:-1], 1))], axis=-1) @ np.asarray(h).T
    return pts[..., :2] / pts[..., 2:3]


def registration_error_hr_px(estimated, true, hr_shape: tuple[int, int], *, step: int = 8,
                             margin: int = 0) -> np.ndarray:
    """Per-image registration error in HR pixels: for ``(K, 3, 3)`` stacks of HR reference ->
    sub-image homographies, the mean distance between where the two map a grid of HR
    reference points, converted to HR pixels (one sub-image pixel = 4 HR pixels).

    Returns shape ``(K,)``.
    """
    est = np.asarray(estimated, dtype=np.float64).reshape(-1, 3, 3)
    tru = np.asarray(true, dtype=np.float64).reshape(-1, 3, 3)
    h, w = hr_shape
    ys, xs = np.meshgrid(np.arange(margin, h - margin, step), np.arange(margin, w - margin, step), indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel()], axis=-1).astype(np.float64)
    errs = []
    for he, ht in zip(est, tru):
        d = apply_homography(he, pts) - apply_homography(ht, pts)
        errs.append(4.0 * float(np.mean(np.hypot(d[:, 0], d[:, 1]))))
    return np.asarray(errs)

