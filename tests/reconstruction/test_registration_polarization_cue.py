"""Registration of polarization-only scenes (flat S0): the motion common to the 45 and 135 deg apertures, which no
intensity criterion sees, is set by the smoothness of the linear polarization (``polarization_cue_radius``)."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from capssim.camera.homography import similarity
from capssim.camera.sensor import Sensor
from capssim.errors import InputError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.registration import RegistrationParameters, estimate_lr_homographies
from capssim.simulate import simulate_capture
from capssim.stokes.polarization import twelve_from_stokes

SIZE = 128
#: 45 and 135 deg share a motion of about 2.5 HR px, which flat S0 hides from the intensity criteria
SHIFTS = [(0.0, 0.0), (2.3, -1.6), (-0.7, 0.4), (1.8, -2.2)]
TRUE = np.stack([similarity(s) for s in SHIFTS])


def _capture(s0, s1, s2):
    stokes = np.stack([np.stack([s0, s1, s2])] * 3, axis=1)  # (3 Stokes, 3 colours, H, W)
    scene = np.asarray(twelve_from_stokes(stokes), dtype=np.float32)
    return simulate_capture(scene, Sensor("none"), aperture_homographies=TRUE, psf={"type": "none"})


def _register(capture, **options):
    images, saturated = capture.lr_images()
    return estimate_lr_homographies(images, hr_shape=(SIZE, SIZE), saturated=saturated,
                                    parameters=RegistrationParameters(**options))


def _max_error(warps) -> np.ndarray:
    """Largest distance (HR px) between the estimated and the true warp of each aperture, over the frame."""
    ys, xs = np.mgrid[8:SIZE - 8:8, 8:SIZE - 8:8]
    points = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    errors = []
    for estimated, true in zip(warps, TRUE):
        a, b = estimated @ points, true @ points
        errors.append(np.hypot(*(a[:2] / a[2] - b[:2] / b[2])).max())
    return np.array(errors)


@pytest.fixture(scope="module")
def fields():
    rng = np.random.default_rng(5)
    smooth = [gaussian_filter(rng.random((SIZE, SIZE)), 6.0) for _ in range(2)]
    return [(f - f.mean()) / f.std() for f in smooth]


@pytest.mark.parametrize("dolp_varies", [False, True])
def test_the_polarization_cue_recovers_the_common_motion(fields, dolp_varies):
    aop, other = fields
    dolp = 0.3 + (0.05 * gaussian_filter(other, 4.0) if dolp_varies else 0.0)
    flat = np.full((SIZE, SIZE), 0.5)
    capture = _capture(flat, flat * dolp * np.cos(2 * aop), flat * dolp * np.sin(2 * aop))
    result = _register(capture)
    cue = result.diagnostics["polarization_cue"]
    assert cue["kept"] and cue["roughness"]["polarization_cue"] < 0.9 * cue["roughness"]["intensity_warps"]
    assert _max_error(result.aperture_homographies).max() < 0.1
    assert any("smoothness of the linear polarization" in w for w in result.diagnostics["warnings"])
    # without the cue the common motion is whatever the intensity criteria left: pixels off, and said so
    blind = _register(capture, polarization_cue_radius=0.0)
    assert "polarization_cue" not in blind.diagnostics
    assert _max_error(blind.aperture_homographies)[[1, 3]].min() > 1.0
    assert any("can be pixels off" in w for w in blind.diagnostics["warnings"])


def test_the_method_record_keeps_what_the_cue_did(fields):
    aop = fields[0]
    flat = np.full((SIZE, SIZE), 0.5)
    _, record = reconstruct(_capture(flat, 0.3 * flat * np.cos(2 * aop), 0.3 * flat * np.sin(2 * aop)), "caps-naive")
    registration = record["registration"]
    assert registration["intensity_texture_ratio"] < 0.2 and registration["polarization_cue"]["kept"]
    assert any("smoothness of the linear polarization" in w for w in registration["warnings"])


def test_the_cue_is_skipped_when_the_pair_fell_back_to_the_identity(fields):
    """An identity fallback (here forced by a scale tolerance no estimate meets) loses the 45/135 pair's relative
    warp, which the cue keeps: it does not run, and the warning says the warps can be pixels off."""
    aop = fields[0]
    flat = np.full((SIZE, SIZE), 0.5)
    capture = _capture(flat, 0.3 * flat * np.cos(2 * aop), 0.3 * flat * np.sin(2 * aop))
    result = _register(capture, max_scale_error=1e-12)
    assert "fell back to the identity" in result.diagnostics["polarization_cue"]["skipped"]
    np.testing.assert_allclose(result.aperture_homographies[[1, 3]], np.tile(np.eye(3), (2, 1, 1)))
    assert any("can be pixels off" in w for w in result.diagnostics["warnings"])


def test_a_scene_with_intensity_texture_is_left_to_the_intensity_criteria(fields):
    s0 = 0.5 + 0.1 * fields[0]
    result = _register(_capture(s0, 0.3 * s0, 0.0 * s0))
    assert "polarization_cue" not in result.diagnostics
    assert _max_error(result.aperture_homographies).max() < 0.3


@pytest.mark.parametrize("radius", [-1.0, 100.0, float("nan")])
def test_a_bad_search_radius_is_refused_with_the_option_named(radius):
    with pytest.raises(InputError, match="polarization_cue_radius"):
        RegistrationParameters(polarization_cue_radius=radius).validate()
