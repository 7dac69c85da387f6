"""Registration: the ``fast`` mode (binomial luminance, warps fitted at half resolution on large frames) and the
registration mode a method uses when a run names none (``array-kr``: ``fast``; every other method: the default).
"""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import capssim.reconstruct.registration.estimate as registration
from capssim.camera.homography import registration_error_hr_px, similarity
from capssim.camera.sensor import Sensor, make_sensor
from capssim.errors import InputError
from capssim.eval.benchmarks.suite_schema import MethodEntrySpec
from capssim.reconstruct import reconstruct
from capssim.reconstruct.registration import estimate_lr_homographies, registration_parameters
from capssim.reconstruct.registration.parameters import RegistrationParameters
from capssim.reconstruct.registry import DEFAULT_REGISTRATION, default_registration
from capssim.simulate import simulate_capture

SHIFTS = [(0.0, 0.0), (0.8, -0.6), (-1.1, 0.4), (0.5, 1.2)]


def _capture(size: int, *, sensor=None, seed: int = 3):
    """A smooth colour scene (no polarization) seen through :data:`SHIFTS` and a 0.3 deg rotation."""
    rng = np.random.default_rng(seed)
    colours = [gaussian_filter(rng.random((size, size)), 3.0) for _ in range(3)]
    rgb = np.stack([0.2 + 0.6 * (c - c.min()) / np.ptp(c) for c in colours])
    scene = np.tile(rgb, (4, 1, 1)).astype(np.float32)
    centre = (size / 2, size / 2)
    homographies = np.stack([similarity(s, rotation_deg=0.3 * (n > 0), center_xy=centre) for n, s in enumerate(SHIFTS)])
    return simulate_capture(scene, sensor or Sensor("none"), aperture_homographies=homographies,
                            psf={"type": "none"}, seed=seed)


@pytest.fixture
def finest_levels(monkeypatch):
    """The finest pyramid level of every engine run (``info["finest_level"]``)."""
    real, levels = registration.register_stack, []

    def engine(ref, moving, **kwargs):
        result = real(ref, moving, **kwargs)
        levels.append(result.info["finest_level"])
        return result

    monkeypatch.setattr(registration, "register_stack", engine)
    return levels


def _register(capture, mode):
    images, saturated = capture.lr_images()
    result = estimate_lr_homographies(images, hr_shape=capture.hr_shape, saturated=saturated,
                                      parameters=registration_parameters(mode))
    return result, registration_error_hr_px(result.lr_homographies, capture.true_lr_homographies(), capture.hr_shape)


def test_fast_fits_a_512_frame_at_half_resolution_to_a_tenth_of_a_pixel(finest_levels):
    capture = _capture(512, sensor=make_sensor("gaussian", sigma=0.01))
    _, err = _register(capture, "fast")
    assert finest_levels and set(finest_levels) == {1}
    assert np.median(err) < 0.05 and np.max(err) < 0.1, err


def test_fast_on_a_small_frame_is_the_binomial_registration(finest_levels):
    capture = _capture(128)
    fast, _ = _register(capture, "fast")
    assert set(finest_levels) == {0}  # its half-resolution level (32 px) is below 128 px: full resolution
    binomial, _ = _register(capture, "binomial-luminance")
    np.testing.assert_array_equal(fast.aperture_homographies, binomial.aperture_homographies)


@pytest.mark.parametrize("value", [-1, 2.5, True, "128"])
def test_a_bad_half_resolution_size_is_refused_naming_it(value):
    with pytest.raises(InputError, match="half_resolution_min_size"):
        RegistrationParameters(half_resolution_min_size=value).validate()


def test_array_kr_registers_with_fast_unless_the_run_names_a_mode():
    capture = _capture(64)
    assert default_registration("array-kr") == "fast" and default_registration("caps-naive") == DEFAULT_REGISTRATION
    assert default_registration("no-such-method") == DEFAULT_REGISTRATION
    _, record = reconstruct(capture, "array-kr", reuse_registration=False)
    assert record["registration"]["mode"] == "fast"
    _, record = reconstruct(capture, "array-kr", registration="local-correlation", reuse_registration=False)
    assert record["registration"]["mode"] == "local-correlation"
    _, record = reconstruct(capture, "caps-naive", reuse_registration=False)
    assert record["registration"]["mode"] == DEFAULT_REGISTRATION


def test_a_suite_entry_takes_the_methods_own_registration():
    spec = MethodEntrySpec()
    assert spec.check("array-kr", "methods[0]")["registration"] == "fast"
    assert spec.check({"name": "caps"}, "methods[1]")["registration"] == DEFAULT_REGISTRATION
    given = spec.check({"name": "array-kr", "registration": "local-correlation"}, "methods[2]")
    assert given["registration"] == "local-correlation"



def _restart_problem(finest: int):
    """Three noisy shifted copies of a smooth 128 px texture, their :class:`LevelCriteria` (fitted down to level
    ``finest``) and the right warps, found from the identity."""
    import torch
    from scipy.ndimage import shift as nd_shift

    from capssim.reconstruct.registration.criterion import minimize
    from capssim.reconstruct.registration.levels import LevelCriteria

    rng = np.random.default_rng(5)
    base = gaussian_filter(rng.random((128, 128)), 2.0)
    base = (base - base.mean()) / base.std()
    moving = np.stack([nd_shift(base, s, order=3, mode="nearest") for s in ((0.7, -0.4), (-1.1, 0.5), (0.3, 1.2))])
    ref, mov = torch.as_tensor(base), torch.as_tensor(moving + rng.normal(0.0, 0.6, moving.shape))
    criteria = LevelCriteria(ref, mov, torch.ones_like(ref), torch.ones_like(mov), model="similarity",
                             window_radius=3, border=3, levels=3, finest=finest)
    right, _, _ = minimize(criteria(0, 0.0), torch.zeros(3, 4, dtype=torch.float64), max_iterations=60)
    return ref, mov, criteria, right


@pytest.mark.parametrize("finest", [0, 1])
def test_in_fast_mode_the_restart_refines_at_full_resolution_only_what_can_gain(finest, monkeypatch):
    """Every image is restarted (threshold 0.9). From the right warps no start beats them: the fast mode (finest
    level 1) then refines nothing at full resolution, the default still refines each image's best start; from a
    wrong basin for image 0 both modes refine it and keep the restart."""
    import capssim.reconstruct.registration.rescue as rescue

    ref, mov, criteria, right = _restart_problem(finest)
    wrong = right.clone()
    wrong[0, :2] += 7.0
    real, sizes = rescue.minimize, []

    def counted(crit, p, **kwargs):
        sizes.append(tuple(crit.shape))
        return real(crit, p, **kwargs)

    monkeypatch.setattr(rescue, "minimize", counted)
    for start in (right, wrong):
        sizes.clear()
        info: dict = {}
        out = rescue.rescue_from_more_peaks(start, ref, mov, criteria, threshold=0.9, peaks=4, max_iterations=60,
                                            info=info)
        record, full = info["rescue"], sizes.count((128, 128))
        assert max(record["r2_before"]) < 0.9  # all three restarted
        if start is wrong:
            assert record["rescued"] == [0] and full == 1
            assert finest == 0 or record["promising"] == [0]
        elif finest:
            assert record["promising"] == [] and record["rescued"] == [] and full == 0 and bool((out == start).all())
        else:
            assert "promising" not in record and record["rescued"] == [] and full == 1
