"""Real rigs: calibration captures, each estimator on ground truth by construction, the round trip
simulate -> calibrate -> reconstruct, and malformed calibration input."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from capssim.camera.homography import registration_error_hr_px
from capssim.camera.rig import RigModel, write_rig_json
from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_capture, write_capture
from capssim.dataset.calibration_captures import make_calibration_captures, polarized_field, sweep_angles
from capssim.errors import InputError
from capssim.eval.metrics import score
from capssim.reconstruct import reconstruct
from capssim.reconstruct.calibration import calibrate_captures
from capssim.reconstruct.calibration.flat_field import fit_flat_field
from capssim.reconstruct.calibration.malus import fit_malus
from capssim.reconstruct.calibration.psf_fit import lanczos_warp
from capssim.reconstruct.model.data_term import ConfidenceDataTerm
from capssim.reconstruct.model.rearrange import rearrange_raw
from capssim.simulate import simulate_capture

SIZE = 128


@pytest.fixture(scope="module")
def rig() -> RigModel:
    """The issue's hardest case: angle errors up to 2 deg, ER 30-300 per colour, gains +-5 %, 20 % vignetting."""
    return RigModel.preset("realistic", seed=3).with_overrides(
        angle_offsets_deg=[2.0, -1.6, 0.9, -2.0], extinction_ratio=[300, 120, 30, 250, 80, 40, 60, 300, 35,
                                                                    100, 200, 30],
        gain=[1.05, 0.95, 1.0, 1.03])


@pytest.fixture(scope="module")
def calibration_set(tmp_path_factory, rig):
    out = tmp_path_factory.mktemp("cal") / "set"
    make_calibration_captures(out, rig=rig, size=SIZE, sensor=make_sensor("gaussian", sigma=0.01), seed=1)
    return out


@pytest.fixture(scope="module")
def calibrated(calibration_set, tmp_path_factory):
    path = tmp_path_factory.mktemp("out") / "calibration.json"
    return calibrate_captures([calibration_set], path)


def test_calibration_set_holds_what_the_format_says(calibration_set, rig):
    index = json.loads((calibration_set / "index.json").read_text())
    targets = [c["target"] for c in index["captures"]]
    assert targets.count("polarizer") == 12 and {"flat", "geometry", "star"} <= set(targets)
    flat = read_capture(calibration_set / "flat")
    assert np.allclose(flat.gt, flat.meta["calibration"]["level"])
    sweep = read_capture(calibration_set / "polarizer-033.75deg")
    assert np.allclose(sweep.gt[:, 0, 0], polarized_field(4, 0.45, 33.75)[:, 0, 0])
    assert np.allclose(flat.rig.analyzer_matrix(), rig.analyzer_matrix())
    assert np.array_equal(flat.aperture_homographies(), read_capture(calibration_set / "star").aperture_homographies())


def test_recovers_the_rig_within_the_issue_tolerances(calibrated, rig, calibration_set):
    est = calibrated.rig
    assert np.max(np.abs(est.angle_offsets_deg - rig.angle_offsets_deg)) < 0.1
    assert np.max(np.abs(est.extinction_ratio / rig.extinction_ratio - 1)) < 0.10
    shape = (SIZE // 2, SIZE // 2)
    rel = (est.flat_field(shape) - rig.flat_field(shape)) / rig.flat_field(shape)
    assert np.sqrt(np.mean(rel ** 2)) < 0.005
    truth = read_capture(calibration_set / "geometry")
    err = registration_error_hr_px(calibrated.geometry.lr_homographies, truth.true_lr_homographies(), truth.hr_shape)
    assert np.median(err) < 0.05
    sigmas = [p["sigma_hr_px"] for p in est.psf]
    assert np.max(np.abs(np.subtract(sigmas, [p["sigma_hr_px"] for p in rig.psf]))) < 0.05
    assert set(calibrated.calibrated) == {"gain", "vignetting", "angle_offsets_deg", "extinction_ratio", "geometry",
                                          "psf"}
    for key in ("angle_offsets_deg", "extinction_ratio", "gain", "psf_sigma_hr_px"):
        assert np.all(np.isfinite(calibrated.uncertainty[key]))


def test_flat_field_fit_is_exact_without_noise(rig):
    frames = rig.flat_field((40, 48))[None] * 0.4
    fit = fit_flat_field(frames, 0.4)
    assert np.allclose(fit.gain, rig.gain, atol=1e-10)
    assert np.allclose(fit.maps((40, 48)), rig.flat_field((40, 48)), atol=1e-10)


def test_malus_fit_is_exact_without_noise(rig):
    from capssim.operators import caps_raw_operator

    phi = sweep_angles(6)
    op = caps_raw_operator((32, 32), np.tile(np.eye(3), (4, 1, 1)), np.ones((1, 1)), rig=rig)
    frames = np.stack([op(torch.from_numpy(polarized_field(32, 0.45, p).astype(np.float64))).numpy() for p in phi])
    fit = fit_malus(frames, phi, [0.45] * 6, rig.flat_field((16, 16)), noise_sigma=1e-6)
    assert np.allclose(fit.angle_offsets_deg, rig.angle_offsets_deg, atol=1e-6)
    assert np.allclose(fit.extinction_ratio, rig.extinction_ratio, rtol=1e-4)


def test_lanczos_warp_is_exact_for_integer_shifts():
    x = torch.rand(3, 24, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    h = np.eye(3)
    h[:2, 2] = (2.0, -1.0)
    out = lanczos_warp(x, h)
    torch.testing.assert_close(out[:, 3:-3, 3:-3], x[:, 4:-2, 1:-5])


def test_calibrated_data_term_is_the_adjoint_of_its_forward(rig):
    obs = rearrange_raw(np.random.default_rng(0).random((4, 16, 16)).astype(np.float32))
    obs.images, obs.weights = obs.images.double(), obs.weights.double()
    from capssim.camera.array_geometry import ArrayGeometry
    from capssim.operators import lr_sampling_operator

    geo = ArrayGeometry(np.tile(np.eye(3), (4, 1, 1)), (32, 32))
    op = lr_sampling_operator(geo, np.ones((1, 1)), psf_kernels=rig.psf_kernels(), flat=rig.lr_flat_field((16, 16)))
    data = ConfidenceDataTerm(obs, op, mixing=rig.lr_channel_matrix())
    x = torch.rand(12, 32, 32, dtype=torch.float64, requires_grad=True)
    with torch.enable_grad():
        value = 0.5 * (data.residual(x) ** 2).sum()
        (grad,) = torch.autograd.grad(value, x)
    torch.testing.assert_close(data.backprojection(x.detach()), -grad, rtol=1e-10, atol=1e-12)


@pytest.fixture(scope="module")
def scene_capture(tmp_path_factory, rig, calibration_set, calibrated):
    """A polarized, textured scene through the rig and the calibration set's homographies."""
    rng = np.random.default_rng(5)
    from scipy.ndimage import gaussian_filter

    s0 = 0.3 + 0.4 * np.clip(gaussian_filter(rng.random((SIZE, SIZE)), 2) * 4 - 1.5, 0, 1)
    aop = np.radians(90 * gaussian_filter(rng.random((SIZE, SIZE)), 8) * 4)
    dolp = 0.5 * gaussian_filter(rng.random((SIZE, SIZE)), 6) * 2
    angles = np.radians([0, 45, 90, 135])
    gt = np.stack([0.5 * s0 * c * (1 + dolp * np.cos(2 * (a - aop))) for a in angles for c in (0.9, 1.0, 0.7)])
    homographies = read_capture(calibration_set / "flat").aperture_homographies()
    capture = simulate_capture(gt.astype(np.float32), make_sensor("gaussian", sigma=0.01), seed=2, rig=rig,
                               aperture_homographies=homographies)
    path = tmp_path_factory.mktemp("scene") / "cap"
    capture.meta["calibration_file"] = "calibration.json"
    write_capture(path, capture)
    shutil.copy(calibrated.path, path / "calibration.json")
    return read_capture(path)


@pytest.mark.parametrize("method,options", [("caps", {"iterations": 4}), ("caps-naive", {})])
def test_round_trip_calibrated_closes_the_gap(scene_capture, method, options):
    scores = {}
    for model in ("ideal", None, "truth"):  # None: the capture's own calibration_file
        out, record = reconstruct(scene_capture, method, calibration=model, **options)
        scores[model] = score(out.image, scene_capture.gt)
        assert (record["calibration"] is None) == (model == "ideal")
    assert scores["truth"]["psnr_mean"] - scores["ideal"]["psnr_mean"] > 1.0
    for metric in ("psnr_mean", "dolp_psnr", "aop_rmse_deg"):  # the issue's "closes 90 % of the gap"
        gap = scores["truth"][metric] - scores["ideal"][metric]
        closed = scores[None][metric] - scores["ideal"][metric]
        assert closed * np.sign(gap) >= 0.9 * abs(gap) - 0.02, (metric, scores)


def test_malformed_calibration_input(calibration_set, tmp_path, rig):
    with pytest.raises(InputError, match="flat-field capture too"):
        calibrate_captures([calibration_set / "polarizer-003.75deg", calibration_set / "polarizer-018.75deg",
                            calibration_set / "polarizer-033.75deg"], tmp_path / "a.json")
    with pytest.raises(InputError, match="at least 3 distinct"):
        calibrate_captures([calibration_set / "flat", calibration_set / "polarizer-003.75deg",
                            calibration_set / "polarizer-018.75deg"], tmp_path / "b.json")
    with pytest.raises(InputError, match="capture folders"):
        calibrate_captures([tmp_path / "missing"], tmp_path / "c.json")
    bright = simulate_capture(polarized_field(SIZE, 0.99, 0.0, dolp=0.0), make_sensor("gaussian", sigma=0.01),
                              rig=rig.with_overrides(gain=[1.1, 1.1, 1.1, 1.1]),
                              extra_meta={"calibration": {"target": "flat", "level": 0.99}})
    write_capture(tmp_path / "sat", bright)
    with pytest.raises(InputError, match="saturated"):
        calibrate_captures([tmp_path / "sat"], tmp_path / "d.json")
    plain = simulate_capture(polarized_field(SIZE, 0.3, 0.0), make_sensor("none"))
    write_capture(tmp_path / "plain", plain)
    with pytest.raises(InputError, match="calibration entry"):
        calibrate_captures([tmp_path / "plain"], tmp_path / "e.json")


def test_reconstruct_refuses_bad_calibrations(scene_capture, tmp_path):
    with pytest.raises(InputError, match="--calibration"):
        reconstruct(scene_capture, "caps-naive", calibration=str(tmp_path / "nope.json"))
    small = write_rig_json(tmp_path / "small.json", RigModel.ideal(),
                           geometry=__import__("capssim.camera.array_geometry", fromlist=["ArrayGeometry"]).ArrayGeometry(
                               np.tile(np.eye(3), (4, 1, 1)), (64, 64)))
    with pytest.raises(InputError, match="HR size"):
        reconstruct(scene_capture, "caps-naive", calibration=str(small))
    ideal_capture = simulate_capture(polarized_field(64, 0.3, 0.0), make_sensor("none"))
    with pytest.raises(InputError, match="true rig"):
        reconstruct(ideal_capture, "caps-naive", calibration="truth")


def test_cli_calibration_round_trip(tmp_path):
    from typer.testing import CliRunner

    from capssim.cli import app

    runner = CliRunner()
    result = runner.invoke(app, ["calibration-captures", "-o", str(tmp_path / "set"), "--size", "64", "--rig", "realistic",
                                 "--polarizer-angles", "6", "--noise", "gaussian", "--sigma", "0.01"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["calibrate", str(tmp_path / "set"), "-o", str(tmp_path / "c.json"),
                                 "--report", str(tmp_path / "report")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "report" / "malus.png").is_file() and "aperture 3" in result.output
    bad = runner.invoke(app, ["calibration-captures", "-o", str(tmp_path / "x"), "--polarizer-angles", "2"])
    assert bad.exit_code != 0 and "--polarizer-angles" in str(bad.exception or bad.output)


def test_rendered_and_simulated_calibrations_agree(tmp_path, rig):
    pytest.importorskip("mitsuba")
    sensor = make_sensor("gaussian", sigma=0.01)
    results = {}
    for renderer in ("simulate", "mitsuba"):
        make_calibration_captures(tmp_path / renderer, rig=rig, size=SIZE, sensor=sensor, renderer=renderer,
                                  polarizer_angles=6, seed=4, spp=16)
        results[renderer] = calibrate_captures([tmp_path / renderer], tmp_path / f"{renderer}.json")
    sim, ren = results["simulate"].rig, results["mitsuba"].rig
    assert np.max(np.abs(sim.angle_offsets_deg - ren.angle_offsets_deg)) < 0.1
    assert np.max(np.abs(ren.extinction_ratio / sim.extinction_ratio - 1)) < 0.10
    shape = (SIZE // 2, SIZE // 2)
    assert np.sqrt(np.mean(((ren.flat_field(shape) - sim.flat_field(shape)) / sim.flat_field(shape)) ** 2)) < 0.005
    for est in (sim, ren):
        assert np.max(np.abs(np.subtract([p["sigma_hr_px"] for p in est.psf],
                                         [p["sigma_hr_px"] for p in rig.psf]))) < 0.05
    truth = read_capture(tmp_path / "simulate" / "geometry")
    for result in results.values():
        err = registration_error_hr_px(result.geometry.lr_homographies, truth.true_lr_homographies(), truth.hr_shape)
        assert np.median(err) < 0.05


def test_dataset_config_rig_form(tmp_path):
    from capssim.dataset.config import load_config, rig_model

    gt = tmp_path / "gt.tiff"
    from capssim.files.imageio import write_tiff

    write_tiff(gt, polarized_field(32, 0.3, 10.0))
    text = (f"seed: 1\nsamples: 1\ndefaults: {{rig: {{preset: realistic, seed: 2, gain: [1.05, 0.95, 1.0, 1.0]}}}}\n"
            f"sources: [{{gt: {gt}, size: 32}}]\n")
    (tmp_path / "ds.yaml").write_text(text)
    spec = load_config(tmp_path / "ds.yaml").sample_spec(0)
    assert np.allclose(rig_model(spec["params"]["rig"]).gain, [1.05, 0.95, 1.0, 1.0])
    (tmp_path / "bad.yaml").write_text(text.replace("[1.05, 0.95, 1.0, 1.0]", "[1, 2]"))
    with pytest.raises(InputError, match="gain"):
        load_config(tmp_path / "bad.yaml").sample_spec(0)
