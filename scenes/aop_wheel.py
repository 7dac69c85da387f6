"""``aop-wheel``: a backlit polarizing wheel with analytic AoP and DoLP (the AoP colour key, made physical).

Geometry: a D65 light box 5 cm behind a polarizing sheet (``capssim_polarizer``) at depth
``depth_m``. Inside a disc of radius ``radius`` the transmission axis is at ``phi / 2``
(``phi`` the angle from the image's +col axis towards -row, so AoP runs once through
0..180 deg around the wheel) and the diattenuation grows linearly from 0 at the centre to 1
at the rim; outside the disc the sheet transmits unpolarized light (DoLP 0).

Known truth: S0 = ``level`` everywhere; inside the disc AoP = ``phi/2`` (mod 180) and
DoLP = ``r / radius``; outside DoLP = 0. Neutral and planar.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError
from capssim.render.scene_base import SceneInfo, d65, evaluate_pattern, pattern, plate_coordinates

from ._targets import DiscCardScene, card_half_size, rectangle


class AopWheel(DiscCardScene):
    info = SceneInfo(
        name="aop-wheel",
        description="backlit polarizing wheel: AoP = azimuth/2, DoLP = radius (analytic)",
        purpose="AoP / DoLP accuracy over all angles and degrees of polarization",
        planar=True, polarizing=True, spectral=False, depth_m=2.0,
        geometry="polarizing sheet at 2 m facing the array, D65 light box 5 cm behind it",
        materials="linear diattenuator sheet: theta = phi/2, diattenuation = r/R inside the disc",
        truth="S0 = level; AoP = phi/2 (mod 180), DoLP = r/R inside the disc, DoLP 0 outside",
        defaults={"level": 0.8, "radius_fraction": 0.45, "depth_m": 2.0, "fov_deg": 20.0},
    )

    def check_params(self, p):
        if not 0 < p["level"] <= 1:
            raise InputError("scene_params.level", p["level"], "a value in (0, 1]")
        super().check_params(p)

    def mitsuba_dict(self, p):
        a = card_half_size(p["depth_m"], p["fov_deg"])
        r = self.disc_radius_m(p)
        sheet = {"type": "capssim_polarizer", "theta": pattern("wheel_aop", half_size=a, radius=r),
                 "dolp": pattern("wheel_dolp", half_size=a, radius=r)}
        return {"type": "scene", "integrator": {"type": "path", "max_depth": 3},
                "sheet": rectangle(a, bsdf=sheet),
                "light_box": rectangle(1.2 * a, z=-0.05, emitter={"type": "area", "radiance": d65(2.0 * p["level"])})}

    def truth(self, p, camera):
        centre = camera.project(np.zeros((1, 3)))[0]
        return {"wheel": {"center_rowcol": [float(centre[1]), float(centre[0])],
                          "radius_px": self.disc_radius_px(p, camera),
                          "s0": p["level"], "aop_deg": "phi/2 (mod 180) inside, phi from +col towards -row",
                          "dolp": "r / radius_px inside, 0 outside"}}

    def analytic_stokes(self, p, camera, xy):
        loc = plate_coordinates(camera, xy)
        r = self.disc_radius_m(p)
        aop = np.deg2rad(evaluate_pattern("wheel_aop", loc[:, 0], loc[:, 1], radius=r))
        d = evaluate_pattern("wheel_dolp", loc[:, 0], loc[:, 1], radius=r)
        s0 = np.full(len(xy), p["level"])
        return np.stack([s0, s0 * d * np.cos(2 * aop), s0 * d * np.sin(2 * aop)])
