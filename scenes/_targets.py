"""Shared layout of the flat test targets: a card facing the array at depth Z, filling the view."""

from __future__ import annotations

import math

from capssim.errors import InputError
from capssim.render.scene_base import CameraPose, Scene

#: half-width of the card relative to the half-width of the reference view at depth Z (covers
#: the other apertures' views, their tilts and the render margins)
CARD_OVERSIZE = 1.6


def target_pose(depth_m: float, fov_deg: float) -> CameraPose:
    return CameraPose(origin=(0.0, 0.0, float(depth_m)), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                      fov_deg=float(fov_deg))


def view_half_width(depth_m: float, fov_deg: float) -> float:
    """Half-width in metres of the reference view at depth Z."""
    return float(depth_m) * math.tan(math.radians(fov_deg) / 2.0)


def card_half_size(depth_m: float, fov_deg: float) -> float:
    return CARD_OVERSIZE * view_half_width(depth_m, fov_deg)


def rectangle(half_size: float, *, z: float = 0.0, **extra) -> dict:
    """A camera-facing (normal +z) square of half-size ``half_size`` at height ``z``."""
    import mitsuba as mi

    d = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0.0, 0.0, z]).scale(
        [half_size, half_size, 1.0])}
    d.update(extra)
    return d


class FacingCardScene(Scene):
    """A flat target card facing the array at ``params["depth_m"]``, viewed with ``params["fov_deg"]``."""

    def camera_pose(self, p):
        return target_pose(p["depth_m"], p["fov_deg"])


class DiscCardScene(FacingCardScene):
    """A facing card with a centred disc pattern whose radius is ``params["radius_fraction"]`` of the view width."""

    def check_params(self, p):
        if not 0.05 <= p["radius_fraction"] <= 0.5:
            raise InputError("scene_params.radius_fraction", p["radius_fraction"], "a value in [0.05, 0.5]")

    def disc_radius_m(self, p) -> float:
        """Disc radius on the card (m)."""
        return 2.0 * p["radius_fraction"] * view_half_width(p["depth_m"], p["fov_deg"])

    def disc_radius_px(self, p, camera) -> float:
        """Disc radius in reference HR pixels."""
        return float(self.disc_radius_m(p) * camera.focal_px / p["depth_m"])
