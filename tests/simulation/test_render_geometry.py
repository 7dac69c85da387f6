"""Array geometry: our pinhole rays against Mitsuba's sensor, exact plane homographies, array errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from capssim.errors import InputError
from capssim.render.pinhole_array import (
    PinholeCamera,
    RigTolerances,
    axis_rotation,
    build_array,
    look_at_rotation,
    parallax_residual,
    plane_homography,
)


def _camera(rng, size=24):
    rot = look_at_rotation([0.3, -0.2, 4.0], [0.1, 0.2, 0.0], [0.1, 1.0, 0.0])
    rot = rot @ axis_rotation([0, 0, 1], math.radians(7.0))
    return PinholeCamera([0.3, -0.2, 4.0], rot, 37.5, (size - 1) / 2 + 1.7, (size - 1) / 2 - 2.3, size, size)


def test_rays_match_mitsuba_perspective_sensor():
    import mitsuba as mi

    import capssim.render  # noqa: F401  (sets DRJIT_LIBLLVM_PATH)
    from capssim.render.variants import select_variant

    select_variant("auto", spectral=False, polarized=False)
    cam = _camera(np.random.default_rng(0))
    sensor = mi.load_dict(cam.mitsuba_sensor())
    rows, cols = np.meshgrid(np.arange(cam.height, dtype=float), np.arange(cam.width, dtype=float), indexing="ij")
    xy = np.stack([cols.ravel(), rows.ravel()], -1)
    # Mitsuba film coordinates are ours + 0.5
    pos = mi.Point2f(mi.Float((xy[:, 0] + 0.5) / cam.width), mi.Float((xy[:, 1] + 0.5) / cam.height))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    d_mi = np.stack([np.asarray(ray.d[k]) for k in range(3)], -1)
    d_ours = cam.directions(xy)
    assert np.max(np.abs(d_mi - d_ours)) < 2e-6
    o = np.stack([np.asarray(ray.o[k]) for k in range(3)], -1)  # on Mitsuba's near clip plane
    assert np.max(np.linalg.norm(np.cross(o - cam.origin, d_ours), axis=1)) < 1e-5


def test_project_inverts_directions():
    cam = _camera(np.random.default_rng(1))
    xy = np.random.default_rng(2).uniform(-3, 27, size=(50, 2))
    pts = cam.origin + 3.7 * cam.directions(xy)
    assert np.allclose(cam.project(pts), xy, atol=1e-9)


def test_plane_homography_is_exact_for_plane_points():
    rng = np.random.default_rng(3)
    ref = _camera(rng)
    other = PinholeCamera(ref.origin + [0.04, 0.03, 0.0], ref.rotation @ axis_rotation([1, 1, 0], 0.01),
                          38.0, 12.0, 11.0, 24, 24)
    p0, n = np.array([0.0, 0.0, 0.5]), np.array([0.1, 0.2, 1.0])
    h = plane_homography(ref, other, p0, n)
    xy = rng.uniform(0, 23, size=(40, 2))
    d = ref.directions(xy)
    nn = n / np.linalg.norm(n)
    t = ((p0 - ref.origin) @ nn) / (d @ nn)
    pts = ref.origin + t[:, None] * d
    pred = np.c_[xy, np.ones(len(xy))] @ h.T
    pred = pred[:, :2] / pred[:, 2:]
    assert np.max(np.abs(pred - other.project(pts))) < 1e-9


def test_supersampled_and_expanded_keep_the_pixel_grid():
    cam = _camera(np.random.default_rng(4))
    big = cam.expanded(5).supersampled(3)
    xy = np.array([[0.0, 0.0], [10.0, 3.0], [23.0, 23.0]])
    fine = 3 * (xy + 5) + 1.0  # pixel p -> 3 (p + margin) + (3 - 1) / 2
    assert np.allclose(big.directions(fine), cam.directions(xy), atol=1e-12)


def test_array_reference_is_identity_and_errors_stay_in_range():
    geo = RigTolerances(baseline_m=0.04, tilt_max_deg=0.2, roll_max_deg=0.5, focal_scale_max=0.005)
    arr = build_array(origin=(0, 0, 2.0), target=(0, 0, 0), up=(0, 1, 0), fov_deg=20.0, size=64, geometry=geo,
                      rng=np.random.default_rng(0))
    assert np.array_equal(arr.homographies[0], np.eye(3))
    for n, err in enumerate(arr.errors[1:], start=1):
        assert abs(err["tilt_right_deg"]) <= 0.2 and abs(err["roll_deg"]) <= 0.5
        assert abs(err["focal_scale"] - 1) <= 0.005
        assert err["offset_m"] == [0.04 * (n % 2), 0.04 * (n // 2)]
    # converged: at the reference depth the offsets come from the small errors only
    f = arr.cameras[0].focal_px
    bound = f * math.tan(math.radians(0.2)) * 2 + 32 * math.radians(0.5) * 1.5 + 32 * 0.005 * 1.5 + 1
    centre = np.array([31.5, 31.5, 1.0])
    for h in arr.homographies[1:]:
        q = h @ centre
        assert np.hypot(*(q[:2] / q[2] - centre[:2])) < bound
    again = build_array(origin=(0, 0, 2.0), target=(0, 0, 0), up=(0, 1, 0), fov_deg=20.0, size=64, geometry=geo,
                        rng=np.random.default_rng(0))
    assert np.array_equal(again.homographies, arr.homographies)


def test_parallax_residual_sees_depth_off_the_plane():
    geo = RigTolerances(tilt_max_deg=0.0, roll_max_deg=0.0, focal_scale_max=0.0)
    arr = build_array(origin=(0, 0, 2.0), target=(0, 0, 0), up=(0, 1, 0), fov_deg=20.0, size=32, geometry=geo,
                      rng=np.random.default_rng(0))
    ref = arr.cameras[0]
    rows, cols = np.meshgrid(np.arange(32.0), np.arange(32.0), indexing="ij")
    d = ref.directions(np.stack([cols, rows], -1).reshape(-1, 2))
    on_plane = ref.origin + (2.0 / -d[:, 2:3]) * d
    valid = np.ones((32, 32), bool)
    flat = parallax_residual(arr, on_plane.reshape(32, 32, 3), valid)
    assert flat["max_hr_px"] < 1e-9
    deeper = ref.origin + (4.0 / -d[:, 2:3]) * d  # twice as far: f B (1/2 - 1/4) px for the diagonal aperture
    res = parallax_residual(arr, deeper.reshape(32, 32, 3), valid)
    expected = ref.focal_px * 0.04 * (1 / 2.0 - 1 / 4.0) * math.sqrt(2)
    assert res["max_hr_px"] == pytest.approx(expected, rel=1e-6)
    assert res["depth_min_m"] == pytest.approx(4.0) and res["depth_max_m"] == pytest.approx(4.0)


@pytest.mark.parametrize("bad", [{"baseline_m": -1.0}, {"tilt_max_deg": float("nan")}, {"focal_scale_max": 0.7},
                                 {"wobble": 1}])
def test_geometry_parameters_are_checked(bad):
    with pytest.raises(InputError):
        RigTolerances.from_params(bad)
