"""``dolp-ramp``: a backlit polarizing sheet with a linear DoLP ramp and four AoP bands.

Geometry: a D65 light box 5 cm behind a polarizing sheet (``capssim_polarizer``) at depth
``depth_m``. The diattenuation rises linearly from 0 at 10% of the view width to 1 at 90%
(left to right); the transmission axis is 0, 45, 90 and 135 deg in four horizontal bands
from top to bottom, each a quarter of the view high.

Known truth: S0 = ``level``; DoLP = ``clip((col - c0) / (c1 - c0), 0, 1)`` and
AoP = ``45 * band`` with the band limits in HR pixels (``meta.json`` scene.ramp).
Neutral and planar.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError
from capssim.render.scene_base import SceneInfo, d65, evaluate_pattern, pattern, plate_coordinates

from ._targets import FacingCardScene, card_half_size, rectangle, view_half_width

RAMP_SPAN = 0.8  # fraction of the view width over which DoLP goes from 0 to 1


class DolpRamp(FacingCardScene):
    info = SceneInfo(
        name="dolp-ramp",
        description="backlit polarizing sheet: DoLP ramps 0 -> 1 left to right, AoP 0/45/90/135 in four bands",
        purpose="DoLP linearity and AoP accuracy at known angles; low-DoLP AoP noise",
        planar=True, polarizing=True, spectral=False, depth_m=2.0,
        geometry="polarizing sheet at 2 m facing the array, D65 light box 5 cm behind it",
        materials="linear diattenuator sheet: diattenuation ramp in x, axis 0/45/90/135 deg in y bands",
        truth="S0 = level; DoLP = clip((col - c0)/(c1 - c0), 0, 1); AoP = 45 k in band k (rows in meta)",
        defaults={"level": 0.8, "depth_m": 2.0, "fov_deg": 20.0},
    )

    def check_params(self, p):
        if not 0 < p["level"] <= 1:
            raise InputError("scene_params.level", p["level"], "a value in (0, 1]")

    def _layout(self, p):
        hw = view_half_width(p["depth_m"], p["fov_deg"])
        return {"x0": -RAMP_SPAN * hw, "x1": RAMP_SPAN * hw, "top": hw, "band_height": hw / 2.0}

    def mitsuba_dict(self, p):
        a = card_half_size(p["depth_m"], p["fov_deg"])
        lay = self._layout(p)
        sheet = {"type": "capssim_polarizer",
                 "theta": pattern("bands_aop", half_size=a, top=lay["top"], band_height=lay["band_height"]),
                 "dolp": pattern("ramp_dolp", half_size=a, x0=lay["x0"], x1=lay["x1"])}
        return {"type": "scene", "integrator": {"type": "path", "max_depth": 3},
                "sheet": rectangle(a, bsdf=sheet),
                "light_box": rectangle(1.2 * a, z=-0.05, emitter={"type": "area", "radiance": d65(2.0 * p["level"])})}

    def truth(self, p, camera):
        lay = self._layout(p)
        c0 = float(camera.project(np.array([[lay["x0"], 0.0, 0.0]]))[0, 0])
        c1 = float(camera.project(np.array([[lay["x1"], 0.0, 0.0]]))[0, 0])
        edges = [float(camera.project(np.array([[0.0, lay["top"] - k * lay["band_height"], 0.0]]))[0, 1])
                 for k in range(5)]
        return {"ramp": {"s0": p["level"], "dolp_zero_col": c0, "dolp_one_col": c1,
                         "bands": [{"aop_deg": 45 * k, "row_from": edges[k], "row_to": edges[k + 1]}
                                   for k in range(4)],
                         "note": "band k covers rows [row_from, row_to) (the outer bands extend to the edges)"}}

    def analytic_stokes(self, p, camera, xy):
        loc = plate_coordinates(camera, xy)
        lay = self._layout(p)
        aop = np.deg2rad(evaluate_pattern("bands_aop", loc[:, 0], loc[:, 1], top=lay["top"],
                                          band_height=lay["band_height"]))
        d = evaluate_pattern("ramp_dolp", loc[:, 0], loc[:, 1], x0=lay["x0"], x1=lay["x1"])
        s0 = np.full(len(xy), p["level"])
        return np.stack([s0, s0 * d * np.cos(2 * aop), s0 * d * np.sin(2 * aop)])
