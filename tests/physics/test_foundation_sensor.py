"""Sensor models: photon-transfer curve, seeding, clipping, presets, errors."""

from __future__ import annotations

import numpy as np
import pytest

from capssim.camera.sensor import (
    SENSOR_PRESETS,
    GaussianSensor,
    NoNoiseSensor,
    PoissonGaussianSensor,
    make_sensor,
    noise_sigma_estimate,
    sensor_from_meta,
)
from capssim.errors import InputError, UnknownNameError


@pytest.mark.parametrize("preset", sorted(SENSOR_PRESETS))
def test_photon_transfer_curve_matches_emva_model(preset):
    sensor = make_sensor("poisson-gaussian", preset=preset)
    rng = np.random.default_rng(0)
    levels = np.array([0.02, 0.1, 0.3, 0.6, 0.85])
    flat = np.repeat(levels[:, None], 200_000, axis=1)
    dn = sensor.capture(flat, rng).astype(np.float64)
    mean, var = dn.mean(axis=1), dn.var(axis=1)
    k, black, read = sensor.gain_dn_per_e, sensor.black_level, sensor.read_noise_e
    expected_var = k * (mean - black) + k**2 * read**2 + 1 / 12
    np.testing.assert_allclose(var, expected_var, rtol=0.03)
    # the mean response is linear: to_float inverts it
    np.testing.assert_allclose(sensor.to_float(dn).mean(axis=1), levels, rtol=0.01, atol=2e-4)
    np.testing.assert_allclose(sensor.noise_std(levels), np.sqrt(var) / (k * sensor.full_well_e), rtol=0.03)


def test_poisson_gaussian_clips_at_full_well_and_flags_saturation():
    sensor = PoissonGaussianSensor(full_well_e=1000, read_noise_e=2, gain_dn_per_e=1.0, black_level_dn=10,
                                   bit_depth=12)
    dn = sensor.capture(np.array([[0.0, 2.0, 5.0]]), np.random.default_rng(0))
    assert dn.dtype == np.uint16
    assert dn[0, 1] == dn[0, 2] == sensor.white_level == 1010
    np.testing.assert_array_equal(sensor.saturation_mask(dn), [[False, True, True]])


def test_gaussian_sensor_sigma_and_quantization():
    sensor = GaussianSensor(sigma=0.02, bit_depth=16)
    x = np.full((400, 400), 0.5)
    raw = sensor.capture(x, np.random.default_rng(1))
    assert raw.dtype == np.uint16
    f = sensor.to_float(raw)
    assert abs(f.std() - 0.02) < 0.0005 and abs(f.mean() - 0.5) < 0.0005
    assert abs(noise_sigma_estimate(sensor) - 0.02) < 1e-4


def test_seeded_reproducibility():
    for sensor in (GaussianSensor(sigma=0.05), make_sensor("poisson-gaussian", preset="python1300")):
        x = np.random.default_rng(5).random((30, 30))
        a = sensor.capture(x, np.random.default_rng(42))
        b = sensor.capture(x, np.random.default_rng(42))
        c = sensor.capture(x, np.random.default_rng(43))
        assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_none_sensor_is_exact():
    x = np.random.default_rng(0).random((4, 5))
    out = NoNoiseSensor().capture(x, np.random.default_rng(0))
    assert out.dtype == np.float32 and np.array_equal(out, x.astype(np.float32))
    assert not NoNoiseSensor().saturation_mask(out).any()


def test_meta_round_trip():
    for sensor in (NoNoiseSensor(), GaussianSensor(sigma=0.01), make_sensor("poisson-gaussian", preset="imx250myr")):
        again = sensor_from_meta(sensor.to_meta())
        assert again == sensor and again.white_level == sensor.white_level


def test_bad_sensor_options_are_clear():
    with pytest.raises(UnknownNameError, match="python1300"):
        make_sensor("poisson-gaussian", preset="nikon")
    with pytest.raises(UnknownNameError, match="gaussian"):
        make_sensor("speckle")
    with pytest.raises(InputError, match="sigma"):
        make_sensor("gaussian")
    with pytest.raises(InputError, match="sigma"):
        make_sensor("gaussian", sigma=-1)
    with pytest.raises(InputError, match="bit_depth"):
        GaussianSensor(sigma=0.1, bit_depth=20)
    with pytest.raises(InputError, match="non-finite"):
        GaussianSensor(sigma=0.1).capture(np.array([np.nan]), np.random.default_rng(0))
    with pytest.raises(InputError, match="float"):
        GaussianSensor(sigma=0.1).capture(np.array([1], dtype=np.uint8), np.random.default_rng(0))
