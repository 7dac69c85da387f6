"""The projection onto physically valid intensities (capssim.stokes.physical_validity) and its use in reconstruct."""

from __future__ import annotations

import numpy as np
import pytest

from capssim.stokes.physical_validity import project_to_physical
from capssim.stokes.polarization import dolp, stokes_from_12, twelve_from_stokes


def _random_valid(rng, shape=(8, 8)) -> np.ndarray:
    s0 = rng.uniform(0, 1, (3, *shape))
    p = s0 * rng.uniform(0, 1, (3, *shape))
    a = rng.uniform(0, np.pi, (3, *shape))
    return twelve_from_stokes(np.stack([s0, p * np.cos(a), p * np.sin(a)]))


def _groups(x: np.ndarray) -> np.ndarray:
    """(12, H, W) -> (N, 4): the four angles of one colour at one pixel per row."""
    return x.reshape(4, 3, -1).transpose(1, 2, 0).reshape(-1, 4)


def test_valid_input_is_unchanged():
    x = _random_valid(np.random.default_rng(0))
    out, report = project_to_physical(x)
    np.testing.assert_allclose(out, x, atol=1e-6)
    assert report.over_polarized_fraction == 0.0 and report.negative_fraction == 0.0


def test_output_is_valid_and_the_projection_is_idempotent():
    x = np.random.default_rng(1).normal(0.3, 0.5, (12, 16, 16))
    out, report = project_to_physical(x)
    g = _groups(out.astype(np.float64))
    assert g.min() >= 0
    np.testing.assert_allclose(g[:, 0] + g[:, 2], g[:, 1] + g[:, 3], atol=1e-6)
    assert np.all(dolp(stokes_from_12(out.astype(np.float64)), clip=False, min_s0=1e-6) <= 1 + 1e-5)
    assert report.negative_fraction > 0.1 and report.over_polarized_fraction > 0.1
    again, _ = project_to_physical(out)
    np.testing.assert_allclose(again, out, atol=1e-6)


def test_it_is_the_nearest_valid_point():
    """Projection onto a closed convex set: <x - P x, y - P x> <= 0 for every valid y."""
    rng = np.random.default_rng(2)
    x = rng.normal(0.2, 0.6, (12, 6, 6))
    px, _ = project_to_physical(x)
    gx, gp = _groups(x), _groups(px.astype(np.float64))
    for seed in range(20):
        gy = _groups(_random_valid(np.random.default_rng(100 + seed), shape=(6, 6)))
        assert np.all(np.sum((gx - gp) * (gy - gp), axis=1) <= 1e-5)
    # and no other valid point is nearer, e.g. the projection of the plain clip
    clipped_then_projected = _groups(project_to_physical(np.maximum(x, 0))[0].astype(np.float64))
    assert np.sum((gx - gp) ** 2) < np.sum((gx - clipped_then_projected) ** 2)


def test_fully_polarized_light_with_noise_stays_non_negative():
    rng = np.random.default_rng(3)
    s0 = np.full((3, 32, 32), 0.5)
    a = rng.uniform(0, np.pi, (3, 32, 32))
    truth = twelve_from_stokes(np.stack([s0, s0 * np.cos(a), s0 * np.sin(a)]))
    noisy = truth + rng.normal(0, 0.05, truth.shape)
    out, _ = project_to_physical(noisy)
    assert noisy.min() < -0.05 and out.min() >= 0
    assert np.sqrt(np.mean((out - truth) ** 2)) < np.sqrt(np.mean((noisy - truth) ** 2))


def test_unobserved_groups_are_left_alone():
    x = -np.ones((12, 4, 4))
    mask = np.zeros(x.shape, dtype=bool)
    mask[0, 0, 0] = True  # channel 0 = angle 0, red: the red group at (0, 0) is left as it is
    out, _ = project_to_physical(x, unobserved=mask)
    assert np.all(out[[0, 3, 6, 9], 0, 0] == -1)
    assert np.all(out[[1, 4, 7, 10], 0, 0] == 0) and np.all(out[:, 1:, :] == 0)


def test_bad_shape_is_refused():
    with pytest.raises(ValueError, match="image12"):
        project_to_physical(np.zeros((4, 8, 8)))


def test_reconstruct_records_the_projection_and_can_skip_it(scene64):
    from capssim.camera.sensor import make_sensor
    from capssim.reconstruct.registry import reconstruct
    from capssim.simulate import simulate_capture

    tiny_capture = simulate_capture(scene64, make_sensor("gaussian", sigma=0.05), seed=1)

    out, record = reconstruct(tiny_capture, "dofp-bilinear")
    assert set(record["physical_projection"]) == {"negative_fraction", "inconsistent_rms",
                                                  "over_polarized_fraction", "change_rms"}
    assert "physical_projection" in record["stages_s"]
    g = _groups(out.image.astype(np.float64))
    assert g.min() >= 0
    np.testing.assert_allclose(g[:, 0] + g[:, 2], g[:, 1] + g[:, 3], atol=1e-5)
    raw, raw_record = reconstruct(tiny_capture, "dofp-bilinear", physical_projection=False)
    assert raw_record["physical_projection"] is None
    assert record["physical_projection"]["change_rms"] > 0
    assert np.sqrt(np.mean((raw.image - out.image) ** 2)) == pytest.approx(record["physical_projection"]["change_rms"],
                                                                           rel=1e-3)


def test_caps_on_a_fully_polarized_scene_is_never_negative(smooth_random_scene):
    """Issue 21 case 4: caps on a DoLP = 1 scene went down to -0.41; its output is now valid."""

    from capssim.camera.sensor import make_sensor
    from capssim.reconstruct.registry import reconstruct
    from capssim.simulate import simulate_capture

    gt = smooth_random_scene(32, seed=4, dolp_max=1.0)
    s = stokes_from_12(gt.astype(np.float64))
    p = np.hypot(s[1], s[2])
    gt = twelve_from_stokes(np.stack([s[0], s[1] * s[0] / p, s[2] * s[0] / p])).astype(np.float32)  # DoLP 1
    capture = simulate_capture(gt, make_sensor("gaussian", sigma=0.02), seed=0)
    raw, _ = reconstruct(capture, "caps", true_warps=True, iterations=2, physical_projection=False)
    out, record = reconstruct(capture, "caps", true_warps=True, iterations=2)
    assert raw.image.min() < 0 and out.image.min() >= 0
    assert record["physical_projection"]["over_polarized_fraction"] > 0.1
    assert np.mean((out.image - gt) ** 2) < np.mean((raw.image - gt) ** 2)
