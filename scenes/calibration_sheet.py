"""``calibration-sheet``: a uniform light box behind a uniform polarizing sheet, for rig calibration.

Geometry: a D65 light box 5 cm behind a sheet (``capssim_polarizer``) at depth ``depth_m``
that fills the view. ``dolp = 0``: uniform unpolarized light, the flat field;
``dolp = 1``: an ideal linear polarizer at ``polarizer_deg`` (image angle, from +col towards
-row), one step of a polarization-state-generator sweep.

Known truth: every one of the 12 channels reads ``level * (1 + dolp cos 2(a - polarizer_deg))``
(so ``S0 = 2 level``), the format of a calibration capture (docs: guides/calibration.md).
Neutral and planar.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError
from capssim.render.scene_base import SceneInfo, d65

from ._targets import FacingCardScene, card_half_size, rectangle


class CalibrationSheet(FacingCardScene):
    info = SceneInfo(
        name="calibration-sheet",
        description="uniform light box behind a uniform polarizing sheet (flat field, polarizer sweep)",
        purpose="rig calibration: gain and vignetting (dolp 0), polarizer angles and extinction (dolp 1)",
        planar=True, polarizing=True, spectral=False, depth_m=2.0,
        geometry="sheet at 2 m filling the view, D65 light box 5 cm behind it",
        materials="linear diattenuator sheet: theta = polarizer_deg, diattenuation = dolp",
        truth="each channel = level (1 + dolp cos 2(a - polarizer_deg))",
        defaults={"level": 0.4, "polarizer_deg": 0.0, "dolp": 0.0, "depth_m": 2.0, "fov_deg": 20.0},
    )

    def check_params(self, p):
        if not 0 < p["level"] <= 0.5:
            raise InputError("scene_params.level", p["level"], "a value in (0, 0.5] (each channel's level; S0 = 2 level)")
        if not 0 <= p["dolp"] <= 1:
            raise InputError("scene_params.dolp", p["dolp"], "a value in [0, 1]")
        if not np.isfinite(p["polarizer_deg"]):
            raise InputError("scene_params.polarizer_deg", p["polarizer_deg"], "a finite angle in degrees")
        super().check_params(p)

    def mitsuba_dict(self, p):
        a = 1.6 * card_half_size(p["depth_m"], p["fov_deg"])
        sheet = {"type": "capssim_polarizer", "theta": float(p["polarizer_deg"]), "dolp": float(p["dolp"])}
        # the sheet transmits S0 = radiance / 2 of the unpolarized light box
        return {"type": "scene", "integrator": {"type": "path", "max_depth": 3},
                "sheet": rectangle(a, bsdf=sheet),
                "light_box": rectangle(1.2 * a, z=-0.05, emitter={"type": "area", "radiance": d65(4.0 * p["level"])})}

    def truth(self, p, camera):
        return {"calibration_sheet": {"level": p["level"], "polarizer_deg": p["polarizer_deg"], "dolp": p["dolp"]}}

    def analytic_stokes(self, p, camera, xy):
        s0 = np.full(len(xy), 2.0 * p["level"])
        t = np.deg2rad(2.0 * p["polarizer_deg"])
        return np.stack([s0, s0 * p["dolp"] * np.cos(t), s0 * p["dolp"] * np.sin(t)])
