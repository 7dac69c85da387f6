"""Physics checks of the renderer (tiny renders): Malus's law and the angle convention against
polarizer-plate renders, Fresnel DoLP of a smooth dielectric, the handedness of the Stokes frame,
the aop-wheel truth, box pixels, and camera-RGB colour."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import capssim.render  # noqa: F401  (sets DRJIT_LIBLLVM_PATH)
from capssim.render.integrator import render_view
from capssim.render.mitsuba_plugins import register_plugins
from capssim.render.pinhole_array import PinholeCamera, look_at_rotation
from capssim.render.spectral import CameraResponse
from capssim.render.variants import select_variant
from capssim.stokes.polarization import angle_difference_deg, aop_deg, dolp


def _variant(spectral: bool, polarized: bool = True):
    choice = select_variant("auto", spectral=spectral, polarized=polarized)
    register_plugins()
    return choice


def _camera(origin, target, size, fov_deg, up=(0.0, 1.0, 0.0)):
    f = (size / 2) / math.tan(math.radians(fov_deg) / 2)
    return PinholeCamera(origin, look_at_rotation(origin, target, up), f, (size - 1) / 2, (size - 1) / 2, size, size)


def _stokes(view, k=None):
    """(3, ...) S0, S1, S2 of colour k (or summed over RGB) from a Stokes render."""
    s = view.mean.reshape(3, 3, *view.mean.shape[1:])
    return s.sum(axis=1) if k is None else s[:, k]


def _backlit(mi, generator: dict | None, analyzer_theta: float | None, radiance: dict):
    T = mi.ScalarTransform4f
    scene = {"type": "scene", "integrator": {"type": "volpath", "max_depth": 6},
             "light": {"type": "rectangle", "to_world": T().translate([0, 0, -1.0]).scale(4.0),
                       "emitter": {"type": "area", "radiance": radiance}}}
    if generator is not None:
        scene["generator"] = {"type": "rectangle", "to_world": T().scale(3.0), "bsdf": generator}
    if analyzer_theta is not None:
        # Mitsuba's own polarizer plate, normal facing the camera, between the scene and the camera
        scene["analyzer"] = {"type": "rectangle", "to_world": T().translate([0, 0, 2.0]).scale(3.0),
                             "bsdf": {"type": "polarizer", "theta": float(analyzer_theta)}}
    return mi.load_dict(scene)


@pytest.mark.parametrize("spectral", [False, True])
def test_malus_law_and_angle_convention_against_plate_renders(spectral):
    """I(a) = (S0 + S1 cos 2a + S2 sin 2a) / 2 from one Stokes render equals what a physical
    polarizer plate in front of the camera transmits, colour by colour; a plate facing the camera
    with theta = t analyzes at image angle -t; and our sheet at angle g emits AoP g."""
    _variant(spectral)
    import mitsuba as mi

    response = CameraResponse()
    cam = _camera([0, 0, 5.0], [0, 0, 0], 4, 10.0)
    g = 25.0  # generator sheet axis, degrees
    radiance = {"type": "rgb", "value": [0.9, 0.6, 0.3]} if spectral else {"type": "d65", "scale": 1.0}
    generator = {"type": "capssim_polarizer", "theta": g, "dolp": 0.7}
    spp = 64
    stokes_view = render_view(_backlit(mi, generator, None, radiance), cam, spp=spp, seed=1, response=response)
    s = stokes_view.mean.reshape(3, 3, -1).mean(axis=2)  # (S0/S1/S2, RGB)
    assert aop_deg(s[:, 1:2])[0] == pytest.approx(g, abs=0.3)
    assert dolp(s[:, 1:2])[0] == pytest.approx(0.7, abs=0.01)
    for t in (0.0, 30.0, 45.0, 100.0, 150.0):
        plate = render_view(_backlit(mi, generator, t, radiance), cam, spp=spp, seed=2, response=response)
        measured = plate.mean[0:3].reshape(3, -1).mean(axis=1)  # S0 behind the plate = transmitted intensity
        a = np.deg2rad(-t)  # the plate analyzes at image angle -theta
        predicted = 0.5 * (s[0] + s[1] * np.cos(2 * a) + s[2] * np.sin(2 * a))
        tol = 0.02 * s[0].max() if spectral else 1e-3 * s[0].max()
        assert np.allclose(measured, predicted, atol=tol), (t, measured, predicted)
        # and Malus's cos^2 law against the generator: I = S0 (1 + d cos 2(g - a)) / 2
        malus = 0.5 * s[0] * (1 + 0.7 * np.cos(2 * (np.deg2rad(g) - a)))
        assert np.allclose(measured, malus, atol=tol)


def test_stokes_frame_handedness_from_fresnel_geometry():
    """Reflection off a glass plane tilted towards the upper right is polarized perpendicular to the
    plane of incidence: at image angle 135 deg if +45 deg turns towards the image top."""
    _variant(False)
    import mitsuba as mi

    T = mi.ScalarTransform4f
    n = np.array([1.0, 1.0, 1.0]) / math.sqrt(3)
    d = np.array([0.0, 0.0, -1.0])
    r = d - 2 * (d @ n) * n
    p = np.array([0.0, 0.0, -3.0])
    e = p + 10 * r
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 4},
                          "glass": {"type": "rectangle", "to_world": T().look_at(origin=p.tolist(),
                                                                                  target=(p + n).tolist(),
                                                                                  up=[0, 1, 0]).scale(2.0),
                                    "bsdf": {"type": "dielectric", "int_ior": 1.5}},
                          "light": {"type": "rectangle", "to_world": T().look_at(origin=e.tolist(), target=p.tolist(),
                                                                                  up=[0, 1, 0]).scale(8.0),
                                    "emitter": {"type": "area", "radiance": {"type": "d65"}}}})
    cam = _camera([0, 0, 0], [0, 0, -1], 2, 0.5)
    view = render_view(scene, cam, spp=256, seed=0, response=CameraResponse())
    s = _stokes(view, 1).reshape(3, -1).mean(axis=1)
    assert aop_deg(s[:, None])[0] == pytest.approx(135.0, abs=1.0)


def _fresnel(theta_deg: float, n: float = 1.5):
    ti = math.radians(theta_deg)
    tt = math.asin(math.sin(ti) / n)
    rs = (math.sin(ti - tt) / math.sin(ti + tt)) ** 2
    rp = (math.tan(ti - tt) / math.tan(ti + tt)) ** 2
    return rs, rp


def test_smooth_dielectric_dolp_follows_fresnel_over_incidence():
    """A glass plane under a uniform sky, a black floor under it: the camera sees only the
    reflection, whose DoLP is (Rs - Rp)/(Rs + Rp): near 1 at Brewster's angle (56.3 deg)."""
    _variant(False)
    import mitsuba as mi

    T = mi.ScalarTransform4f
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 4},
                          "sky": {"type": "constant", "radiance": {"type": "d65", "scale": 1.0}},
                          "glass": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(50.0),
                                    "bsdf": {"type": "dielectric", "int_ior": 1.5}},
                          "floor": {"type": "rectangle", "to_world": T().translate([0, -0.05, 0])
                                    .rotate([1, 0, 0], -90).scale(50.0),
                                    "bsdf": {"type": "diffuse", "reflectance": 0.0}}})
    response = CameraResponse()
    brewster = math.degrees(math.atan(1.5))
    for theta in (20.0, 40.0, brewster, 70.0, 80.0):
        t = math.radians(theta)
        origin = [0.0, 3.0 * math.cos(t), 3.0 * math.sin(t)]
        view = render_view(scene, _camera(origin, [0, 0, 0], 2, 0.5), spp=1024, seed=3, response=response)
        s = _stokes(view, 1).reshape(3, -1).mean(axis=1)
        rs, rp = _fresnel(theta)
        # S0 carries the reflect/refract sampling noise; every reflected sample has the Fresnel DoLP
        assert s[0] == pytest.approx((rs + rp) / 2, rel=0.05), theta
        assert dolp(s[:, None])[0] == pytest.approx((rs - rp) / (rs + rp), abs=0.005), theta
        assert abs(angle_difference_deg(aop_deg(s[:, None])[0], 0.0)) < 1.0  # s-polarized: horizontal
        if theta == brewster:
            assert dolp(s[:, None])[0] > 0.98


def test_aop_wheel_ground_truth_equals_analytic():
    from capssim.render import render_capture
    from capssim.scenes import get_scene
    from capssim.stokes.polarization import stokes_from_12

    size = 32
    cap = render_capture("aop-wheel", size=size, spp=16, psf={"type": "none"})
    sc = get_scene("aop-wheel")
    p = sc.params(None)
    wheel = cap.meta["scene"]["wheel"]
    rows, cols = np.meshgrid(np.arange(size, dtype=float), np.arange(size, dtype=float), indexing="ij")
    xy = np.stack([cols.ravel(), rows.ravel()], -1)
    ref = PinholeCamera(**{k: v for k, v in _ref_camera(cap).items()})
    analytic = sc.analytic_stokes(p, ref, xy).reshape(3, size, size)
    s = stokes_from_12(cap.gt.astype(np.float64))  # (3, RGB, H, W)
    r = np.hypot(rows - wheel["center_rowcol"][0], cols - wheel["center_rowcol"][1]) / wheel["radius_px"]
    ring = (r > 0.3) & (r < 0.9)
    for k in range(3):
        err = np.abs(angle_difference_deg(aop_deg(s[:, k]), aop_deg(analytic)))
        assert np.median(err[ring]) < 0.5 and np.max(err[ring]) < 3.0
        assert np.max(np.abs(dolp(s[:, k]) - dolp(analytic))[ring]) < 0.05
        assert np.allclose(s[0, k], p["level"], atol=1e-4)  # S0 is flat


def _ref_camera(cap):
    c = cap.meta["render"]["array"]["apertures"][0]["camera"]
    rot = np.stack([c["right"], c["down"], c["forward"]], axis=1)
    return {"origin": np.array(c["origin_m"]), "rotation": rot, "focal_px": c["focal_px"],
            "cx": c["principal_point_xy"][0], "cy": c["principal_point_xy"][1], "width": c["width"],
            "height": c["height"]}


def test_box_rendered_raw_equals_box_downsampled_ground_truth():
    """Reference aperture, planar scene: rendering at raw resolution with the box pixel filter gives
    the 2x2 box average of the HR render, within Monte-Carlo noise."""
    from capssim.operators import IntegrateDecimate
    from capssim.render.integrator import stokes_to_twelve
    from capssim.scenes import get_scene

    _variant(False, polarized=False)
    import mitsuba as mi

    sc = get_scene("siemens-star")
    p = sc.params({"cycles": 12})
    mscene = mi.load_dict(sc.mitsuba_dict(p))
    response = CameraResponse()
    hr = _camera([0, 0, 2.0], [0, 0, 0], 32, 20.0)
    raw_cam = PinholeCamera(hr.origin, hr.rotation, hr.focal_px / 2, (hr.cx + 0.5) / 2 - 0.5,
                            (hr.cy + 0.5) / 2 - 0.5, 16, 16)
    gt_view = render_view(mscene, hr, spp=64, seed=5, response=response)
    raw_view = render_view(mscene, raw_cam, spp=64, seed=6, response=response, mode="analyzer", analyzer_deg=0.0)
    gt0 = torch.from_numpy(stokes_to_twelve(gt_view.mean)[0:3])
    down = IntegrateDecimate(2, tuple(gt0.shape))(gt0).numpy()
    diff = raw_view.mean - down
    # MC std of the difference from the single-sample variances of both renders
    var_gt = IntegrateDecimate(2, (3, 32, 32))(torch.from_numpy(gt_view.sample_variance[0:3])).numpy() / 4
    sigma = np.sqrt(raw_view.sample_variance / raw_view.spp + var_gt / gt_view.spp)
    assert np.sqrt(np.mean(diff ** 2)) < 2.0 * np.sqrt(np.mean(sigma ** 2)) + 1e-6
    assert np.max(np.abs(diff)) < 6.0 * sigma.max() + 1e-6
    assert np.std(down) > 0.05  # the star is really there


def test_colorchecker_patches_match_analytic_camera_rgb():
    from capssim.render import render_capture

    cap = render_capture("colorchecker", size=48, spp=64, psf={"type": "none"})
    errs = []
    for patch in cap.meta["scene"]["patches"]:
        r0, r1 = int(math.ceil(patch["row_from"])) + 1, int(math.floor(patch["row_to"])) - 1
        c0, c1 = int(math.ceil(patch["col_from"])) + 1, int(math.floor(patch["col_to"])) - 1
        assert r1 > r0 and c1 > c0
        for p in range(4):  # unpolarized: every analyzer sees the same colour
            got = cap.gt[3 * p:3 * p + 3, r0:r1, c0:c1].mean(axis=(1, 2))
            errs.append(np.abs(got - np.asarray(patch["rgb_per_analyzer"])))
    assert np.max(errs) < 0.012  # white patch: 0.8; measured max 0.007


def test_neutral_scene_is_the_same_in_mono_and_spectral_variants():
    """'Model only what a scene needs': the mono variant is exact for a neutral scene."""
    from capssim.render import render_capture

    kw = dict(size=16, spp=64, psf={"type": "none"}, scene_params={"cycles": 8})
    mono = render_capture("siemens-star", **kw)
    full = render_capture("siemens-star", variant="llvm_ad_spectral_polarized", **kw) \
        if mono.meta["render"]["variant"]["backend"] == "llvm" else None
    assert mono.meta["render"]["variant"]["variant"].endswith("mono")
    if full is None:
        pytest.skip("LLVM backend not available")
    assert np.max(np.abs(mono.gt - full.gt)) < 0.03
    assert abs(float(mono.gt.mean() - full.gt.mean())) < 0.003
