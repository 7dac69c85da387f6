"""``siemens-star``: a sinusoidal Siemens star on a light box, for MTF and SR magnification.

Geometry: a square transmissive chart at depth ``depth_m`` (default 2 m) filling the view,
lit from behind by a uniform D65 light box (so the chart itself is the emitter and the
only Monte-Carlo noise is pixel-area sampling). Inside ``radius`` the chart radiance is
``mean * (1 + contrast * cos(cycles * phi))`` with ``phi`` the angle from the image's +col
axis towards -row; outside it is ``mean``. The texture is evaluated analytically at each
ray hit (``capssim_pattern``), so there is no texel blur: the ground truth's only blur is
the box pixel and the optical PSF.

Known truth (``meta.json["scene"]["star"]``): centre (row, col), cycles, radius in HR
pixels, mean and contrast; the paper's fig. 14-15 MTF / SR magnification protocol.
Unpolarized, neutral: Mitsuba's ``*_mono`` variant is exact.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError
from capssim.render.scene_base import SceneInfo, d65, evaluate_pattern, pattern, plate_coordinates

from ._targets import DiscCardScene, card_half_size, rectangle


class SiemensStar(DiscCardScene):
    info = SceneInfo(
        name="siemens-star",
        description="sinusoidal Siemens star (analytic, no texel blur) on a D65 light box",
        purpose="MTF and SR magnification (paper fig. 14-15)",
        planar=True, polarizing=False, spectral=False, depth_m=2.0,
        geometry="flat chart facing the array at 2 m, filling the 20 deg view",
        materials="emissive chart: radiance = mean (1 + contrast cos(N phi)) x D65",
        truth="star centre, cycles N, radius (HR px), mean, contrast: meta.json scene.star",
        defaults={"cycles": 72, "contrast": 0.8, "mean": 0.5, "radius_fraction": 0.45, "depth_m": 2.0,
                  "fov_deg": 20.0},
    )

    def check_params(self, p):
        if not 4 <= p["cycles"] <= 1000:
            raise InputError("scene_params.cycles", p["cycles"], "an integer in [4, 1000]")
        if not (0 <= p["contrast"] <= 1 and 0 < p["mean"] and p["mean"] * (1 + p["contrast"]) <= 1.0):
            raise InputError("scene_params.contrast/mean", (p["contrast"], p["mean"]),
                             "0 <= contrast <= 1, mean > 0 and mean * (1 + contrast) <= 1 (full scale)")
        super().check_params(p)

    def mitsuba_dict(self, p):
        a = card_half_size(p["depth_m"], p["fov_deg"])
        radiance = pattern("siemens", base=d65(2.0), half_size=a, cycles=p["cycles"], contrast=p["contrast"],
                           mean=p["mean"], radius=self.disc_radius_m(p))
        return {"type": "scene", "integrator": {"type": "path", "max_depth": 1},
                "chart": rectangle(a, emitter={"type": "area", "radiance": radiance})}

    def truth(self, p, camera):
        centre = camera.project(np.zeros((1, 3)))[0]
        radius_px = self.disc_radius_px(p, camera)
        return {"star": {"center_rowcol": [float(centre[1]), float(centre[0])], "cycles": int(p["cycles"]),
                         "radius_px": float(radius_px), "mean": p["mean"], "contrast": p["contrast"],
                         "formula": "I = mean * (1 + contrast * cos(cycles * phi)), phi from +col towards -row",
                         "applies_to": "all 12 channels (unpolarized, neutral)"}}

    def analytic_stokes(self, p, camera, xy):
        loc = plate_coordinates(camera, xy)
        s0 = evaluate_pattern("siemens", loc[:, 0], loc[:, 1], cycles=p["cycles"], contrast=p["contrast"],
                              mean=p["mean"], radius=self.disc_radius_m(p))
        return np.stack([s0, np.zeros_like(s0), np.zeros_like(s0)])
