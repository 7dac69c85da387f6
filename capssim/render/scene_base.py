"""What a scene in ``scenes/`` provides, and the analytic Mitsuba plugins the scenes share.

A scene is one module of :mod:`capssim.scenes` with one :class:`Scene` subclass registered by
:func:`capssim.render.scene_registry.register`. It says, in one place:

* :class:`SceneInfo`: name, description, purpose, geometry, materials, depth, known
  truth, and what it needs from the renderer (``planar``, ``polarizing``, ``spectral``);
* :meth:`Scene.camera_pose`: where the array looks from (the reference aperture);
* :meth:`Scene.mitsuba_dict`: the Mitsuba scene (no sensor: capssim traces its own rays);
* :meth:`Scene.truth`: the known truth in HR pixel terms, stored in ``meta.json``;
* optionally :meth:`Scene.analytic_stokes`: the exact ``S0, S1, S2`` at image points.

Plugins (registered per Mitsuba variant by :func:`capssim.render.mitsuba_plugins.register_plugins`):

* ``capssim_pattern`` texture: an analytic function of the surface position, evaluated
  exactly at every ray hit (no texels, no interpolation MTF), optionally multiplied by a
  nested ``base`` spectrum (e.g. ``d65`` for an emitter). Patterns are in
  :data:`PATTERNS`; coordinates are the rectangle's local ``(x, y)`` in metres
  (``x`` right, ``y`` up when the rectangle faces the camera), ``phi`` the angle from
  ``+x`` towards ``+y`` - which is the image's AoP convention for a camera-facing plate.
* ``capssim_polarizer`` BSDF: an ideal linear diattenuator sheet (transmission only,
  no refraction): transmission axis at ``theta`` degrees from the local ``x`` axis
  towards ``y``, diattenuation ``dolp`` (intensity transmittances ``(1 +- dolp)/2``).
  Unpolarized light leaves it with ``S0 = t L/2``, ``DoLP = dolp`` and, seen from its front,
  ``AoP = theta`` - deterministic, unlike a stochastic ``blendbsdf`` of two polarizers.
  An optional ``transmittance`` texture ``t`` (e.g. a colour slide) scales both axes.
  Note: keep at least a few mm between such sheets and surfaces behind them; Mitsuba's
  ray-spawn offset (about ``1e-4 (1 + |p|)`` m) skips anything closer.
  (Mitsuba's own ``polarizer`` measures ``theta`` the other way: facing the camera it
  analyzes at ``-theta``; a render test pins both.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from capssim.errors import InputError

_TRUE_WORDS, _FALSE_WORDS = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def _coerce_param(argument: str, value, default):
    """``value`` as the type of the scene's ``default`` (bool, int, finite float), or an :class:`InputError`."""
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        word = str(value).strip().lower()
        if word in _TRUE_WORDS + _FALSE_WORDS and not isinstance(value, (dict, list)):
            return word in _TRUE_WORDS
        raise InputError(argument, repr(value), "a boolean (true/false, yes/no, on/off, 1/0)")
    if isinstance(default, (int, float)):
        kind = "an integer" if isinstance(default, int) else "a finite number"
        bad = InputError(argument, repr(value), kind, f"For example {argument.split('.')[-1]}={default}.")
        if isinstance(value, (bool, dict, list)) or value is None:
            raise bad
        if isinstance(default, int) and isinstance(value, (int, str)) and str(value).strip().lstrip("+-").isdigit():
            return int(value)  # exact, also past float precision
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise bad from None
        if not math.isfinite(number) or (isinstance(default, int) and number != int(number)):
            raise bad
        return int(number) if isinstance(default, int) else number
    return value



#: the ranges of the parameters several scenes share (``--param depth_m=0`` names ``depth_m``, not the camera)
SHARED_PARAM_RANGES = {"depth_m": (0.1, 1000.0, "metres from the array to the target, in front of it"),
                       "fov_deg": (0.5, 120.0, "horizontal field of view in degrees")}


@dataclass(frozen=True)
class SceneInfo:
    """Description of a scene (``capssim scenes`` lists these)."""

    name: str
    description: str
    purpose: str
    planar: bool
    polarizing: bool
    spectral: bool
    depth_m: float
    geometry: str
    materials: str
    truth: str = ""
    defaults: dict = field(default_factory=dict)

    def needs(self) -> str:
        parts = ["polarized" if self.polarizing else "unpolarized", "spectral" if self.spectral else "neutral (mono)",
                 "planar (render once + warp)" if self.planar else "3-D (one render per aperture)"]
        return ", ".join(parts)


@dataclass(frozen=True)
class CameraPose:
    """Reference aperture pose (metres), horizontal field of view, optional reference plane."""

    origin: tuple
    target: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov_deg: float = 20.0
    plane_point: tuple | None = None
    plane_normal: tuple | None = None


class Scene:
    """Base class of a library scene. Subclasses set :attr:`info` and implement the methods."""

    info: SceneInfo

    def params(self, overrides: dict | None) -> dict:
        """Defaults updated with ``overrides``; unknown keys and values of the wrong type are an error."""
        params = dict(self.info.defaults)
        for key, value in (overrides or {}).items():
            if key not in params:
                raise InputError("scene_params", key,
                                 f"a parameter of scene {self.info.name!r}: {sorted(params) or 'none'}")
            params[key] = _coerce_param(f"scene_params.{key}", value, params[key])
        for key, (low, high, what) in SHARED_PARAM_RANGES.items():  # before the scene's own checks and the camera's
            if key in params and not low <= params[key] <= high:
                raise InputError(f"scene_params.{key}", params[key], f"a number in [{low:g}, {high:g}] ({what})",
                                 f"For example {key}={self.info.defaults[key]}.")
        self.check_params(params)
        return params

    def check_params(self, params: dict) -> None:
        """Raise :class:`InputError` for invalid parameter values (override in scenes)."""

    def camera_pose(self, params: dict) -> CameraPose:
        raise NotImplementedError

    def mitsuba_dict(self, params: dict) -> dict:
        """The Mitsuba scene dict (without sensor) for the active variant."""
        raise NotImplementedError

    def truth(self, params: dict, camera) -> dict:
        """Known truth for ``meta.json["scene"]`` in HR pixel terms (``camera`` = reference)."""
        return {}

    def analytic_stokes(self, params: dict, camera, xy: np.ndarray) -> np.ndarray | None:
        """``(3, N)`` exact ``S0, S1, S2`` (camera RGB, equal for R, G, B) at pixel points
        ``xy`` ``(N, 2)`` of the reference view, or ``None`` if the scene has no closed form."""
        return None


# -- helpers for scenes ----------------------------------------------------------------------
def plate_coordinates(camera, xy: np.ndarray, *, center=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0),
                      x_axis=(1.0, 0.0, 0.0)) -> np.ndarray:
    """Local ``(x, y)`` metres on a plate where the rays of pixels ``xy`` hit it."""
    c, n, xa = (np.asarray(v, dtype=np.float64) for v in (center, normal, x_axis))
    ya = np.cross(n, xa)
    d = camera.directions(xy)
    t = ((c - camera.origin) @ n) / (d @ n)
    p = camera.origin + t[:, None] * d - c
    return np.stack([p @ xa, p @ ya], axis=-1)


def d65(scale: float = 1.0) -> dict:
    """A D65 spectrum of the given scale (camera white balance: a white reads ``scale``)."""
    return {"type": "d65", "scale": float(scale)}


def pattern(name: str, *, base: dict | None = None, half_size: float = 1.0, **params) -> dict:
    """A ``capssim_pattern`` texture dict (see :data:`PATTERNS`)."""
    d = {"type": "capssim_pattern", "pattern": name, "half_size": float(half_size)}
    for k, v in params.items():
        d[k] = float(v)
    if base is not None:
        d["base"] = base
    return d


# -- analytic patterns (drjit functions of local x, y in metres) ----------------------------------
def _polar(dr, x, y):
    return dr.sqrt(x * x + y * y), dr.atan2(y, x)


def _siemens(dr, mi, x, y, p):
    r, phi = _polar(dr, x, y)
    inside = r <= p.get("radius", 1.0)
    star = p.get("mean", 0.5) * (1.0 + p.get("contrast", 0.8) * dr.cos(p.get("cycles", 72.0) * phi))
    return dr.select(inside, star, p.get("mean", 0.5))


def _star_aop(dr, mi, x, y, p):
    r, phi = _polar(dr, x, y)
    return dr.select(r <= p.get("radius", 1.0), 0.5 * p.get("cycles", 72.0) * dr.rad2deg(phi), p.get("outside", 0.0))


def _wheel_aop(dr, mi, x, y, p):
    r, phi = _polar(dr, x, y)
    return dr.select(r <= p.get("radius", 1.0), 0.5 * dr.rad2deg(phi), p.get("outside", 0.0))


def _wheel_dolp(dr, mi, x, y, p):
    r, _ = _polar(dr, x, y)
    radius = p.get("radius", 1.0)
    return dr.select(r <= radius, dr.clip(r / radius, 0.0, 1.0), 0.0)


def _ramp_dolp(dr, mi, x, y, p):
    x0, x1 = p.get("x0", -1.0), p.get("x1", 1.0)
    return dr.clip((x - x0) / (x1 - x0), 0.0, 1.0)


def _bands_aop(dr, mi, x, y, p):
    # band k (0 at the top) of height h has AoP 45 k; bands repeat every 4
    top, h = p.get("top", 1.0), p.get("band_height", 0.5)
    k = dr.clip(dr.floor((top - y) / h), 0.0, 3.0)
    return 45.0 * k


def _smooth_field(dr, x, y, p, key):
    # a fixed sum of sinusoids: deterministic, smooth, analytic
    f = p.get("frequency", 1.0)
    s = (dr.sin(f * (1.3 * x + 0.4 * y) + 0.3) + 0.7 * dr.sin(f * (-0.6 * x + 1.7 * y) + 1.9)
         + 0.5 * dr.sin(f * (2.3 * x - 1.1 * y) + 4.1))
    return s / 2.2  # in about [-1, 1]


def _smooth_aop(dr, mi, x, y, p):
    return 90.0 + 90.0 * _smooth_field(dr, x, y, p, "aop")


def _smooth_dolp(dr, mi, x, y, p):
    lo, hi = p.get("dolp_min", 0.1), p.get("dolp_max", 0.8)
    v = _smooth_field(dr, y + 0.37, -x + 0.11, p, "dolp")
    return lo + (hi - lo) * dr.clip(0.5 * (v + 1.0), 0.0, 1.0)


PATTERNS: dict[str, Callable] = {
    "siemens": _siemens,
    "star_aop": _star_aop,
    "wheel_aop": _wheel_aop,
    "wheel_dolp": _wheel_dolp,
    "ramp_dolp": _ramp_dolp,
    "bands_aop": _bands_aop,
    "smooth_aop": _smooth_aop,
    "smooth_dolp": _smooth_dolp,
}


def evaluate_pattern(name: str, x: np.ndarray, y: np.ndarray, **params) -> np.ndarray:
    """Evaluate a pattern with numpy (for analytic truth); same formulas as the texture."""
    return np.asarray(PATTERNS[name](_NumpyDr, None, np.asarray(x, float), np.asarray(y, float), params))


class _NumpyDr:
    """The few drjit functions the patterns use, in numpy."""

    sqrt = staticmethod(np.sqrt)
    atan2 = staticmethod(np.arctan2)
    cos = staticmethod(np.cos)
    sin = staticmethod(np.sin)
    floor = staticmethod(np.floor)
    rad2deg = staticmethod(np.rad2deg)

    @staticmethod
    def select(m, a, b):
        return np.where(m, a, b)

    @staticmethod
    def clip(v, lo, hi):
        return np.clip(v, lo, hi)


def scale_scene(scene: dict, factor: float) -> dict:
    """Scale every shape and light position of a Mitsuba scene dict by ``factor`` (about the origin).

    Geometry is scale-invariant for ray optics (radiance, BSDFs and polarization do not
    change), so a scene can be moved further from the array to reduce parallax. Point-light
    intensities are multiplied by ``factor^2`` so irradiance is unchanged.
    """
    import mitsuba as mi

    s = float(factor)
    out = {}
    for key, value in scene.items():
        if not isinstance(value, dict):
            out[key] = value
            continue
        v = dict(value)
        kind = v.get("type")
        if kind == "sphere" and "center" in v:
            c, r = v.pop("center"), v.pop("radius", 1.0)
            v["to_world"] = mi.ScalarTransform4f().scale(s).translate(list(c)).scale(r)
        elif kind == "cylinder" and "p0" in v:
            v["p0"] = [s * x for x in v["p0"]]
            v["p1"] = [s * x for x in v["p1"]]
            v["radius"] = s * v.get("radius", 1.0)
        elif kind == "point":
            v["position"] = [s * x for x in v["position"]]
            if isinstance(v.get("intensity"), dict) and "scale" in v["intensity"]:
                v["intensity"] = dict(v["intensity"], scale=v["intensity"]["scale"] * s * s)
        elif "to_world" in v and kind not in ("envmap", "constant"):
            v["to_world"] = mi.ScalarTransform4f().scale(s) @ v["to_world"]
        out[key] = v
    return out


def scale_pose(pose: CameraPose, factor: float) -> CameraPose:
    s = float(factor)
    sc = lambda v: None if v is None else tuple(s * x for x in v)  # noqa: E731
    return CameraPose(origin=sc(pose.origin), target=sc(pose.target), up=pose.up, fov_deg=pose.fov_deg,
                      plane_point=sc(pose.plane_point), plane_normal=pose.plane_normal)
