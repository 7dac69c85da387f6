"""``textured``: a natural-image colour slide laminated with a polarizing film, on a light box.

Geometry: a sheet at depth ``depth_m`` covering 1.15x the view, 5 cm in front of a uniform
D65 light box. The sheet is a ``capssim_polarizer`` whose transmittance is a natural image
from ``skimage.data`` (loaded at run time, sRGB decoded to linear, spectrally upsampled by
Mitsuba as a reflectance-like spectrum, so a white texel transmits a flat spectrum and reads
white) and whose transmission axis and diattenuation are fixed smooth sums of sinusoids
(``smooth_aop`` / ``smooth_dolp`` in ``capssim.render.scene_base``). So every one of the 12
channels carries natural-image texture while polarization varies smoothly across it: generic
SR scoring.

Known truth: S0 is the image (no closed form); AoP and DoLP follow the analytic fields
(``meta.json`` scene.fields). Texture sharpness is limited by the image: ``astronaut`` has
512 px across the sheet, about 445 across the view (bilinear texel interpolation).
Polarizing; spectral (colour image); planar.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError
from capssim.render.scene_base import SceneInfo, d65, evaluate_pattern, pattern, plate_coordinates

from ._targets import FacingCardScene, rectangle, view_half_width

IMAGES = ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry", "hubble_deep_field", "retina",
          "brick", "grass", "gravel", "camera", "moon",  # the last five are grey (shown neutral)
          "motorcycle")  # the left view of skimage.data.stereo_motorcycle: kept for the frozen test suite only
CARD = 1.15  # card half-size / view half-width


def load_image(name: str) -> np.ndarray:
    """``(H, W, 3)`` linear RGB in [0, 1] of a ``skimage.data`` image, cropped square."""
    import skimage.data

    if name not in IMAGES:
        raise InputError("scene_params.image", name, f"one of {', '.join(IMAGES)}")
    img = np.asarray(skimage.data.stereo_motorcycle()[0] if name == "motorcycle" else getattr(skimage.data, name)())
    img = (np.repeat(img[..., None], 3, axis=-1) if img.ndim == 2 else img[..., :3]).astype(np.float64) / 255.0
    h, w = img.shape[:2]
    s = min(h, w)
    img = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    return np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4)


class Textured(FacingCardScene):
    info = SceneInfo(
        name="textured",
        description="natural-image colour slide (skimage.data) with a polarizing film of smooth AoP/DoLP fields",
        purpose="generic SR scoring on natural texture in all 12 channels",
        planar=True, polarizing=True, spectral=True, depth_m=2.0,
        geometry="colour slide + polarizing film at 2 m facing the array, D65 light box 5 cm behind",
        materials="linear diattenuator sheet with image transmittance (sRGB -> linear, spectral upsampling)",
        truth="AoP/DoLP: analytic smooth fields (scene.fields); S0: the image",
        defaults={"image": "astronaut", "level": 0.9, "field_cycles": 1.5, "dolp_min": 0.1, "dolp_max": 0.7,
                  "depth_m": 2.0, "fov_deg": 20.0},
    )

    def check_params(self, p):
        if p["image"] not in IMAGES:
            raise InputError("scene_params.image", p["image"], f"one of {', '.join(IMAGES)}")
        if not (0 < p["level"] <= 1 and 0 <= p["dolp_min"] <= p["dolp_max"] <= 1 and 0 < p["field_cycles"] <= 20):
            raise InputError("scene_params", p, "0 < level <= 1, 0 <= dolp_min <= dolp_max <= 1, 0 < field_cycles <= 20")

    def _field_params(self, p):
        hw = view_half_width(p["depth_m"], p["fov_deg"])
        return {"frequency": 2 * np.pi * p["field_cycles"] / (2 * hw), "dolp_min": p["dolp_min"],
                "dolp_max": p["dolp_max"]}

    def mitsuba_dict(self, p):
        import mitsuba as mi

        a = CARD * view_half_width(p["depth_m"], p["fov_deg"])
        # bitmaps map their first row to the bottom of a camera-facing rectangle: flip
        img = np.ascontiguousarray(np.flipud(load_image(p["image"])), dtype=np.float32)
        f = self._field_params(p)
        sheet = {"type": "capssim_polarizer", "theta": pattern("smooth_aop", half_size=a, **f),
                 "dolp": pattern("smooth_dolp", half_size=a, **f),
                 "transmittance": {"type": "bitmap", "bitmap": mi.Bitmap(img), "filter_type": "bilinear",
                                   "wrap_mode": "clamp"}}
        return {"type": "scene", "integrator": {"type": "path", "max_depth": 3},
                "sheet": rectangle(a, bsdf=sheet),
                "light_box": rectangle(1.5 * a, z=-0.05, emitter={"type": "area", "radiance": d65(2.0 * p["level"])})}

    def truth(self, p, camera):
        f = self._field_params(p)
        return {"fields": {"aop_deg": "scene_base.smooth_aop(x, y) on the film, x/y in metres",
                           "dolp": "scene_base.smooth_dolp(x, y)", "params": {k: float(v) for k, v in f.items()},
                           "image": p["image"]}}

    def analytic_polarization(self, p, camera, xy):
        """``(aop_deg, dolp)`` of the film at pixel points ``xy`` ``(N, 2)``."""
        loc = plate_coordinates(camera, xy)
        f = self._field_params(p)
        return (evaluate_pattern("smooth_aop", loc[:, 0], loc[:, 1], **f) % 180.0,
                evaluate_pattern("smooth_dolp", loc[:, 0], loc[:, 1], **f))
