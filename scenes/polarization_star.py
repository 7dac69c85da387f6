"""``polarization-star``: a backlit polarizer whose transmission axis follows a Siemens star.

Geometry: a D65 light box 5 cm behind a polarizing sheet (``capssim_polarizer``, an ideal
linear diattenuator) at depth ``depth_m`` filling the view. Inside ``radius`` the sheet's
transmission axis is at ``theta = (cycles / 2) * phi`` (``phi`` from the image's +col axis
towards -row), outside it is at 0 deg. So ``S0`` is flat (``level``) while the analyzer
image at angle ``a`` is ``S0/2 (1 + dolp cos(cycles phi - 2a))``: a full sine star with
``cycles`` cycles in every polarization channel, phase-shifted by ``2a``. Resolution can be
measured per polarization channel, and intensity-only methods see nothing.

Known truth: AoP = ``cycles/2 * phi`` (mod 180) and DoLP = ``dolp`` inside the star,
AoP 0 outside; S0 = ``level``; star geometry as for ``siemens-star``.
Neutral and planar: ``*_mono_polarized``, rendered once and warped.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError
from capssim.render.scene_base import SceneInfo, d65, evaluate_pattern, pattern, plate_coordinates

from ._targets import DiscCardScene, card_half_size, rectangle


class PolarizationStar(DiscCardScene):
    info = SceneInfo(
        name="polarization-star",
        description="backlit polarizer whose axis follows a Siemens star: flat S0, a sine star in every analyzer",
        purpose="resolution per polarization channel (MTF of each analyzer image, AoP fidelity)",
        planar=True, polarizing=True, spectral=False, depth_m=2.0,
        geometry="polarizing sheet at 2 m facing the array, D65 light box 5 cm behind it",
        materials="ideal linear diattenuator sheet (capssim_polarizer), theta = cycles/2 * phi",
        truth="S0 = level; AoP = cycles/2 * phi (mod 180), DoLP = dolp inside the star; star centre/cycles/radius",
        defaults={"cycles": 72, "level": 0.9, "dolp": 1.0, "radius_fraction": 0.45, "depth_m": 2.0, "fov_deg": 20.0},
    )

    def check_params(self, p):
        if not 4 <= p["cycles"] <= 1000:
            raise InputError("scene_params.cycles", p["cycles"], "an integer in [4, 1000]")
        if not (0 < p["level"] <= 1 and 0 <= p["dolp"] <= 1):
            raise InputError("scene_params.level/dolp", (p["level"], p["dolp"]), "0 < level <= 1, 0 <= dolp <= 1")
        super().check_params(p)

    def mitsuba_dict(self, p):
        a = card_half_size(p["depth_m"], p["fov_deg"])
        sheet = {"type": "capssim_polarizer", "dolp": float(p["dolp"]),
                 "theta": pattern("star_aop", half_size=a, cycles=p["cycles"], radius=self.disc_radius_m(p))}
        return {"type": "scene", "integrator": {"type": "path", "max_depth": 3},
                "sheet": rectangle(a, bsdf=sheet),
                "light_box": rectangle(1.2 * a, z=-0.05, emitter={"type": "area", "radiance": d65(2.0 * p["level"])})}

    def truth(self, p, camera):
        centre = camera.project(np.zeros((1, 3)))[0]
        return {"star": {"center_rowcol": [float(centre[1]), float(centre[0])], "cycles": int(p["cycles"]),
                         "radius_px": self.disc_radius_px(p, camera),
                         "mean": p["level"] / 2, "contrast": p["dolp"],
                         "formula": "I(a) = level/2 * (1 + dolp * cos(cycles * phi - 2 a)), "
                                    "phi from +col towards -row",
                         "applies_to": "each analyzer channel; S0 is flat"},
                "polarization": {"s0": p["level"], "dolp_inside": p["dolp"],
                                 "aop_deg": "cycles/2 * phi (mod 180) inside the star, 0 outside"}}

    def analytic_stokes(self, p, camera, xy):
        loc = plate_coordinates(camera, xy)
        aop = np.deg2rad(evaluate_pattern("star_aop", loc[:, 0], loc[:, 1], cycles=p["cycles"],
                                          radius=self.disc_radius_m(p)))
        s0 = np.full(len(xy), p["level"])
        return np.stack([s0, s0 * p["dolp"] * np.cos(2 * aop), s0 * p["dolp"] * np.sin(2 * aop)])
