"""``colorchecker``: a spectral ColorChecker chart (24 measured reflectance spectra) in daylight.

Geometry: 6 x 4 Lambertian patches (ColorChecker N Ohta reflectances from colour-science,
380-780 nm) on a black card (reflectance 0.04) at depth ``depth_m``, facing the array, lit
by a uniform D65 sky of radiance ``illuminance`` (a constant environment). Each patch is a
flat plane seeing the sky over its whole hemisphere, so its radiance is exactly
``reflectance x illuminance``; the ``direct`` integrator with BSDF sampling only makes that
noise-free except for the spectral sampling. The card sits 0.2 mm behind the patches (the
parallax this causes is far below the planar tolerance).

Known truth: per patch, its pixel box and its camera RGB behind each analyzer,
``illuminance/2 * int R(l) D65(l) s_c(l) / int D65(l) s_c(l)`` (the camera's D65 white
balance, ``meta.json`` scene.patches). Unpolarized; spectral; planar.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError
from capssim.render.scene_base import SceneInfo, d65
from capssim.render.spectral import CameraResponse, cached_arrays

from ._targets import FacingCardScene, card_half_size, rectangle, view_half_width

CHART = "ColorChecker N Ohta"
COLUMNS, ROWS = 6, 4
GAP = 0.2  # gap between patches relative to the patch size
CARD_REFLECTANCE = 0.04


def colorchecker_spectra() -> tuple[list[str], np.ndarray, np.ndarray]:
    """Patch names, wavelengths (nm) and reflectances ``(24, K)`` (cached after first use)."""
    def build():
        import colour

        sds = colour.SDS_COLOURCHECKERS[CHART]
        names = list(sds)
        lam = np.asarray(sds[names[0]].wavelengths, dtype=np.float64)
        values = np.stack([np.asarray(sds[n].values, dtype=np.float64) for n in names])
        return {"names": np.asarray(names), "wavelengths": lam, "reflectance": values}

    data = cached_arrays("colorchecker_" + CHART, build)
    return [str(n) for n in data["names"]], data["wavelengths"], data["reflectance"]


class ColorChecker(FacingCardScene):
    info = SceneInfo(
        name="colorchecker",
        description="ColorChecker with 24 measured reflectance spectra under a uniform D65 sky",
        purpose="colour fidelity of the camera-RGB channels (spectral rendering, real camera sensitivities)",
        planar=True, polarizing=False, spectral=True, depth_m=2.0,
        geometry="6 x 4 patch chart on a black card at 2 m facing the array",
        materials="Lambertian patches with ColorChecker N Ohta spectra; black card (0.04)",
        truth="per patch: pixel box and camera RGB = illuminance/2 * <R D65 s_c> / <D65 s_c> (meta scene.patches)",
        defaults={"illuminance": 1.8, "depth_m": 2.0, "fov_deg": 20.0},
    )

    def check_params(self, p):
        if not 0 < p["illuminance"] <= 2.2:
            raise InputError("scene_params.illuminance", p["illuminance"], "a value in (0, 2.2] (white patch < 1)")

    def _patches(self, p):
        hw = view_half_width(p["depth_m"], p["fov_deg"])
        size = 1.6 * hw / (COLUMNS + (COLUMNS + 1) * GAP)
        step = size * (1 + GAP)
        out = []
        for r in range(ROWS):
            for c in range(COLUMNS):
                x = (c - (COLUMNS - 1) / 2) * step
                y = ((ROWS - 1) / 2 - r) * step
                out.append((x, y, size / 2))
        return out

    def mitsuba_dict(self, p):
        import mitsuba as mi

        names, lam, refl = colorchecker_spectra()
        a = card_half_size(p["depth_m"], p["fov_deg"])
        scene = {"type": "scene", "integrator": {"type": "direct", "emitter_samples": 0, "bsdf_samples": 1},
                 "sky": {"type": "constant", "radiance": d65(p["illuminance"])},
                 "card": rectangle(a, z=-2e-4, bsdf={"type": "diffuse", "reflectance": CARD_REFLECTANCE})}
        for i, (x, y, h) in enumerate(self._patches(p)):
            spectrum = {"type": "regular", "wavelength_min": float(lam[0]), "wavelength_max": float(lam[-1]),
                        "values": ", ".join(f"{v:.6f}" for v in refl[i])}
            scene[f"patch_{i:02d}"] = {"type": "rectangle",
                                       "to_world": mi.ScalarTransform4f().translate([x, y, 0.0]).scale([h, h, 1.0]),
                                       "bsdf": {"type": "diffuse", "reflectance": spectrum}}
        return scene

    def truth(self, p, camera):
        names, lam, refl = colorchecker_spectra()
        response = CameraResponse()
        patches = []
        for i, (x, y, h) in enumerate(self._patches(p)):
            tl = camera.project(np.array([[x - h, y + h, 0.0]]))[0]
            br = camera.project(np.array([[x + h, y - h, 0.0]]))[0]
            rgb = response.expected_rgb(lam, refl[i]) * p["illuminance"] / 2.0
            patches.append({"name": names[i], "row_from": float(tl[1]), "row_to": float(br[1]),
                            "col_from": float(tl[0]), "col_to": float(br[0]),
                            "rgb_per_analyzer": [float(v) for v in rgb]})
        return {"patches": patches, "chart": CHART,
                "note": "rgb_per_analyzer is each analyzer channel's camera RGB (D65 white balance), "
                        "the same for 0/45/90/135 deg (unpolarized)"}
