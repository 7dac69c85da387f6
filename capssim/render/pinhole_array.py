"""The camera array: four pinhole apertures on a 2x2 grid, their small random errors, and the
exact homographies and parallax they give.

Frames and units
----------------
* World: metres, the scene's own frame.
* Camera ``(right, down, forward)``: the columns of :attr:`PinholeCamera.rotation` in world
  coordinates. Image column grows along ``right``, row along ``down``.
* Pixels: ``(x=col, y=row)`` with pixel centres on integers (capssim convention); pixel
  ``(i, j)`` covers ``[j - 0.5, j + 0.5) x [i - 0.5, i + 0.5)``. The intrinsics
  ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]`` map camera coordinates to pixels. Mitsuba's
  film coordinates are ours + 0.5; a test pins our rays against Mitsuba's ``perspective``.

The array (defaults in :class:`RigTolerances`)
----------------------------------------------
Aperture ``n`` (polarizer at ``45 n`` deg) sits at the scene's camera origin plus
``B * (n % 2)`` along ``right`` and ``B * (n // 2)`` along ``down``: a 2x2 grid of
baseline ``B``, with aperture 0 (top-left) the reference that defines the ground-truth
grid. Apertures 1-3 get random assembly errors, drawn uniformly from the ranges: an
optical-axis tilt about the camera's right and down axes (``tilt_max_deg``), a roll about
the optical axis (``roll_max_deg``) and a focal-length scale (``focal_scale_max``). With
``converge=True`` (default) each sensor's principal point is offset so the scene's
reference point (at depth Z) images at the same pixel in every error-free aperture, as in
an aligned array: the remaining offsets at Z are the sub-pixel, non-redundant ones the
errors make (paper section 2.2), and objects off the reference depth show parallax
``f B (1/Z' - 1/Z)`` pixels.

For a plane ``n . X = c`` the map from the reference image to aperture n is exactly the
plane-induced homography::

    H_n = K_n R_n^T [ I + (o_0 - o_n) n^T / (c - n . o_0) ] R_0 K_0^-1

(:func:`plane_homography`). The capture stores it for the scene's reference plane; the
residual of every other depth is reported as parallax (:func:`parallax_residual`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from capssim.conventions import N_APERTURES
from capssim.errors import InputError


def look_at_rotation(origin, target, up) -> np.ndarray:
    """``(3, 3)`` rotation with columns ``(right, down, forward)`` of a camera at ``origin``
    looking at ``target`` with ``up`` pointing up in the image."""
    o, t, u = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    fwd = t - o
    if np.linalg.norm(fwd) < 1e-12:
        raise InputError("camera", "origin == target", "a camera looking somewhere")
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, u)  # forward x up = right (right-handed world)
    if np.linalg.norm(right) < 1e-9:
        raise InputError("camera.up", u.tolist(), "an up vector not parallel to the viewing direction")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    return np.stack([right, down, fwd], axis=1)


def axis_rotation(axis, angle_rad: float) -> np.ndarray:
    """Rodrigues rotation about a unit ``axis`` (right-handed)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * (k @ k)


@dataclass
class PinholeCamera:
    """A pinhole camera with square pixels; see the module docstring for the frames."""

    origin: np.ndarray
    rotation: np.ndarray  # columns: right, down, forward (world)
    focal_px: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        self.origin = np.asarray(self.origin, dtype=np.float64)
        self.rotation = np.asarray(self.rotation, dtype=np.float64)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.focal_px, 0.0, self.cx], [0.0, self.focal_px, self.cy], [0.0, 0.0, 1.0]])

    @property
    def up(self) -> np.ndarray:
        return -self.rotation[:, 1]

    @property
    def forward(self) -> np.ndarray:
        return self.rotation[:, 2]

    def project(self, points) -> np.ndarray:
        """World points ``(..., 3)`` -> pixel ``(..., 2)`` as ``(x=col, y=row)``."""
        p = (np.asarray(points, dtype=np.float64) - self.origin) @ self.rotation
        z = np.where(np.abs(p[..., 2]) < 1e-12, 1e-12, p[..., 2])
        return np.stack([self.focal_px * p[..., 0] / z + self.cx, self.focal_px * p[..., 1] / z + self.cy], axis=-1)

    def directions(self, xy) -> np.ndarray:
        """Pixel ``(..., 2)`` ``(x=col, y=row)`` -> unit world ray directions ``(..., 3)``."""
        xy = np.asarray(xy, dtype=np.float64)
        cam = np.stack([(xy[..., 0] - self.cx) / self.focal_px, (xy[..., 1] - self.cy) / self.focal_px,
                        np.ones(xy.shape[:-1])], axis=-1)
        d = cam @ self.rotation.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def expanded(self, margin: int) -> "PinholeCamera":
        """The same camera with ``margin`` more pixels on every side (same pixel grid)."""
        return replace(self, cx=self.cx + margin, cy=self.cy + margin, width=self.width + 2 * margin,
                       height=self.height + 2 * margin)

    def supersampled(self, factor: int) -> "PinholeCamera":
        """The same field of view on a grid ``factor`` times finer (pixel ``p`` -> ``factor p + (factor-1)/2``)."""
        k = int(factor)
        return replace(self, focal_px=self.focal_px * k, cx=(self.cx + 0.5) * k - 0.5, cy=(self.cy + 0.5) * k - 0.5,
                       width=self.width * k, height=self.height * k)

    def mitsuba_sensor(self, *, rfilter: str = "box") -> dict:
        """A Mitsuba ``perspective`` sensor dict equivalent to this camera (for checks)."""
        import mitsuba as mi

        fov = 2.0 * math.degrees(math.atan((self.width / 2.0) / self.focal_px))
        t = mi.ScalarTransform4f().look_at(origin=self.origin.tolist(),
                                           target=(self.origin + self.forward).tolist(), up=self.up.tolist())
        return {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": t,
                "principal_point_offset_x": ((self.width - 1) / 2.0 - self.cx) / self.width,
                "principal_point_offset_y": ((self.height - 1) / 2.0 - self.cy) / self.height,
                "film": {"type": "hdrfilm", "width": self.width, "height": self.height, "rfilter": {"type": rfilter}}}

    def to_meta(self) -> dict:
        return {"origin_m": self.origin.tolist(), "right": self.rotation[:, 0].tolist(),
                "down": self.rotation[:, 1].tolist(), "forward": self.rotation[:, 2].tolist(),
                "focal_px": self.focal_px, "principal_point_xy": [self.cx, self.cy],
                "width": self.width, "height": self.height}


def scale_matrix(factor: int) -> np.ndarray:
    """Pixel coordinates on a grid -> the same point on a grid ``factor`` times finer."""
    k = float(factor)
    return np.array([[k, 0.0, (k - 1) / 2], [0.0, k, (k - 1) / 2], [0.0, 0.0, 1.0]])


def shift_matrix(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RigTolerances:
    """Parameters of the 2x2 array (metres, degrees, relative scale); see the module docstring."""

    baseline_m: float = 0.04
    tilt_max_deg: float = 0.2
    roll_max_deg: float = 0.5
    focal_scale_max: float = 0.005
    converge: bool = True

    def __post_init__(self):
        for name in ("baseline_m", "tilt_max_deg", "roll_max_deg", "focal_scale_max"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InputError(f"geometry.{name}", repr(v), "a finite number >= 0")
        if not isinstance(self.converge, (bool, np.bool_)):
            raise InputError("geometry.converge", repr(self.converge), "true or false",
                             "Write --geometry converge=true (or false).")
        if self.focal_scale_max >= 0.5 or self.tilt_max_deg > 10 or self.roll_max_deg > 45:
            raise InputError("geometry", asdict(self), "small errors (focal scale < 0.5, tilt <= 10, roll <= 45 deg)")

    @classmethod
    def from_params(cls, params: dict | None) -> "RigTolerances":
        """The tolerances of a ``geometry_params`` mapping (missing keys: defaults), each value type-checked."""
        if params is not None and not isinstance(params, dict):
            raise InputError("geometry_params", type(params).__name__, "a mapping of geometry parameters")
        params = dict(params or {})
        known = {f for f in cls.__dataclass_fields__}
        unknown = sorted(set(params) - known)
        if unknown:
            raise InputError("geometry_params", unknown, f"keys among {sorted(known)}")
        return cls(**params)


@dataclass
class ArrayCameras:
    """The four aperture cameras at HR resolution, their drawn errors and plane homographies."""

    cameras: list[PinholeCamera]
    errors: list[dict]
    geometry: RigTolerances
    reference_depth_m: float
    plane_point: np.ndarray
    plane_normal: np.ndarray
    homographies: np.ndarray = field(default=None)  # (4, 3, 3) HR reference -> aperture-HR

    def to_meta(self) -> dict:
        return {"parameters": asdict(self.geometry), "reference_depth_m": self.reference_depth_m,
                "reference_plane": {"point_m": self.plane_point.tolist(), "normal": self.plane_normal.tolist()},
                "apertures": [{"index": n, "polarizer_deg": 45 * n, **self.errors[n], "camera": cam.to_meta()}
                              for n, cam in enumerate(self.cameras)]}


def plane_homography(ref: PinholeCamera, cam: PinholeCamera, plane_point, plane_normal) -> np.ndarray:
    """Exact homography ``ref`` pixel -> ``cam`` pixel for points on the plane (module docstring)."""
    n = np.asarray(plane_normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    c = float(n @ np.asarray(plane_point, dtype=np.float64))
    denom = c - float(n @ ref.origin)
    if abs(denom) < 1e-12:
        raise InputError("reference plane", "a plane through the reference camera", "a plane in front of it")
    inner = np.eye(3) + np.outer(ref.origin - cam.origin, n) / denom
    h = cam.K @ cam.rotation.T @ inner @ ref.rotation @ np.linalg.inv(ref.K)
    return h / h[2, 2]


def build_array(*, origin, target, up, fov_deg: float, size: int, geometry: RigTolerances,
                rng: np.random.Generator, plane_point=None, plane_normal=None) -> ArrayCameras:
    """The four apertures at HR resolution ``size x size`` for a scene camera pose.

    ``fov_deg`` is the reference aperture's horizontal field of view. The reference plane
    defaults to the fronto-parallel plane through ``target``.
    """
    if not (0 < fov_deg < 170):
        raise InputError("fov_deg", fov_deg, "a field of view in (0, 170) degrees")
    rot0 = look_at_rotation(origin, target, up)
    f = (size / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    c = (size - 1) / 2.0
    origin = np.asarray(origin, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    plane_point = target if plane_point is None else np.asarray(plane_point, dtype=np.float64)
    plane_normal = -rot0[:, 2] if plane_normal is None else np.asarray(plane_normal, dtype=np.float64)
    depth = float((plane_point - origin) @ rot0[:, 2])
    if depth <= 0:
        raise InputError("scene target", target.tolist(), "a reference point in front of the camera")
    ref = PinholeCamera(origin, rot0, f, c, c, size, size)
    cams, errors = [ref], [{"tilt_right_deg": 0.0, "tilt_down_deg": 0.0, "roll_deg": 0.0, "focal_scale": 1.0,
                            "offset_m": [0.0, 0.0]}]
    b = geometry.baseline_m
    for n in range(1, N_APERTURES):
        ax, ay = n % 2, n // 2
        tilt_r = float(rng.uniform(-geometry.tilt_max_deg, geometry.tilt_max_deg))
        tilt_d = float(rng.uniform(-geometry.tilt_max_deg, geometry.tilt_max_deg))
        roll = float(rng.uniform(-geometry.roll_max_deg, geometry.roll_max_deg))
        scale = 1.0 + float(rng.uniform(-geometry.focal_scale_max, geometry.focal_scale_max))
        err = (axis_rotation([1, 0, 0], math.radians(tilt_r)) @ axis_rotation([0, 1, 0], math.radians(tilt_d))
               @ axis_rotation([0, 0, 1], math.radians(roll)))
        rot = rot0 @ err
        o = origin + b * ax * rot0[:, 0] + b * ay * rot0[:, 1]
        fn = f * scale
        cxn, cyn = c, c
        if geometry.converge:
            cxn, cyn = c + fn * b * ax / depth, c + fn * b * ay / depth
        cams.append(PinholeCamera(o, rot, fn, cxn, cyn, size, size))
        errors.append({"tilt_right_deg": tilt_r, "tilt_down_deg": tilt_d, "roll_deg": roll, "focal_scale": scale,
                       "offset_m": [b * ax, b * ay]})
    arr = ArrayCameras(cams, errors, geometry, depth, plane_point, plane_normal / np.linalg.norm(plane_normal))
    arr.homographies = np.stack([plane_homography(ref, cam, plane_point, plane_normal) for cam in cams])
    arr.homographies[0] = np.eye(3)
    return arr


def parallax_residual(array: ArrayCameras, points: np.ndarray, valid: np.ndarray) -> dict:
    """How far true projections of scene points stray from the stored homographies.

    ``points`` ``(H, W, 3)`` world hit points of the reference view's pixel centres, ``valid``
    ``(H, W)`` where a surface was hit. Returns statistics in HR pixels per aperture, and
    the depth range seen (metres along the optical axis).
    """
    ref = array.cameras[0]
    hh, ww = valid.shape
    rows, cols = np.meshgrid(np.arange(hh, dtype=np.float64), np.arange(ww, dtype=np.float64), indexing="ij")
    xy_ref = np.stack([cols, rows], axis=-1)[valid]
    pts = points[valid]
    out = {"valid_fraction": float(valid.mean()), "apertures": []}
    if pts.size == 0:
        out.update(depth_min_m=None, depth_max_m=None, max_hr_px=0.0, p95_hr_px=0.0)
        return out
    depth = (pts - ref.origin) @ ref.forward
    out["depth_min_m"], out["depth_max_m"] = float(depth.min()), float(depth.max())
    worst, p95 = 0.0, 0.0
    for n, cam in enumerate(array.cameras):
        true = cam.project(pts)
        h = array.homographies[n]
        hom = np.concatenate([xy_ref, np.ones((len(xy_ref), 1))], axis=1) @ h.T
        pred = hom[:, :2] / hom[:, 2:3]
        d = np.hypot(*(true - pred).T)
        stats = {"max_hr_px": float(d.max()), "p95_hr_px": float(np.percentile(d, 95)),
                 "mean_hr_px": float(d.mean())}
        out["apertures"].append(stats)
        worst, p95 = max(worst, stats["max_hr_px"]), max(p95, stats["p95_hr_px"])
    out["max_hr_px"], out["p95_hr_px"] = worst, p95
    return out
