"""Stokes helpers: Malus's law, round trips, DoLP/AoP edge cases, numpy/torch parity."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.errors import InputError
from capssim.stokes.polarization import (
    angle_difference_deg,
    aop_deg,
    dark_mask,
    dolp,
    intensities_from_stokes,
    split_12,
    stokes_from_12,
    stokes_from_intensities,
    twelve_from_stokes,
)


def test_malus_law_for_fully_polarized_light():
    # linear polarization at angle theta: I(a) = S0 cos^2(a - theta)
    for theta in (0.0, 30.0, 45.0, 100.0, 170.0):
        t = np.deg2rad(2 * theta)
        s = np.array([1.0, np.cos(t), np.sin(t)])
        angles = np.arange(0, 180, 15.0)
        got = intensities_from_stokes(s, angles_deg=angles)
        np.testing.assert_allclose(got, np.cos(np.deg2rad(angles - theta)) ** 2, atol=1e-12)


def test_stokes_round_trip_and_consistency():
    rng = np.random.default_rng(0)
    s0 = rng.uniform(0.1, 1, (5, 6))
    d = rng.uniform(0, 1, (5, 6))
    a = rng.uniform(0, np.pi, (5, 6))
    s = np.stack([s0, s0 * d * np.cos(2 * a), s0 * d * np.sin(2 * a)])
    inten = intensities_from_stokes(s)
    np.testing.assert_allclose(stokes_from_intensities(inten), s, atol=1e-12)
    np.testing.assert_allclose(inten[0] + inten[2], inten[1] + inten[3], atol=1e-12)
    np.testing.assert_allclose(dolp(s), d, atol=1e-12)
    np.testing.assert_allclose(np.deg2rad(aop_deg(s)), a, atol=1e-9)


def test_twelve_channel_round_trip_and_order():
    rng = np.random.default_rng(1)
    s0 = rng.uniform(0.1, 1, (3, 4, 4))
    s = np.stack([s0, 0.3 * s0, -0.2 * s0])
    img = twelve_from_stokes(s)
    assert img.shape == (12, 4, 4)
    # channel c = 3p + k: channel 3 is 45-R and equals (S0 + S2)/2 of red
    np.testing.assert_allclose(img[3], (s[0, 0] + s[2, 0]) / 2)
    np.testing.assert_allclose(stokes_from_12(img), s, atol=1e-12)
    assert split_12(img).shape == (4, 3, 4, 4)
    with pytest.raises(InputError):
        split_12(img[:11])


def test_dolp_guards_dark_pixels_and_clips():
    s = np.array([[0.0, 1e-9, -0.1, 1.0], [0.0, 1e-9, 0.05, 1.5], [0.0, 0.0, 0.0, 0.0]])
    d = dolp(s, min_s0=1e-6)
    assert np.all(np.isfinite(d))
    np.testing.assert_array_equal(d[:3], [0, 0, 0])
    assert d[3] == 1.0  # |S1| > S0 from noise is clipped
    d_nan = dolp(s, min_s0=1e-6, fill=np.nan)
    assert np.isnan(d_nan[:3]).all() and d_nan[3] == 1.0
    assert dolp(s, clip=False)[3] == 1.5
    np.testing.assert_array_equal(dark_mask(s, min_s0=1e-6), [True, True, True, False])


def test_nan_propagates_only_where_present():
    s = np.ones((3, 2, 2)) * np.array([1.0, 0.2, 0.1])[:, None, None]
    s[1, 0, 1] = np.nan
    d = dolp(s)
    assert np.isnan(d[0, 1]) and np.isfinite(d[[0, 1, 1], [0, 0, 1]]).all()
    a = aop_deg(s)
    assert np.isnan(a[0, 1]) and np.isfinite(a[1, 1])


def test_aop_wrap_and_range():
    angles = np.array([0.0, 44.9, 90.0, 135.0, 179.99, 180.0, -0.001])
    t = np.deg2rad(2 * angles)
    s = np.stack([np.ones_like(t), np.cos(t), np.sin(t)])
    a = aop_deg(s)
    assert np.all((a >= 0) & (a < 180))
    np.testing.assert_allclose(angle_difference_deg(a, angles % 180), 0, atol=1e-6)
    # S1 = S2 = 0: undefined, reads 0; negative zero must not give 180
    assert aop_deg(np.array([1.0, -0.0, -0.0])) == 0.0
    assert aop_deg(np.array([1.0, -1.0, -1e-18])) < 180
    np.testing.assert_allclose(angle_difference_deg(np.array(179.0), np.array(1.0)), -2.0)
    assert aop_deg(np.array([0.0, 0.3, 0.4]), min_s0=1e-3, fill=-1.0) == -1.0


def test_numpy_and_torch_agree():
    rng = np.random.default_rng(2)
    inten = rng.uniform(0, 1, (4, 3, 5))
    s_np = stokes_from_intensities(inten)
    s_t = stokes_from_intensities(torch.from_numpy(inten))
    np.testing.assert_allclose(s_t.numpy(), s_np)
    np.testing.assert_allclose(dolp(s_t).numpy(), dolp(s_np))
    np.testing.assert_allclose(aop_deg(s_t).numpy(), aop_deg(s_np), atol=1e-9)
    s_axis = stokes_from_intensities(np.moveaxis(inten, 0, 2), axis=2)
    np.testing.assert_allclose(np.moveaxis(s_axis, 2, 0), s_np)
