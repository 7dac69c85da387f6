"""``materials``: six spheres of different materials side by side on a textured floor (paper fig. 12).

Geometry (+y up), a tabletop scene scaled by ``scale`` (default 4, so the spheres are
32 cm across at 8 m): six spheres of radius 0.08 on a row at z = 0, on a checkered floor
(5 cm squares) with a checkered back wall at z = -0.8; the array looks down at them from
(0, 0.55, 2.0) (times ``scale``). Depths from about 0.65x to 1.4x the reference depth: real
parallax (a few HR pixels at 256 px with the default 4 cm baseline), so every aperture is
rendered from its own position.

Materials, left to right: smooth gold (``conductor``, Au), rough aluminium
(``roughconductor``, alpha 0.12), red polarizing plastic (``pplastic``, alpha 0.06), smooth
glass (``dielectric``, n = 1.5), rough glass (``roughdielectric``, alpha 0.15), and diffuse
green paint (``diffuse``, depolarizing). Lighting: a 1 m square D65 soft box up-left-front
and a dim uniform D65 sky.

Known truth: no closed form; the qualitative polarization signatures (specular reflections
of the dielectrics and plastic strongly polarized perpendicular to the plane of incidence,
metals weakly, diffuse paint not at all) are what fig. 12 shows. Spectral; polarizing; 3-D.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError
from capssim.render.scene_base import CameraPose, Scene, SceneInfo, d65, scale_pose, scale_scene

RADIUS = 0.08
XS = (-0.425, -0.255, -0.085, 0.085, 0.255, 0.425)
MATERIALS = (
    ("gold", {"type": "conductor", "material": "Au"}),
    ("rough aluminium", {"type": "roughconductor", "material": "Al", "alpha": 0.12}),
    ("red plastic", {"type": "pplastic", "diffuse_reflectance": {"type": "rgb", "value": [0.55, 0.04, 0.04]},
                     "alpha": 0.06}),
    ("smooth glass", {"type": "dielectric", "int_ior": 1.5}),
    ("rough glass", {"type": "roughdielectric", "int_ior": 1.5, "alpha": 0.15}),
    ("green paint", {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.08, 0.40, 0.12]}}),
)


def checker(c0, c1, squares: float) -> dict:
    import mitsuba as mi

    return {"type": "checkerboard", "color0": {"type": "rgb", "value": list(c0)},
            "color1": {"type": "rgb", "value": list(c1)}, "to_uv": mi.ScalarTransform4f().scale([squares, squares, 1])}


class Materials(Scene):
    info = SceneInfo(
        name="materials",
        description="gold, rough aluminium, red plastic, smooth and rough glass, diffuse paint spheres on a checker floor",
        purpose="material classification by polarization (paper fig. 12); 3-D parallax",
        planar=False, polarizing=True, spectral=True, depth_m=8.0,
        geometry="six spheres in a row (r = 32 cm at 8 m), checker floor and back wall (5-11 m)",
        materials="conductor Au, roughconductor Al, pplastic, dielectric, roughdielectric, diffuse",
        truth="none in closed form: sphere positions and materials in meta scene.spheres",
        defaults={"light": 9.0, "sky": 0.7, "scale": 4.0},
    )

    def check_params(self, p):
        if not 0.1 <= p["scale"] <= 100:
            raise InputError("scene_params.scale", p["scale"], "a factor in [0.1, 100]")

    def camera_pose(self, p):
        return scale_pose(CameraPose(origin=(0.0, 0.55, 2.0), target=(0.0, 0.12, 0.0), up=(0.0, 1.0, 0.0),
                                     fov_deg=26.0), p["scale"])

    def mitsuba_dict(self, p):
        import mitsuba as mi

        T = mi.ScalarTransform4f
        scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 10},
                 "sky": {"type": "constant", "radiance": d65(p["sky"])},
                 "softbox": {"type": "rectangle",
                             "to_world": T().look_at(origin=[-1.0, 1.6, 1.3], target=[0.0, 0.1, 0.0],
                                                     up=[0, 1, 0]).scale([0.5, 0.5, 1.0]),
                             "emitter": {"type": "area", "radiance": d65(p["light"])}},
                 "floor": {"type": "rectangle",
                           "to_world": T().rotate([1, 0, 0], -90).scale([3.0, 3.0, 1.0]),
                           "bsdf": {"type": "diffuse", "reflectance": checker((0.55, 0.52, 0.45), (0.25, 0.24, 0.22),
                                                                              60.0)}},
                 "wall": {"type": "rectangle", "to_world": T().translate([0.0, 1.0, -0.8]).scale([3.0, 1.5, 1.0]),
                          "bsdf": {"type": "diffuse", "reflectance": checker((0.30, 0.38, 0.55), (0.60, 0.55, 0.40),
                                                                             12.0)}}}
        for i, (x, (name, bsdf)) in enumerate(zip(XS, MATERIALS)):
            scene[f"sphere_{i}"] = {"type": "sphere", "center": [x, RADIUS, 0.0], "radius": RADIUS, "bsdf": bsdf}
        return scale_scene(scene, p["scale"])

    def truth(self, p, camera):
        spheres = []
        s = p["scale"]
        for x, (name, bsdf) in zip(XS, MATERIALS):
            centre = s * np.array([x, RADIUS, 0.0])
            c = camera.project(centre[None])[0]
            dist = float(np.linalg.norm(centre - camera.origin))
            spheres.append({"material": name, "bsdf": bsdf["type"], "center_rowcol": [float(c[1]), float(c[0])],
                            "radius_px": float(s * RADIUS * camera.focal_px / dist)})
        return {"spheres": spheres}
