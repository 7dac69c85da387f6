"""Scores of a reconstruction's error bars (capssim.eval.uncertainty_scores) and their place in
``capssim evaluate``: coverage of the 90 % intervals, interval width, AUSE (Ilg et al. 2018), the AoP
wrap-around, the metrics' crop and masks, clear errors, metrics.json and the printed line."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture, write_reconstruction
from capssim.cli import app
from capssim.errors import InputError
from capssim.eval.evaluate import evaluate_capture
from capssim.eval.synthetic import synthetic_scene
from capssim.eval.uncertainty_scores import SPARSIFICATION_FRACTIONS, score_uncertainty, sparsification
from capssim.reconstruct.uncertainty.maps import UncertaintyMaps, stokes_plane
from capssim.simulate import simulate_capture
from capssim.stokes.polarization import stokes_from_12, twelve_from_stokes

Z90 = 1.6448536269514722  # the standard normal's 95th percentile: +-Z90 std holds 90 %


def _gaussian_case(size: int, *, seed: int = 0, border_junk: int = 0):
    """``(estimate, gt, std)``: ``gt = estimate - noise`` with ``noise ~ N(0, std)``, std varying per value;
    the outer ``border_junk`` pixels get a 100x larger error (the crop must drop them)."""
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0.2, 0.8, (12, size, size))
    std = rng.uniform(0.005, 0.03, gt.shape)
    estimate = gt + rng.standard_normal(gt.shape) * std
    if border_junk:
        ring = np.ones((size, size), dtype=bool)
        ring[border_junk:-border_junk, border_junk:-border_junk] = False
        estimate[:, ring] = gt[:, ring] + 100 * std[:, ring]
    return estimate, gt, std


def _maps(estimate: np.ndarray, std: np.ndarray, z: float = Z90) -> UncertaintyMaps:
    """Error bars of a Gaussian case: ``estimate +- z std`` per channel; S0's std propagated from the four
    polarizer channels (S0 = sum / 2); DoLP [0, 1] and AoP [0, 180] (always inside) with constant std."""
    stokes = np.zeros((27, *estimate.shape[1:]))
    s0 = stokes_from_12(estimate)[0]
    for k in range(3):
        s0_std = 0.5 * np.sqrt(sum(std[3 * p + k] ** 2 for p in range(4)))
        stokes[stokes_plane("S0", "std", k)] = s0_std
        stokes[stokes_plane("S0", "lower", k)] = s0[k] - z * s0_std
        stokes[stokes_plane("S0", "upper", k)] = s0[k] + z * s0_std
        stokes[stokes_plane("DoLP", "std", k)], stokes[stokes_plane("DoLP", "upper", k)] = 0.1, 1.0
        stokes[stokes_plane("AoP", "std", k)], stokes[stokes_plane("AoP", "upper", k)] = 10.0, 180.0
    return UncertaintyMaps(std, np.stack([estimate - z * std, estimate + z * std]), stokes)


def _binomial_tolerance(p: float, n: int) -> float:
    """Four binomial standard deviations of a coverage ``p`` measured on ``n`` independent values."""
    return 4 * math.sqrt(p * (1 - p) / n)


@pytest.mark.parametrize("z, expected", [(Z90, 0.90), (1.0, 0.6826894921370859)])
def test_coverage_of_gaussian_errors_is_the_intervals_probability(z, expected):
    estimate, gt, std = _gaussian_case(80, border_junk=8)
    scores = score_uncertainty(estimate, gt, _maps(estimate, std, z))  # capssim: 8 px crop drops the junk
    g12, s0 = scores.groups["12ch"], scores.groups["S0"]
    assert g12.scored == 12 * 64 * 64 and s0.scored == 3 * 64 * 64
    assert g12.coverage == pytest.approx(expected, abs=_binomial_tolerance(expected, g12.scored))
    assert s0.coverage == pytest.approx(expected, abs=_binomial_tolerance(expected, s0.scored))
    assert g12.mean_width == pytest.approx(2 * z * std[:, 8:-8, 8:-8].mean(), rel=1e-5)
    assert scores.groups["DoLP"].coverage == 1.0 and scores.groups["AoP"].mean_width == pytest.approx(180.0)
    assert scores.settings == {"convention": "capssim", "border": 8, "min_s0": 0.02, "min_dolp": 0.05}
    without_crop = score_uncertainty(estimate, gt, _maps(estimate, std, z), border=0)
    assert without_crop.groups["12ch"].coverage < expected - 0.15  # the junk ring, outside every interval


def _polarized_gt(aop_deg: float, *, size: int = 12, dolp: float = 0.5) -> np.ndarray:
    """A uniform ``(12, size, size)`` ground truth with S0 = 1, the given DoLP and AoP in every colour."""
    stokes = np.zeros((3, 3, size, size))
    stokes[0] = 1.0
    stokes[1] = dolp * np.cos(np.radians(2 * aop_deg))
    stokes[2] = dolp * np.sin(np.radians(2 * aop_deg))
    return twelve_from_stokes(stokes)


def _aop_interval_maps(size: int, lower: float, upper: float) -> UncertaintyMaps:
    """Error bars whose AoP interval is ``[lower, upper]`` degrees everywhere (the rest wide)."""
    stokes = np.zeros((27, size, size))
    for k in range(3):
        stokes[stokes_plane("S0", "upper", k)], stokes[stokes_plane("DoLP", "upper", k)] = 2.0, 1.0
        stokes[stokes_plane("AoP", "std", k)] = (upper - lower) / (2 * Z90)
        stokes[stokes_plane("AoP", "lower", k)], stokes[stokes_plane("AoP", "upper", k)] = lower, upper
    std = np.full((12, size, size), 0.01)
    return UncertaintyMaps(std, np.stack([np.zeros_like(std), np.ones_like(std)]), stokes)


@pytest.mark.parametrize("truth_deg, covered", [(179.0, True), (1.0, True), (0.0, True), (90.0, False),
                                                (165.0, False), (15.0, False)])
def test_aop_interval_crossing_0_180_covers_angles_on_both_sides_only(truth_deg, covered):
    gt = _polarized_gt(truth_deg)
    maps = _aop_interval_maps(12, 170.0, 190.0)  # 170 .. 180 = 0 .. 10 degrees
    aop = score_uncertainty(gt.copy(), gt, maps, border=0).groups["AoP"]
    assert aop.scored == 3 * 12 * 12
    assert aop.coverage == (1.0 if covered else 0.0)
    assert aop.mean_width == pytest.approx(20.0)


def test_aop_is_scored_on_the_metrics_mask_only():
    gt = _polarized_gt(90.0)
    gt[:, :, :6] = _polarized_gt(179.0, dolp=0.01)[:, :, :6]  # below min_dolp = 0.05: not scored
    gt[:, :3, 6:] = _polarized_gt(179.0)[:, :3, 6:] * 0.01  # S0 = 0.01 <= min_s0 = 0.02: not scored
    maps = _aop_interval_maps(12, 170.0, 190.0)
    scores = score_uncertainty(gt.copy(), gt, maps, border=0)
    assert scores.groups["AoP"].scored == 3 * 9 * 6 and scores.groups["AoP"].coverage == 0.0  # 90 deg: outside
    assert scores.groups["DoLP"].scored == 3 * (12 * 12 - 3 * 6)  # DoLP: the S0 condition only
    assert scores.groups["S0"].scored == 3 * 12 * 12
    assert score_uncertainty(gt.copy(), gt, maps, border=0, min_dolp=0.0).groups["AoP"].scored == 3 * (144 - 18)


def _reference_curve(abs_error: np.ndarray, key: np.ndarray, fractions) -> np.ndarray:
    """RMSE of what is left after removing each fraction with the largest ``key``, the slow way."""
    order = np.argsort(-key, kind="stable")
    out = []
    for f in fractions:
        left = order[int(math.floor(f * key.size + 1e-9)):]
        out.append(math.sqrt(float(np.mean(abs_error[left] ** 2))))
    return np.asarray(out) / out[0]


def test_sparsification_matches_a_loop_and_its_area():
    rng = np.random.default_rng(3)
    err = np.abs(rng.standard_normal(537))
    std = err * rng.uniform(0.5, 1.5, err.size)  # a noisy ranking
    sp = sparsification(err, std)
    assert sp.fractions.shape == (100,) and sp.fractions[0] == 0 and sp.fractions[-1] == pytest.approx(0.99)
    np.testing.assert_allclose(sp.curve, _reference_curve(err, std, SPARSIFICATION_FRACTIONS), rtol=1e-12)
    np.testing.assert_allclose(sp.oracle, _reference_curve(err, err, SPARSIFICATION_FRACTIONS), rtol=1e-12)
    assert sp.ause == pytest.approx(np.trapezoid(sp.curve - sp.oracle, SPARSIFICATION_FRACTIONS), rel=1e-12)
    assert np.all(np.diff(sp.oracle) <= 1e-12)  # removing the largest errors first never raises the RMSE
    worst = sparsification([1.0, 2.0, 3.0, 4.0], [4.0, 3.0, 2.0, 1.0], fractions=[0, 0.25, 0.5, 0.75])
    rmse = math.sqrt(7.5)
    np.testing.assert_allclose(worst.curve, np.array([rmse, math.sqrt(29 / 3), math.sqrt(12.5), 4.0]) / rmse)
    np.testing.assert_allclose(worst.oracle, np.array([rmse, math.sqrt(14 / 3), math.sqrt(2.5), 1.0]) / rmse)


def test_ause_is_zero_for_std_proportional_to_the_error_and_large_for_random_std():
    estimate, gt, _ = _gaussian_case(48)
    error = np.abs(estimate - gt)
    ranked = score_uncertainty(estimate, gt, _maps(estimate, 3.0 * error), border=0).groups["12ch"]
    assert abs(ranked.ause) < 1e-9
    np.testing.assert_allclose(ranked.sparsification.curve, ranked.sparsification.oracle, atol=1e-12)
    random_std = np.random.default_rng(9).uniform(0.005, 0.03, gt.shape)
    unranked = score_uncertainty(estimate, gt, _maps(estimate, random_std), border=0).groups["12ch"]
    # std unrelated to the errors: the curve stays near 1 while the oracle falls; the area is about 0.4 or more
    assert unranked.ause > 0.3
    assert sparsification([0.0, 0.0], [1.0, 2.0]) is None  # no error at all: the normalization is undefined


def test_mismatched_and_non_finite_inputs_are_clear_errors():
    estimate, gt, std = _gaussian_case(32)
    maps = _maps(estimate, std)
    with pytest.raises(InputError, match="the estimate's grid"):
        score_uncertainty(estimate[:, :16, :16], gt[:, :16, :16], maps)
    with pytest.raises(InputError, match="ground-truth shape"):
        score_uncertainty(estimate[:, :16], gt, maps)
    bad = estimate.copy()
    bad[3, 20, 20] = np.inf
    with pytest.raises(InputError, match="NaN/inf"):
        score_uncertainty(bad, gt, maps)
    with pytest.raises(InputError, match="UncertaintyMaps"):
        score_uncertainty(estimate, gt, {"std": std})
    nan_std = _maps(estimate, std)
    nan_std.std[0, 16, 16] = np.nan
    with pytest.raises(InputError, match=r"METHOD\.std\.tiff \(12ch std\).*1 NaN/inf"):
        score_uncertainty(estimate, gt, nan_std)
    nan_std.std[0, 16, 16] = 0.01
    nan_std.std[0, 0, 0] = np.nan  # in the border crop: never scored
    assert score_uncertainty(estimate, gt, nan_std).groups["12ch"].scored == 12 * 16 * 16
    flipped = _maps(estimate, std)
    flipped.stokes[stokes_plane("S0", "lower", 1)] += 1.0
    with pytest.raises(InputError, match="S0 interval"):
        score_uncertainty(estimate, gt, flipped)
    with pytest.raises(InputError, match="border"):
        score_uncertainty(estimate, gt, maps, border=16)


@pytest.fixture
def capture_with_error_bars(tmp_path) -> Path:
    """A 64 px simulated capture with ``recon/m`` (error bars, calibrated +-Z90 std) and ``recon/plain``."""
    gt, scene = synthetic_scene("texture", size=64)
    write_capture(tmp_path / "cap", simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=1,
                                                     extra_meta={"scene": {"name": "texture", **scene}}))
    rng = np.random.default_rng(5)
    std = rng.uniform(0.005, 0.02, gt.shape)
    estimate = (gt + rng.standard_normal(gt.shape) * std).astype(np.float32)
    maps = _maps(estimate.astype(np.float64), std)
    record = {"wall_time_s": 2.0, "stages_s": {}, "uncertainty": {"replicates": 8, "calibration": "conformal-test"}}
    write_reconstruction(tmp_path / "cap", "m", estimate, record, companions=maps.arrays())
    write_reconstruction(tmp_path / "cap", "plain", estimate, {"wall_time_s": 1.0, "stages_s": {}})
    return tmp_path / "cap"


def test_evaluate_adds_the_uncertainty_block_to_methods_with_error_bars(capture_with_error_bars):
    result = evaluate_capture(capture_with_error_bars, with_mtf=False)
    assert "uncertainty" not in result["methods"]["plain"] and "metrics" in result["methods"]["plain"]
    block = json.loads((capture_with_error_bars / "metrics.json").read_text())["methods"]["m"]["uncertainty"]
    assert block["nominal_coverage"] == 0.9 and block["calibration"] == "conformal-test" and block["replicates"] == 8
    assert list(block["groups"]) == ["12ch", "S0", "DoLP", "AoP"] and block["notes"] == []
    g12 = block["groups"]["12ch"]
    assert g12["scored"] == 12 * 48 * 48
    assert g12["coverage"] == pytest.approx(0.9, abs=_binomial_tolerance(0.9, g12["scored"]))
    assert g12["width_unit"] == "full scale [0, 1]" and len(g12["sparsification"]) == len(block["fractions"]) == 100
    assert 0 < g12["ause"] < 0.6 and block["groups"]["AoP"]["width_unit"] == "degrees"
    assert "plots" not in block


def test_evaluate_draws_the_error_bar_plots_of_methods_with_error_bars(capture_with_error_bars, tmp_path):
    result = evaluate_capture(capture_with_error_bars, methods=["m", "plain"], with_mtf=False, write=False,
                              plot_dir=tmp_path / "plots")
    names = sorted(Path(p).name for p in result["methods"]["m"]["uncertainty"]["plots"])
    assert names == ["m.dolp-aop.png", "m.s0-std.png", "m.sparsification.png"]
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == names  # nothing for "plain"
    assert all((tmp_path / "plots" / n).read_bytes()[:4] == b"\x89PNG" for n in names)


def test_evaluate_prints_one_line_and_flags_stale_or_broken_error_bars(capture_with_error_bars, tmp_path):
    r = CliRunner().invoke(app, ["evaluate", str(capture_with_error_bars), "--no-mtf", "--threads", "1"])
    assert r.exit_code == 0, r.output
    line = next(x for x in r.output.splitlines() if re.match(r"m: 90 % intervals cover 12ch 0\.(89|90|91), S0 ", x))
    assert "AUSE 12ch 0." in line and "(calibration conformal-test)" in line
    assert not any(x.startswith("plain:") for x in r.output.splitlines())
    record = capture_with_error_bars / "recon" / "m.json"
    record.write_text(json.dumps({"wall_time_s": 2.0}))  # a record without the block: the files may be stale
    block = evaluate_capture(capture_with_error_bars, methods=["m"], with_mtf=False)["methods"]["m"]["uncertainty"]
    assert block["calibration"] is None and "no 'uncertainty' block" in block["notes"][0]
    (capture_with_error_bars / "recon" / "m.interval90.tiff").unlink()
    r = CliRunner().invoke(app, ["evaluate", str(capture_with_error_bars), "--no-mtf", "-m", "m", "--threads", "1",
                                 "--plots", str(tmp_path / "plots")])
    assert r.exit_code == 1 and "m: error bars not scored" in r.output and "m.interval90.tiff missing" in r.output
    assert "metrics" in json.loads((capture_with_error_bars / "metrics.json").read_text())["methods"]["m"]
