"""Error bars of ``--uncertainty``: the bootstrap against a closed form, the intervals, the files, the refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from support.fuzz import refused_before_work, small_gaussian_capture

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import list_reconstructions, read_capture, write_capture
from capssim.errors import InputError
from capssim.reconstruct.registry import reconstruct, run_method
from capssim.reconstruct.uncertainty.bootstrap import (
    BootstrapMoments,
    bootstrap_moments,
    check_replicates,
    grid_transforms,
    replicate_statistics,
)
from capssim.reconstruct.uncertainty.conformal import Z90, calibration_scales, conformal_quantile, noise_key
from capssim.reconstruct.uncertainty.intervals import bootstrap_spreads, uncertainty_maps
from capssim.reconstruct.uncertainty.maps import aop_inside, read_uncertainty, stokes_plane
from capssim.simulate import simulate_capture


def test_bootstrap_of_tikhonov_least_squares_matches_its_closed_form_covariance():
    """x_hat = (A'A + lam I)^-1 A' y with y = A x + n, n ~ N(0, s^2 I): the parametric bootstrap's spread is the
    estimator's, Cov = (A'A + lam I)^-1 A' (s^2 I) A (A'A + lam I)^-1, whatever x_hat it starts from."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(40, 12))
    lam, sigma = 0.5, 0.2
    normal = a.T @ a + lam * np.eye(12)
    solve = np.linalg.solve
    y = a @ rng.normal(size=12) + sigma * rng.normal(size=40)
    x_hat = solve(normal, a.T @ y)
    moments = bootstrap_moments(x_hat, lambda x, r: a @ x + sigma * r.normal(size=40),
                                lambda data, start, i: solve(normal, a.T @ data), replicates=3000, seed=1)
    inverse = np.linalg.inv(normal)
    closed = np.sqrt(np.diag(inverse @ a.T @ (sigma**2 * np.eye(40)) @ a @ inverse))
    assert np.max(np.abs(moments.std("x") / closed - 1)) < 0.10
    # the replicates' mean is the estimator applied to A x_hat (its bias, the shrinkage, seen once more), not x_hat
    assert np.allclose(moments.mean("x"), inverse @ a.T @ a @ x_hat, atol=4 * closed.max() / np.sqrt(3000))


def test_moments_are_the_sample_mean_and_std():
    samples = np.random.default_rng(0).normal(size=(7, 3))
    moments = BootstrapMoments()
    for s in samples:
        moments.add({"v": s})
    assert np.allclose(moments.mean("v"), samples.mean(axis=0))
    assert np.allclose(moments.std("v"), samples.std(axis=0, ddof=1))


def test_equivariant_moves_are_undone():
    x = np.random.default_rng(0).random((12, 16, 20))
    for seed in range(6):
        forward, backward = grid_transforms(np.random.default_rng(seed))
        assert np.array_equal(backward(forward(x)), x)


def test_conformal_quantile_is_the_finite_sample_rank():
    scores = np.arange(1, 11, dtype=float)  # n = 10: rank ceil(11 * 0.9) = 10
    assert conformal_quantile(scores) == 10.0
    assert conformal_quantile(np.arange(1, 101, dtype=float)) == 91.0  # ceil(101 * 0.9) = 91
    assert conformal_quantile(np.ones(20)) == 1.0 and conformal_quantile([]) == np.inf
    assert conformal_quantile(np.ones(5)) == np.inf  # rank ceil(6 * 0.9) = 6 > n: no finite scale covers 90 %


def test_aop_interval_wraps_around_180_degrees():
    lower, upper = stokes_plane("AoP", "lower", 0), stokes_plane("AoP", "upper", 0)
    assert (lower, upper) == (21, 24)
    assert aop_inside(179.0, 170.0, 190.0) and aop_inside(5.0, 170.0, 190.0) and not aop_inside(90.0, 170.0, 190.0)
    assert aop_inside(90.0, 10.0, 190.0)  # the whole half-circle


def _moments_of(images):
    moments = BootstrapMoments()
    for image in images:
        moments.add(replicate_statistics(image))
    return moments


def test_intervals_scale_with_the_calibration_and_wrap_the_aop():
    rng = np.random.default_rng(1)
    estimate = (0.3 + 0.2 * rng.random((12, 8, 8))).astype(np.float32)
    replicates = [estimate + 0.01 * rng.normal(size=estimate.shape) for _ in range(6)]
    spreads = bootstrap_spreads(_moments_of(replicates))
    raw = uncertainty_maps(estimate, spreads, {g: Z90 for g in spreads})
    wide = uncertainty_maps(estimate, spreads, {g: 2 * Z90 for g in spreads})
    half_raw = raw.interval90[1] - estimate
    assert np.allclose(half_raw, Z90 * np.maximum(spreads["12ch"], 1e-4), rtol=1e-5)
    assert np.allclose(raw.std, np.maximum(spreads["12ch"], 1e-4), rtol=1e-5)
    assert np.allclose(wide.interval90[1] - estimate, 2 * half_raw, rtol=1e-5)
    lower, upper = wide.stokes[stokes_plane("AoP", "lower", 1)], wide.stokes[stokes_plane("AoP", "upper", 1)]
    assert np.all((lower >= 0) & (lower < 180)) and np.all((upper - lower >= 0) & (upper - lower <= 180 + 1e-4))
    assert np.all(wide.stokes[stokes_plane("DoLP", "upper", 2)] <= 1.0)


def test_noise_keys_name_the_sensor_level():
    assert noise_key(make_sensor("gaussian", sigma=0.01)) == "gaussian-0.01"
    assert noise_key(make_sensor("poisson-gaussian", preset="imx250myr")) == "poisson-gaussian-imx250myr"
    assert noise_key(make_sensor("none")) is None
    scales, record = calibration_scales("no-such-method", make_sensor("gaussian", sigma=0.01))
    assert record["name"] == "none" and set(scales.values()) == {Z90}


@pytest.mark.parametrize("bad", [1, 0, 2.5, "x", 10_000])
def test_a_bad_replicate_count_is_refused(bad):
    with pytest.raises(InputError, match="--uncertainty"):
        check_replicates(bad)


def test_uncertainty_files_of_a_dofp_method_and_a_warm_started_caps(tmp_path):
    folder = small_gaussian_capture(tmp_path / "cap")
    record = run_method(folder, "dofp-bilinear", uncertainty=3)
    maps = read_uncertainty(folder, "dofp-bilinear")
    assert maps.std.shape == (12, 32, 32) and maps.interval90.shape == (2, 12, 32, 32)
    assert maps.stokes.shape == (27, 32, 32) and np.all(maps.std > 0)
    assert record["uncertainty"]["replicates"] == 3 and "name" in record["uncertainty"]["calibration"]
    assert len(record["uncertainty"]["stokes_layout"]) == 27
    assert list_reconstructions(folder) == ["dofp-bilinear"]  # the companions are no reconstructions
    capture = read_capture(folder)
    out, rec = reconstruct(capture, "caps", true_warps=True, iterations=3, uncertainty=2,
                           uncertainty_options={"warm_iterations": 1, "calibration": "none"})
    assert rec["uncertainty"]["replicate_options"]["iterations"] == 1
    assert rec["uncertainty"]["calibration"]["name"] == "none"
    image = out.image
    assert np.all(out.uncertainty.interval90[0] <= image + 1e-6) and np.all(out.uncertainty.interval90[1] >= image)


def test_a_noise_free_capture_or_a_tiled_run_is_refused_before_work(tmp_path, capsys, monkeypatch):
    gt = np.full((12, 32, 32), 0.4, dtype=np.float32)
    write_capture(tmp_path / "clean", simulate_capture(gt, make_sensor("none"), seed=0))
    line = refused_before_work(["reconstruct", "{root}/clean", "-m", "dofp-bilinear", "--uncertainty", "4"],
                               tmp_path, capsys, monkeypatch, fragments=("--uncertainty", "noise model"),
                               forbid="capssim.reconstruct.registry:run_method")
    assert "Traceback" not in line
    small_gaussian_capture(tmp_path / "cap")
    refused_before_work(["reconstruct", "{root}/cap", "-m", "caps", "--uncertainty", "4", "--tile", "64"],
                        tmp_path, capsys, monkeypatch, fragments=("--uncertainty", "untiled"),
                        forbid="capssim.reconstruct.registry:run_method")
    refused_before_work(["reconstruct", "{root}/cap", "-m", "caps", "--uncertainty", "1"], tmp_path, capsys,
                        monkeypatch, fragments=("--uncertainty", "at least 2"))
    assert not (tmp_path / "cap" / "recon").exists()
    meta = json.loads((tmp_path / "cap" / "meta.json").read_text())
    assert meta["sensor"]["model"] == "gaussian"


def test_a_suite_that_asks_for_uncertainty_scores_the_error_bars(tmp_path):
    from typer.testing import CliRunner

    from capssim.cli import app

    suite = tmp_path / "bars.yaml"
    suite.write_text("name: bars\nrole: development\nuncertainty: 3\nnoise: [{name: g, noise: gaussian, sigma: 0.01}]\n"
                     "methods: [dofp-bilinear, {name: dofp-igri2, uncertainty: 2}]\n"
                     "scenes: [{name: tex, source: synthetic, generator: texture, size: 48}]\n")
    result = CliRunner().invoke(app, ["bench", "suite", str(suite), "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    records = [json.loads(line) for line in (tmp_path / "out" / "results.jsonl").read_text().splitlines()]
    by_method = {r["method"]: r for r in records}
    assert by_method["dofp-bilinear"]["uncertainty"]["replicates"] == 3
    assert by_method["dofp-igri2"]["uncertainty"]["replicates"] == 2  # a method's own count wins
    coverage = by_method["dofp-bilinear"]["uncertainty"]["groups"]["12ch"]["coverage"]
    assert 0.0 < coverage <= 1.0
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Error bars" in report and "| dofp-igri2 | 1 |" in report
    assert (tmp_path / "out" / "plots" / "bars_tex_g_dofp-igri2.png").is_file()  # DoLP and AoP with their bars


def test_caps_plus_warm_start_keeps_the_replicates_own_polarization_part():
    """caps-plus's data direction leaves the polarization part where the analyzers disagree as its start made it:
    a warm-started replicate takes the warm image's analyzer mean and draws its polarization part from its own data."""
    import torch

    from capssim.reconstruct.methods.caps_plus import warm_start
    from capssim.reconstruct.model.polarization_split import angle_mean
    from capssim.reconstruct.run_context import RunContext, StageTimer

    rng = np.random.default_rng(0)
    warm = (0.4 + 0.1 * rng.random((12, 8, 8))).astype(np.float32)
    own = torch.as_tensor(0.4 + 0.1 * rng.random((12, 8, 8)), dtype=torch.float32)
    cpu = torch.device("cpu")
    start = warm_start(RunContext(device=cpu, timer=StageTimer(cpu), start=warm), own)
    assert torch.allclose(angle_mean(start), angle_mean(torch.as_tensor(warm)), atol=1e-6)
    assert torch.allclose(start - angle_mean(start), own - angle_mean(own), atol=1e-6)


def test_the_command_writes_the_error_bars_beside_the_reconstruction(tmp_path):
    from typer.testing import CliRunner

    from capssim.cli import app

    folder = small_gaussian_capture(tmp_path / "cap")
    result = CliRunner().invoke(app, ["reconstruct", str(folder), "-m", "dofp-bilinear", "--uncertainty", "3",
                                      "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "error bars: 3 replicates" in result.output
    maps = read_uncertainty(folder, "dofp-bilinear")
    assert maps is not None and maps.interval90.shape == (2, 12, 32, 32)
    again = CliRunner().invoke(app, ["reconstruct", str(folder), "-m", "dofp-bilinear", "--no-progress"])
    assert again.exit_code == 0, again.output
    assert read_uncertainty(folder, "dofp-bilinear") is None  # a run without error bars leaves no stale ones
