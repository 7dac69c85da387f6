"""eval.mtf: the sinusoidal Siemens-star MTF is exact on analytic stars and does not credit aliasing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from capssim.errors import InputError
from capssim.eval.mtf import find_star_center, measure_mtf, measure_star, sinusoidal_star

CYCLES = 36


@pytest.fixture(scope="module")
def blurred_stars():
    centre = (79.3, 80.6)
    return {sigma: sinusoidal_star((160, 160), CYCLES, center_rowcol=centre, blur_sigma=sigma, modulation=0.8,
                                   supersample=7) for sigma in (1.0, 1.5)}, centre


@pytest.mark.parametrize("sigma", [1.0, 1.5])
@pytest.mark.parametrize("given_reference", [True, False])
def test_gaussian_blur_mtf_matches_theory(blurred_stars, sigma, given_reference):
    stars, _ = blurred_stars
    ref = 0.8 if given_reference else None
    r = measure_mtf(stars[sigma], CYCLES, reference_modulation=ref)
    expected = np.exp(-2 * math.pi ** 2 * sigma ** 2 * r.frequency ** 2)
    for group in ("hv", "diagonal"):
        cred = r.credited[group]
        assert cred.sum() >= 20
        assert r.frequency[cred].max() > 0.25
        np.testing.assert_array_less(np.abs(r.mtf[group][cred] - expected[cred]), 0.02)
        limit_theory = math.sqrt(math.log(1 / 0.03) / (2 * math.pi ** 2 * sigma ** 2))
        assert r.limit[group] == pytest.approx(limit_theory, abs=0.01)
        assert r.limited_by[group] == "mtf"


def test_centre_is_found_to_a_small_fraction_of_a_pixel(blurred_stars):
    stars, centre = blurred_stars
    found = find_star_center(stars[1.0], cycles=CYCLES)
    assert np.hypot(found[0] - centre[0], found[1] - centre[1]) < 0.01
    # a bounded, off-centre, noisy star on a flat background
    img = sinusoidal_star((128, 128), 48, center_rowcol=(55.4, 70.7), radius=45, background=0.2, pixel_box=1.0,
                          blur_sigma=0.6, supersample=5)
    img = img + np.random.default_rng(0).normal(0, 0.02, img.shape)
    found = find_star_center(img, cycles=48)
    assert np.hypot(found[0] - 55.4, found[1] - 70.7) < 0.03
    r = measure_mtf(img, 48)
    assert r.radius_px == pytest.approx(45, abs=3)


@pytest.mark.parametrize("factor", [2, 4])
@pytest.mark.parametrize("cycles", [36, 72])
def test_bicubic_upsampling_is_not_credited_as_super_resolution(factor, cycles):
    import cv2

    lr_centre = (47.3, 48.1)
    lr = sinusoidal_star((96, 96), cycles, center_rowcol=lr_centre, pixel_box=1.0, blur_sigma=0.3, modulation=0.9,
                         supersample=5)
    up = cv2.resize(lr, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)
    centre = ((lr_centre[0] + 0.5) * factor - 0.5, (lr_centre[1] + 0.5) * factor - 0.5)  # cv2 pixel-centre mapping
    r = measure_mtf(up, cycles, center_rowcol=centre, reference_pitch=factor)
    assert r.magnification("hv") <= 1.05
    assert r.magnification("diagonal") <= 1.05
    # and with the automatic centre
    r_auto = measure_mtf(up, cycles, reference_pitch=factor)
    assert r_auto.magnification("hv") <= 1.05
    # the trap: without the residual stop the known-frequency fit would credit aliasing
    r_naive = measure_mtf(up, cycles, center_rowcol=centre, reference_pitch=factor, residual_limit=np.inf)
    assert r_naive.magnification("hv") > 1.2


def test_own_grid_never_credits_above_nyquist():
    img = sinusoidal_star((128, 128), 72, pixel_box=1.0, supersample=5)  # box pixel: MTF 0.64 at Nyquist
    r = measure_mtf(img, 72)
    for group in ("hv", "diagonal"):
        assert r.limit[group] <= 0.5
        assert r.limited_by[group] == "nyquist"
        assert r.magnification(group) <= 1.0
    assert measure_mtf(img, 72, reference_pitch=4).magnification("hv") == pytest.approx(4 * r.limit["hv"] / 0.5)


def test_noise_stops_the_measurement():
    img = sinusoidal_star((128, 128), 36, blur_sigma=1.0, modulation=0.5, supersample=5)
    noisy = img + np.random.default_rng(1).normal(0, 0.03, img.shape)
    r = measure_mtf(noisy, 36, reference_modulation=0.5)
    assert r.limited_by["hv"] == "residual"
    # the sinusoid's amplitude where it stopped is within a few noise stds
    stop = np.nonzero(~r.credited["hv"])[0][0]
    amplitude = r.mtf["hv"][stop] * 0.5 * 0.5
    assert amplitude < 4 * 0.03


def test_polarization_star_channels_and_mean():
    # four analyzer channels of a polarization star: same frequency, different phases
    angles = np.deg2rad([0, 45, 90, 135])
    chans = np.stack([sinusoidal_star((128, 128), 36, blur_sigma=1.0, phase_rad=-2 * a, supersample=5)
                      for a in angles])
    res = measure_star(chans, 36, names=["0", "45", "90", "135"]).results
    assert set(res) == {"0", "45", "90", "135", "mean"}
    lims = [res[k].limit["hv"] for k in ("0", "45", "90", "135")]
    assert np.ptp(lims) < 0.01
    assert res["mean"].limit["hv"] == pytest.approx(np.mean(lims), abs=0.01)
    d = res["mean"].to_dict()
    assert d["magnification"]["hv"] == pytest.approx(res["mean"].limit["hv"] / 0.5)


def test_bad_inputs():
    img = sinusoidal_star((64, 64), 36, supersample=3)
    with pytest.raises(InputError, match="cycles"):
        measure_mtf(img, 2)
    bad = img.copy()
    bad[3, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        measure_mtf(bad, 36)
    with pytest.raises(InputError, match="flat image"):
        measure_mtf(np.full((64, 64), 0.5), 36)
    with pytest.raises(InputError, match="center"):
        measure_mtf(img, 36, center_rowcol=(100, 5))
    with pytest.raises(InputError, match="one 2-D channel"):
        measure_mtf(np.stack([img, img]), 36)


def test_flat_or_dark_estimates_score_zero_not_nan():
    for value in (0.0, 0.5):
        flat = np.full((12, 96, 96), value)
        r = measure_star(flat, 24, center_rowcol=(48, 48), radius=44, reference_modulation=np.ones(12)).results["mean"]
        assert r.limit == {"hv": 0.0, "diagonal": 0.0}
        assert r.limited_by["hv"] in ("residual", "mtf")
    with pytest.raises(InputError, match="Siemens star"):
        measure_star(np.full((96, 96), 0.5), 24, center_rowcol=(48, 48))
