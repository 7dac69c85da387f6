"""Registration (reconstruct.registration): known homographies, conventions and hard cases."""

import logging

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

import capssim.reconstruct.registration.engine as core
import capssim.reconstruct.registration.estimate as registration
from capssim.camera.homography import registration_error_hr_px, similarity
from capssim.camera.sensor import Sensor
from capssim.errors import InputError, UnknownNameError
from capssim.reconstruct.registration import estimate_lr_homographies
from capssim.reconstruct.registration.luminance import mosaic_from_sub_images, ri_binomial_luminance
from capssim.reconstruct.registration.parameters import RegistrationParameters, registration_parameters
from capssim.simulate import simulate_capture
from capssim.stokes.polarization import twelve_from_stokes

SHIFTS = [(0.0, 0.0), (0.3, -0.7), (1.25, 0.5), (-0.6, 1.1)]
TRANSLATION = RegistrationParameters(model="translation")


def _capture(scene, homographies):
    cap = simulate_capture(scene, Sensor("none"), aperture_homographies=homographies, psf={"type": "none"})
    return cap.lr_images()


@pytest.fixture
def unpolarized(smooth_random_scene):
    """Factory: ``(size, seed=0, *, grey=True) -> (12, size, size)`` unpolarized scene."""

    def _unpolarized(size, seed=0, *, grey=True):
        """Same image behind every polarizer; ``grey``: also the same in R, G, B (no Bayer colour aliasing)."""
        s = smooth_random_scene(size, seed=seed, dolp_max=0.0).reshape(4, 3, size, size)
        s = s.mean(0, keepdims=True)
        if grey:
            s = np.repeat(s.mean(1, keepdims=True), 3, 1)
        return np.repeat(s, 4, 0).reshape(12, size, size)

    return _unpolarized


def test_recovers_known_translations_grey_unpolarized(unpolarized):
    """Pure translations, no polarization or colour texture: checks raw/Bayer/pixel-centre conventions.

    A half-pixel or Bayer-offset mistake would give >= 0.25 HR px; the tolerance is 0.05.
    """
    size = 128
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(unpolarized(size), h)
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat, parameters=TRANSLATION)
    true = simulate_capture(unpolarized(size), Sensor("none"), aperture_homographies=h,
                            psf={"type": "none"}).true_lr_homographies()
    err = registration_error_hr_px(res.lr_homographies, true, (size, size))
    assert np.all(np.isfinite(res.lr_homographies))
    assert np.median(err) < 0.05, err
    np.testing.assert_allclose(res.aperture_homographies[1:, :2, 2], np.array(SHIFTS[1:]), atol=0.05)


def test_flat_images_fall_back_with_warning(caplog):
    images = np.full((16, 16, 16), 0.5, np.float32)
    with caplog.at_level(logging.WARNING):
        res = estimate_lr_homographies(images, hr_shape=(64, 64))
    assert np.all(np.isfinite(res.lr_homographies))
    np.testing.assert_allclose(res.aperture_homographies, np.tile(np.eye(3), (4, 1, 1)))
    assert any("flat" in w for w in res.diagnostics["warnings"])


def test_saturated_pixels_are_finite(unpolarized):
    size = 96
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(unpolarized(size, seed=1), h)
    images = images.copy()
    images[:, :6, :6] = 1.0
    sat = sat.copy()
    sat[:, :6, :6] = True
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat, parameters=TRANSLATION)
    assert np.all(np.isfinite(res.lr_homographies))


def test_nan_input_is_an_input_error():
    images = np.random.default_rng(0).random((16, 16, 16)).astype(np.float32)
    images[3, 2, 2] = np.nan
    with pytest.raises(InputError):
        estimate_lr_homographies(images, hr_shape=(64, 64))


def test_bad_shapes_are_input_errors():
    with pytest.raises(InputError):
        estimate_lr_homographies(np.zeros((15, 8, 8), np.float32), hr_shape=(32, 32))
    with pytest.raises(InputError):
        estimate_lr_homographies(np.zeros((16, 8, 8), np.float32), hr_shape=(30, 32))


def test_too_small_frames_fall_back():
    images = np.random.default_rng(0).random((16, 2, 2)).astype(np.float32)
    res = estimate_lr_homographies(images, hr_shape=(8, 8))
    assert np.all(np.isfinite(res.lr_homographies))
    assert res.diagnostics["model"] is None
    assert res.diagnostics["warnings"]


def test_large_misregistration_is_finite_or_flagged(unpolarized):
    """A shift far beyond the search range: a finite result, flagged unreliable or off by a lot, never NaN."""
    size = 64
    h = np.stack([similarity((40.0 * (n > 0), 0.0)) for n in range(4)])
    images, sat = _capture(unpolarized(size, seed=2), h)
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat, parameters=TRANSLATION)
    assert np.all(np.isfinite(res.lr_homographies))


@pytest.mark.xfail(strict=True, reason="known open bias (~0.1 HR px) from R, G, B textures that are independent of "
                   "each other: the binomial luminance leaks their colour edges, the demosaicking's "
                   "smooth-colour-difference assumption fails; see docs: notes/registration.md")
def test_recovers_known_translations_independent_colour_texture(unpolarized):
    size = 128
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(unpolarized(size, grey=False), h)
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat, parameters=TRANSLATION)
    err = np.abs(res.aperture_homographies[1:, :2, 2] - np.array(SHIFTS[1:]))
    assert err.max() < 0.05, err


def _translation_errors(scene, *, size=128, **kw):
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(scene, h)
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat,
                                   parameters=TRANSLATION.replace(**kw))
    return np.abs(res.aperture_homographies[1:, :2, 2] - np.array(SHIFTS[1:])), res.diagnostics


def test_colour_and_polarization_texture_is_registered_through_the_demosaicked_luminance(smooth_random_scene):
    """Colour and polarization texture (DoLP up to 0.6): the binomial luminance leaks the colour edges as a
    pattern tied to each sensor grid (0.147 HR px); the default keeps the RI-demosaicked luminance's warps,
    whose registered images are more Stokes-consistent, within the issue's 0.05."""
    scene = smooth_random_scene(128, seed=0, dolp_max=0.6)
    binomial, _ = _translation_errors(scene, luminance="binomial")
    err, diag = _translation_errors(scene)
    assert binomial.max() > 0.1, binomial  # the bias exists
    assert err.max() < 0.05, err
    assert diag["luminance"] == "ri-binomial"
    rms = diag["luminance_stokes_residual_rms"]
    assert rms["ri-binomial"] < rms["binomial"]


def test_ri_luminance_removes_most_of_the_colour_aliasing_bias(unpolarized):
    """Independent R, G, B textures: the RI-demosaicked luminance at least halves the binomial's worst error."""
    scene = unpolarized(128, grey=False)
    binomial, _ = _translation_errors(scene, luminance="binomial")
    ri, _ = _translation_errors(scene, luminance="ri-binomial")
    assert binomial.max() > 0.2, binomial  # the bias exists
    assert ri.max() < 0.5 * binomial.max(), (ri, binomial)


def test_ri_binomial_luminance_constant_colour_and_tiny_frames():
    """A constant colour gives (R + 2G + B) / 4 everywhere, border included; frames down to 2x2 work."""
    for side in (2, 6, 16):
        sub = torch.tensor([0.2, 0.5, 0.5, 0.8], dtype=torch.float64).repeat(4)[:, None, None]
        raw = mosaic_from_sub_images(sub.expand(16, side // 2, side // 2).contiguous())
        lum = ri_binomial_luminance(raw)
        assert lum.shape == raw.shape
        torch.testing.assert_close(lum, torch.full_like(lum, 0.5))


def test_unknown_luminance_is_a_clear_error():
    with pytest.raises(UnknownNameError, match="luminance.*auto"):
        estimate_lr_homographies(np.zeros((16, 8, 8), np.float32), hr_shape=(32, 32),
                                 parameters=RegistrationParameters(luminance="demosaic"))


@pytest.fixture
def grey_polarized(smooth_random_scene):
    """Factory: ``(size, seed) -> (12, size, size)`` grey, polarized scene."""

    def _grey_polarized(size, seed):
        """Polarization texture (DoLP up to 0.6, varying AoP), Stokes-consistent, R = G = B."""
        s = smooth_random_scene(size, seed=seed, dolp_max=0.6).reshape(4, 3, size, size)
        return np.repeat(s.mean(1, keepdims=True), 3, 1).reshape(12, size, size)

    return _grey_polarized


@pytest.mark.parametrize("seed", [1, 2])
def test_stokes_subspace_mode_removes_polarization_texture_bias(seed, grey_polarized):
    """The local-correlation estimate is biased by polarization texture (0.1-0.27 px here); the
    stokes-subspace mode fixes the directions the Stokes residual determines (< 0.05 px)."""
    size = 128
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(grey_polarized(size, seed), h)
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat,
                                   parameters=registration_parameters("stokes-subspace").replace(model="translation"))
    err = np.abs(res.aperture_homographies[1:, :2, 2] - np.array(SHIFTS[1:]))
    assert err.max() < 0.05, err
    steps = res.diagnostics["engine"]["stokes_subspace"]["steps"]
    assert steps and steps[0]["kept_directions"] > 0


def test_stokes_subspace_mode_keeps_unpolarized_estimate(unpolarized):
    """Without polarization texture the Stokes residual fixes few directions; the result stays accurate."""
    size = 128
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(unpolarized(size), h)
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat,
                                   parameters=TRANSLATION.replace(stokes_subspace_std=0.01))
    np.testing.assert_allclose(res.aperture_homographies[1:, :2, 2], np.array(SHIFTS[1:]), atol=0.05)


def test_registration_mode_names_and_bad_values():
    with pytest.raises(UnknownNameError, match="local-correlation"):
        registration_parameters("stokes")
    assert RegistrationParameters.for_mode("local-correlation") == RegistrationParameters()
    assert registration_parameters("stokes-subspace").stokes_subspace_std == 0.01
    with pytest.raises(InputError, match="stokes_subspace_std"):
        estimate_lr_homographies(np.zeros((16, 8, 8), np.float32), hr_shape=(32, 32),
                                 parameters=RegistrationParameters(stokes_subspace_std=-1.0))
    with pytest.raises(UnknownNameError, match="registration parameter"):
        RegistrationParameters().replace(stokes=1.0)
    for bad in ({"max_iterations": 0}, {"window_radius": 1.5}, {"presmooth_sigma": float("nan")}):
        with pytest.raises(InputError, match=next(iter(bad))):
            RegistrationParameters(**bad).validate()
    with pytest.raises(InputError, match="parameters"):
        estimate_lr_homographies(np.zeros((16, 8, 8), np.float32), hr_shape=(32, 32), parameters={"model": "affine"})


def _photoelastic(size, seed):
    """Weak S0 texture under strong S1/S2 fringes (a smooth phase field, DoLP up to 0.5, R = G = B):
    the 45 and 135 deg images look unlike the 0 deg one, as on qiu-cellphonecases."""
    rng = np.random.default_rng(seed)

    def texture(sigma):
        t = gaussian_filter(rng.random((size, size)), sigma)
        return (t - t.mean()) / t.std()

    s0 = 0.5 + 0.05 * texture(1.5)
    phase = 12.0 * texture(6.0)
    stokes = np.stack([s0, 0.225 * np.cos(phase), 0.36 * np.sin(phase)])[:, None].repeat(3, 1)
    return twelve_from_stokes(stokes).astype(np.float32)


@pytest.mark.parametrize("seed", [1, 2])
def test_photoelastic_texture_is_registered_by_the_stokes_rescue(seed, monkeypatch):
    """Two or three analyzer images match the 0 deg image poorly; the local correlation alone
    lands pixels off, the Stokes-consistency rescue brings them back (docs: notes/registration.md)."""
    size = 128
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(_photoelastic(size, seed), h)
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat, parameters=TRANSLATION)
    err = np.abs(res.aperture_homographies[1:, :2, 2] - np.array(SHIFTS[1:]))
    assert err.max() < 0.05, err
    joint = res.diagnostics["engine"]["stokes_joint"]
    assert joint["kept"] and joint["stokes_rms_after"] < 0.5 * joint["stokes_rms_before"]
    rescued = [a for a in res.diagnostics["apertures"] if a.get("stokes_rescued")]
    assert len(rescued) >= 2 and not any(a.get("unreliable") for a in rescued)

    monkeypatch.setattr(core, "stokes_joint_rescue", lambda p, *args, **kwargs: p)
    off = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat, parameters=TRANSLATION)
    err_off = np.abs(off.aperture_homographies[1:, :2, 2] - np.array(SHIFTS[1:]))
    assert err_off.max() > 0.5, err_off   # the case needs the rescue


def test_stokes_rescue_is_not_tried_on_well_matched_apertures(unpolarized):
    size = 128
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(unpolarized(size), h)
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat, parameters=TRANSLATION)
    joint = res.diagnostics["engine"]["stokes_joint"]
    assert joint["images"] == [] and "kept" not in joint


def _polarizing_wheel(size):
    """Flat S0 = 1, AoP = azimuth / 2, DoLP = 0.8: each analyzer image is the 0 deg one rotated by 2 theta."""
    yy, xx = np.mgrid[0:size, 0:size] - (size - 1) / 2.0
    azimuth = np.arctan2(yy, xx)
    rings = 0.3 + 0.2 * (np.hypot(xx, yy) < 0.3 * size)  # some radial structure for the matcher
    inten = [0.5 * (1 + 0.8 * np.cos(2 * np.radians(t) - azimuth)) * (1 - rings) + 0.5 * rings
             for t in (0, 45, 90, 135)]
    return np.repeat(np.stack(inten)[:, None], 3, 1).reshape(12, size, size).astype(np.float32)


def test_implausible_rotation_falls_back_to_identity():
    """A polarizing wheel's 45/135 deg images are 90 deg rotated copies of the 0 deg one: a camera
    array cannot be rotated that much, so those apertures get the identity and a warning, not a
    warp tens of pixels off."""
    size = 128
    h = np.stack([similarity(s) for s in SHIFTS])
    cap = simulate_capture(_polarizing_wheel(size), Sensor("none"), aperture_homographies=h, psf={"type": "none"})
    images, sat = cap.lr_images()
    res = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat)
    fallbacks = [a["fallback"] for a in res.diagnostics["apertures"]]
    assert "identity: implausible warp" in fallbacks, (fallbacks, res.diagnostics["warnings"])
    assert any("implausible for a camera array" in w for w in res.diagnostics["warnings"])
    for n, fb in enumerate(fallbacks):
        if fb == "identity: implausible warp":
            np.testing.assert_allclose(res.aperture_homographies[n], np.eye(3))
            assert abs(res.diagnostics["apertures"][n]["rejected"]["rotation_deg"]) > 5.0
    err = registration_error_hr_px(res.lr_homographies, cap.true_lr_homographies(), (size, size))
    assert np.max(err) < 3.0, err  # the identity is off by the true shifts only (<= 1.4 px)
    # the same data with a looser limit keeps the false match
    loose = estimate_lr_homographies(images, hr_shape=(size, size), saturated=sat,
                                     parameters=RegistrationParameters(max_rotation_deg=180.0, luminance="binomial"))
    assert "identity: implausible warp" not in [a["fallback"] for a in loose.diagnostics["apertures"]]
    assert np.max(registration_error_hr_px(loose.lr_homographies, cap.true_lr_homographies(), (size, size))) > 10


def test_plausibility_limits_are_checked():
    images = np.random.default_rng(0).random((16, 16, 16)).astype(np.float32)
    with pytest.raises(InputError, match="max_rotation_deg"):
        estimate_lr_homographies(images, hr_shape=(64, 64), parameters=RegistrationParameters(max_rotation_deg=-1.0))
    with pytest.raises(InputError, match="max_scale_error"):
        estimate_lr_homographies(images, hr_shape=(64, 64), parameters=RegistrationParameters(max_scale_error=1.5))


def test_auto_refines_the_demosaicked_image_from_the_binomial_warps(smooth_random_scene):
    """``auto`` judges the demosaicked image at the binomial warps and, when it is more Stokes-consistent
    there, refines it from them on the finest level: the same warps as registering it from scratch."""
    scene = smooth_random_scene(128, seed=0, dolp_max=0.6)
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(scene, h)
    auto = estimate_lr_homographies(images, hr_shape=(128, 128), saturated=sat, parameters=TRANSLATION)
    full = estimate_lr_homographies(images, hr_shape=(128, 128), saturated=sat,
                                    parameters=TRANSLATION.replace(luminance="ri-binomial"))
    rms = auto.diagnostics["luminance_stokes_residual_rms"]
    assert rms["ri-binomial at the binomial warps"] < rms["binomial"]
    assert auto.diagnostics["luminance"] == "ri-binomial"
    np.testing.assert_allclose(auto.aperture_homographies, full.aperture_homographies, atol=2e-3)


def test_auto_keeps_the_binomial_warps_without_a_second_registration(monkeypatch, smooth_random_scene):
    """When the demosaicked image is less Stokes-consistent at the binomial warps, it is not registered."""
    scene = smooth_random_scene(128, seed=0, dolp_max=0.6)
    h = np.stack([similarity(s) for s in SHIFTS])
    images, sat = _capture(scene, h)
    calls = []
    real = registration.register_stack
    monkeypatch.setattr(registration, "register_stack", lambda *a, **k: calls.append(k) or real(*a, **k))
    monkeypatch.setattr(registration, "stokes_residual_rms", lambda *a, **k: float("inf"))
    auto = estimate_lr_homographies(images, hr_shape=(128, 128), saturated=sat, parameters=TRANSLATION)
    binomial = estimate_lr_homographies(images, hr_shape=(128, 128), saturated=sat,
                                        parameters=TRANSLATION.replace(luminance="binomial"))
    assert len(calls) == 2 and "initial" not in calls[0]  # one registration each
    assert auto.diagnostics["luminance"] == "binomial"
    assert "ri-binomial" not in auto.diagnostics["luminance_stokes_residual_rms"]
    np.testing.assert_array_equal(auto.aperture_homographies, binomial.aperture_homographies)


def test_poor_and_implausible_matches_name_aliasing_as_well_as_polarization():
    """An unpolarized Siemens star too small for its cycles (72 on 96 HR px: it aliases in the 24 px Bayer
    sub-images) matches poorly or implausibly, like polarization texture does: the warnings name both causes."""
    diag, record = {"warnings": []}, {}
    registration._flag_match_quality(1, 0.2, {"stokes_rms_before": 0.01, "stokes_rms_after": 0.005}, 0.5, record, diag)
    assert record["stokes_rescued"]
    turn = np.deg2rad(10.0)
    rotated = np.array([[np.cos(turn), -np.sin(turn), 0.0], [np.sin(turn), np.cos(turn), 0.0], [0.0, 0.0, 1.0]])
    reg = core.StackRegistration(params=np.zeros((3, 4)), matrices=np.stack([rotated] * 3), correlation=np.ones(3))
    aperture, per_aperture = np.tile(np.eye(3), (4, 1, 1)), [{} for _ in range(4)]
    registration._accept_warps(reg, [1, 2, 3], RegistrationParameters(), aperture, per_aperture, diag)
    assert [a.get("fallback") for a in per_aperture[1:]] == ["identity: implausible warp"] * 3
    assert len(diag["warnings"]) == 4
    assert all("polarization texture" in w and "finer than the Bayer sub-images" in w for w in diag["warnings"])
