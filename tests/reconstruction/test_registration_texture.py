"""Registration: the warning for scenes whose structure is in their polarization only (flat S0)."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from capssim.camera.homography import similarity
from capssim.camera.sensor import Sensor
from capssim.reconstruct.registration import estimate_lr_homographies
from capssim.reconstruct.registration.polarization_cue import POLARIZATION_ONLY_TEXTURE
from capssim.simulate import simulate_capture
from capssim.stokes.polarization import twelve_from_stokes

SIZE = 128
SHIFTS = [(0.0, 0.0), (0.8, -0.6), (-1.1, 0.4), (0.5, 1.2)]


def _register(s0, s1, s2):
    stokes = np.stack([np.stack([s0, s1, s2])] * 3, axis=1)  # (3 Stokes, 3 colours, H, W)
    scene = np.asarray(twelve_from_stokes(stokes), dtype=np.float32)
    capture = simulate_capture(scene, Sensor("none"), aperture_homographies=np.stack([similarity(s) for s in SHIFTS]),
                               psf={"type": "none"})
    images, saturated = capture.lr_images()
    return estimate_lr_homographies(images, hr_shape=(SIZE, SIZE), saturated=saturated)


@pytest.fixture(scope="module")
def texture():
    rng = np.random.default_rng(5)
    field = gaussian_filter(rng.random((SIZE, SIZE)), 3.0)
    return (field - field.mean()) / field.std()


def test_polarization_only_texture_is_flagged(texture):
    aop = 2.0 * texture  # radians: the angle of polarization varies, the intensity does not
    flat = np.full((SIZE, SIZE), 0.5)
    result = _register(flat, 0.3 * np.cos(2 * aop), 0.3 * np.sin(2 * aop))
    assert result.diagnostics["intensity_texture_ratio"] < POLARIZATION_ONLY_TEXTURE
    assert any("structure is in its polarization" in w and "--true-warps" in w
               for w in result.diagnostics["warnings"])


@pytest.mark.parametrize("dolp", [0.0, 0.3])
def test_intensity_texture_is_not_flagged(texture, dolp):
    s0 = 0.5 + 0.1 * texture
    result = _register(s0, dolp * s0, 0.0 * s0)
    assert result.diagnostics["intensity_texture_ratio"] > 0.8
    assert not any("structure is in its polarization" in w for w in result.diagnostics["warnings"])
