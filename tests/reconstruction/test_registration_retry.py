"""Registration: the retry with wider windows after an implausible warp (reconstruct.registration.estimate).

A false match (a 512 px rendered Siemens star locks small windows onto its aliased centre at a scale of
1.5) is replaced by a second registration with ``retry_window_radius`` windows, kept only when all its
warps are plausible and it is more Stokes-consistent. The first registration's false match is injected here by
wrapping the engine, so that every branch of the rule runs on a real capture.
"""

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

import capssim.reconstruct.registration.estimate as registration
from capssim.camera.homography import registration_error_hr_px, similarity
from capssim.camera.sensor import Sensor
from capssim.errors import InputError
from capssim.reconstruct.registration import estimate_lr_homographies
from capssim.reconstruct.registration.engine import params_to_matrices
from capssim.reconstruct.registration.parameters import RegistrationParameters
from capssim.simulate import simulate_capture

SIZE = 128
SHIFTS = [(0.0, 0.0), (0.8, -0.6), (-1.1, 0.4), (0.5, 1.2)]


@pytest.fixture(scope="module")
def shifted_capture():
    """``(images, saturated, true_lr)`` of a smooth unpolarized grey scene seen through :data:`SHIFTS`."""
    rng = np.random.default_rng(3)

    grey = gaussian_filter(rng.random((SIZE, SIZE)), 2.0)
    grey = 0.2 + 0.6 * (grey - grey.min()) / np.ptp(grey)
    scene = np.repeat(grey[None], 12, 0).astype(np.float32)
    homographies = np.stack([similarity(s) for s in SHIFTS])
    capture = simulate_capture(scene, Sensor("none"), aperture_homographies=homographies, psf={"type": "none"})
    images, saturated = capture.lr_images()
    return images, saturated, capture.true_lr_homographies()


@pytest.fixture
def false_match(monkeypatch):
    """Make the engine's runs with windows of the radii in ``bad`` return aperture 2 scaled by 1.5 (a false match);
    returns ``(bad, radii)``: the set to fill and the window radius of every engine run."""
    real = registration.register_stack
    bad: set[int] = set()
    radii: list[int] = []

    def engine(ref, moving, **kwargs):
        radii.append(kwargs["window_radius"])
        result = real(ref, moving, **kwargs)
        if kwargs["window_radius"] in bad:  # similarity parameters (tx, ty, a, b) in pixels at the image radius
            hh, ww = ref.shape
            radius = max(hh, ww) / 2.0
            params = torch.as_tensor(result.params).clone()
            params[1, 2] += 0.5 * radius  # aperture 2 (the second moving image) scaled by 1.5
            result.params = params.numpy()
            result.matrices = params_to_matrices(params, kwargs["model"], ((ww - 1) / 2.0, (hh - 1) / 2.0),
                                                 radius).numpy()
        return result

    monkeypatch.setattr(registration, "register_stack", engine)
    return bad, radii


def _error(result, true_lr):
    return registration_error_hr_px(result.lr_homographies, true_lr, (SIZE, SIZE))


def test_retry_replaces_an_implausible_warp(shifted_capture, false_match):
    images, saturated, true_lr = shifted_capture
    bad, radii = false_match
    bad.add(3)
    result = estimate_lr_homographies(images, hr_shape=(SIZE, SIZE), saturated=saturated,
                                      parameters=RegistrationParameters(luminance="binomial"))
    retry = result.diagnostics["wide_window_retry"]
    assert retry["implausible_apertures"] == [2] and retry["window_radius"] == 6
    assert retry["kept"] is True
    assert retry["stokes_residual_rms"]["retry"] < retry["stokes_residual_rms"]["first"]
    assert 6 in radii
    assert not any("implausible" in w for w in result.diagnostics["warnings"])
    assert result.diagnostics["apertures"][2]["fallback"] == "none"
    assert np.max(_error(result, true_lr)) < 0.1


def test_a_retry_that_is_implausible_too_keeps_the_identity_fallback(shifted_capture, false_match):
    images, saturated, true_lr = shifted_capture
    bad, _ = false_match
    bad.update({3, 6})
    result = estimate_lr_homographies(images, hr_shape=(SIZE, SIZE), saturated=saturated,
                                      parameters=RegistrationParameters(luminance="binomial"))
    assert result.diagnostics["wide_window_retry"]["kept"] is False
    assert result.diagnostics["apertures"][2]["fallback"] == "identity: implausible warp"
    np.testing.assert_array_equal(result.aperture_homographies[2], np.eye(3))
    assert any("aperture 2 (90 deg)" in w and "implausible" in w for w in result.diagnostics["warnings"])


def test_no_retry_when_every_warp_is_plausible_or_the_retry_is_off(shifted_capture, false_match):
    images, saturated, _ = shifted_capture
    bad, radii = false_match
    plain = estimate_lr_homographies(images, hr_shape=(SIZE, SIZE), saturated=saturated,
                                     parameters=RegistrationParameters(luminance="binomial"))
    assert "wide_window_retry" not in plain.diagnostics and 6 not in radii
    bad.add(3)
    off = estimate_lr_homographies(images, hr_shape=(SIZE, SIZE), saturated=saturated,
                                   parameters=RegistrationParameters(luminance="binomial", retry_window_radius=0))
    assert "wide_window_retry" not in off.diagnostics and 6 not in radii
    assert off.diagnostics["apertures"][2]["fallback"] == "identity: implausible warp"


@pytest.mark.parametrize("value", [-1, 2.5, True])
def test_retry_window_radius_is_checked(value):
    with pytest.raises(InputError, match="retry_window_radius"):
        RegistrationParameters(retry_window_radius=value).validate()
