"""``water-glare``: a lake seen at Brewster's angle, glaring with the reflected cloudy sky (paper fig. 13).

Geometry (metres, +y up): the array stands 12 m above a flat water surface (``dielectric``,
n = 1.333) and looks down at a point 16 m ahead, so the view centre meets the water at
53.1 deg incidence, Brewster's angle for water. The lake bed lies 1.5 m below the surface
(procedural sand texture); three wooden posts stand out of the water. The sky is a
procedural equirectangular map (blue gradient and fractal clouds, ``_procedural.sky_envmap``).
The reflected sky is at infinity while the homography is the water plane's: the glare
shows about ``f B / 20 m`` pixels of parallax (recorded in ``meta.json`` render.depth).

Physics: near Brewster's angle the specular reflection is almost purely s-polarized:
electric field horizontal, AoP 0 deg, reflected DoLP -> 1 (single interface Fresnel).
An analyzer at 90 deg removes the glare, one at 0 deg keeps it. Light refracted up from
the lake bed adds weakly p-polarized light. The sky itself is unpolarized here (Mitsuba
emitters are), a simplification of real skylight. Spectral; polarizing; 3-D.
"""

from __future__ import annotations

import math

from capssim.render.scene_base import CameraPose, Scene, SceneInfo

from ._procedural import sand_texture, sky_envmap
from .window_reflection import fresnel_dolp

N_WATER = 1.333
HEIGHT, AHEAD = 12.0, 16.0


class WaterGlare(Scene):
    info = SceneInfo(
        name="water-glare",
        description="lake at Brewster's angle reflecting a cloudy sky; lake bed and wooden posts",
        purpose="glare removal by polarization (paper fig. 13); sky reflection at infinity vs the water plane",
        planar=False, polarizing=True, spectral=True, depth_m=20.0,
        geometry="array 12 m above the water looking 16 m ahead (53.1 deg incidence); bed 1.5 m deep; posts",
        materials="dielectric water n = 1.333; diffuse sand bed and wood; procedural sky envmap",
        truth="centre ray at Brewster's angle: reflected DoLP 1, AoP 0 deg (horizontal)",
        defaults={"sky": 3.0, "cloud_cover": 0.45, "seed": 3},
    )

    def camera_pose(self, p):
        return CameraPose(origin=(0.0, HEIGHT, 0.0), target=(0.0, 0.0, -AHEAD), up=(0.0, 1.0, 0.0), fov_deg=40.0,
                          plane_point=(0.0, 0.0, -AHEAD), plane_normal=(0.0, 1.0, 0.0))

    def mitsuba_dict(self, p):
        import mitsuba as mi

        T = mi.ScalarTransform4f
        scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 8},
                 "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky_envmap(seed=int(p["seed"]),
                                                                          cloud_cover=p["cloud_cover"])),
                         "scale": float(p["sky"])},
                 "water": {"type": "rectangle", "to_world": T().translate([0.0, 0.0, -40.0]).rotate([1, 0, 0], -90)
                           .scale([60.0, 60.0, 1.0]), "bsdf": {"type": "dielectric", "int_ior": N_WATER}},
                 "bed": {"type": "rectangle", "to_world": T().translate([0.0, -1.5, -40.0]).rotate([1, 0, 0], -90)
                         .scale([60.0, 60.0, 1.0]),
                         "bsdf": {"type": "diffuse", "reflectance": {
                             "type": "bitmap", "bitmap": mi.Bitmap(sand_texture(512)),
                             "to_uv": mi.ScalarTransform4f().scale([12.0, 12.0, 1.0])}}}}
        for i, (x, z) in enumerate([(-3.0, -13.0), (2.5, -19.0), (5.5, -12.5)]):
            scene[f"post_{i}"] = {"type": "cylinder", "p0": [x, -1.5, z], "p1": [x, 1.2, z], "radius": 0.18,
                                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                                              "value": [0.35, 0.22, 0.12]}}}
        return scene

    def truth(self, p, camera):
        incidence = math.degrees(math.atan2(AHEAD, HEIGHT))
        rs, rp, dolp = fresnel_dolp(incidence, N_WATER)
        return {"glare": {"centre_incidence_deg": incidence, "brewster_deg": math.degrees(math.atan(N_WATER)),
                          "reflected_dolp": dolp, "aop_deg": 0.0, "rs": rs, "rp": rp}}
