"""Reconstruction with a calibrated array model (issue "Real rigs", item 4).

Pins: the calibrated data term (analyzer mixing, per-aperture PSFs, flat field) is the exact
adjoint of its forward model (float64 dot tests, CAPS and ICCP forms); an ideal mixing matrix gives
the index-select path bit for bit; a capture through an imperfect rig is reconstructed better with
the true rig than with the ideal model (caps, caps-naive, caps-iccp); without a calibration (or with
an ideal one) the output is identical; a capture's own ``calibration_file`` is used by default; bad
calibration input is an ``InputError`` naming ``--calibration``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.homography import random_aperture_homographies
from capssim.camera.rig import RigModel, write_rig_json
from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_capture, write_capture
from capssim.errors import InputError
from capssim.eval.metrics import score
from capssim.operators.camera import lr_sampling_operator
from capssim.reconstruct import reconstruct
from capssim.reconstruct.methods.caps_iccp import aperture_sampling_operator
from capssim.reconstruct.methods.caps_naive import demosaic_apertures
from capssim.reconstruct.model.data_term import ConfidenceDataTerm
from capssim.reconstruct.model.observation_model import unmix_analyzer
from capssim.reconstruct.model.rearrange import Observations, rearrange_raw
from capssim.simulate import simulate_capture

SIZE = 64  # HR pixels


@pytest.fixture(scope="module")
def rig() -> RigModel:
    """An imperfect array at the issue's limits: +-2 deg, extinction 30-100, gains +-5 %, 20 % vignetting."""
    return RigModel.ideal().with_overrides(angle_offsets_deg=[2.0, -2.0, 1.5, -1.0], extinction_ratio=[30, 60, 100],
                                           gain=[1.05, 0.95, 1.0, 1.03], vignetting_corner=0.2,
                                           psf_sigmas_hr_px=[0.4, 0.6, 0.5, 0.45])


def polarized_scene(size: int, seed: int) -> np.ndarray:
    """``(12, size, size)``: a smooth textured scene with strong, varying linear polarization."""
    rng = np.random.default_rng(seed)
    s0 = 0.35 + 0.5 * np.clip(gaussian_filter(rng.random((size, size)), 1.5) * 4 - 1.5, 0, 1)
    aop = np.pi * gaussian_filter(rng.random((size, size)), 6) * 3
    dolp = np.clip(0.8 * gaussian_filter(rng.random((size, size)), 4) * 2, 0, 0.9)
    angles = np.radians([0, 45, 90, 135])
    return np.stack([0.5 * s0 * c * (1 + dolp * np.cos(2 * (a - aop))) for a in angles
                     for c in (0.9, 1.0, 0.7)]).astype(np.float32)


def random_geometry(size: int, seed: int) -> ArrayGeometry:
    homographies, _ = random_aperture_homographies(np.random.default_rng(seed), (size, size))
    return ArrayGeometry(homographies, (size, size))


def _float64_observations(n_obs: int, n_channels: int, shape, channel_of, seed: int) -> Observations:
    gen = torch.Generator().manual_seed(seed)
    return Observations(images=torch.rand(n_obs, *shape, dtype=torch.float64, generator=gen),
                        weights=torch.ones(n_obs, *shape, dtype=torch.float64),
                        channel_of=torch.as_tensor(channel_of), n_channels=n_channels)


def _dot_test(data: ConfidenceDataTerm, seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(data.image_shape, dtype=torch.float64, generator=gen)
    r = torch.rand(tuple(data.obs.images.shape), dtype=torch.float64, generator=gen)
    lhs = float((data.forward(x) * r).sum())
    rhs = float((x * data.adjoint(r)).sum())
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs), (lhs, rhs)


def test_calibrated_caps_data_term_is_exactly_adjoint(rig):
    geometry = random_geometry(SIZE, 0)
    raw_shape = (SIZE // 2, SIZE // 2)
    op = lr_sampling_operator(geometry, np.ones((1, 1)), psf_kernels=rig.psf_kernels(), flat=rig.lr_flat_field(raw_shape))
    obs = rearrange_raw(np.zeros((4, *raw_shape), dtype=np.float32))
    obs = _float64_observations(16, 12, (SIZE // 4, SIZE // 4), obs.channel_of, 1)
    data = ConfidenceDataTerm(obs, op, mixing=rig.lr_channel_matrix())
    _dot_test(data, 2)
    # the back-projection is -grad f, with data weights
    obs.weights = (torch.rand(obs.weights.shape, generator=torch.Generator().manual_seed(3)) > 0.2).double()
    data = ConfidenceDataTerm(obs, op, mixing=rig.lr_channel_matrix())
    x = torch.rand(12, SIZE, SIZE, dtype=torch.float64, requires_grad=True)
    with torch.enable_grad():
        (grad,) = torch.autograd.grad(0.5 * data.residual(x).square().sum(), x)
    torch.testing.assert_close(data.backprojection(x.detach()), -grad, rtol=1e-10, atol=1e-12)


def test_calibrated_iccp_data_term_is_exactly_adjoint(rig):
    geometry = random_geometry(SIZE, 4)
    op = aperture_sampling_operator(geometry, rig.psf_kernels())
    obs = _float64_observations(4, 4, (SIZE // 2, SIZE // 2), np.arange(4), 5)
    for k in range(3):
        _dot_test(ConfidenceDataTerm(obs, op, mixing=rig.analyzer_matrix()[k::3, k::3]), 6 + k)


def test_ideal_mixing_matrix_is_the_channel_selection():
    geometry = random_geometry(SIZE, 7)
    op = lr_sampling_operator(geometry, np.ones((1, 1)))
    channel_of = rearrange_raw(np.zeros((4, SIZE // 2, SIZE // 2), dtype=np.float32)).channel_of
    obs = _float64_observations(16, 12, (SIZE // 4, SIZE // 4), channel_of, 8)
    plain = ConfidenceDataTerm(obs, op)
    mixed = ConfidenceDataTerm(obs, op, mixing=RigModel.ideal().lr_channel_matrix())
    x = torch.rand(12, SIZE, SIZE, dtype=torch.float64, generator=torch.Generator().manual_seed(9))
    assert torch.equal(plain.forward(x), mixed.forward(x))
    r = plain.residual(x)
    assert torch.equal(plain.adjoint(r), mixed.adjoint(r))


def test_unmix_analyzer_inverts_the_mixing_per_pixel(rig):
    x = torch.rand(12, 8, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(10))
    a = rig.analyzer_matrix()
    y = torch.einsum("ij,jhw->ihw", torch.from_numpy(a), x)
    torch.testing.assert_close(unmix_analyzer(y, a), x, rtol=0, atol=1e-12)
    torch.testing.assert_close(unmix_analyzer(y[1::3], a[1::3, 1::3]), x[1::3], rtol=0, atol=1e-12)


def test_demosaicking_keeps_flat_corrected_values_above_one():
    raw = np.full((1, 16, 16), 1.2, dtype=np.float32)
    assert np.allclose(demosaic_apertures(raw, bayer_method="bilinear", clip_max=1.25), 1.2)
    assert np.allclose(demosaic_apertures(raw, bayer_method="bilinear"), 1.0)


@pytest.fixture(scope="module")
def rig_capture(tmp_path_factory, rig):
    """A capture through ``rig`` whose meta.json names its calibration: the true rig and geometry."""
    capture = simulate_capture(polarized_scene(SIZE, 1), make_sensor("gaussian", sigma=0.002), seed=3, rig=rig)
    path = tmp_path_factory.mktemp("rig") / "cap"
    capture.meta["calibration_file"] = "calibration.json"
    write_capture(path, capture)
    write_rig_json(path / "calibration.json", rig, geometry=capture.geometry,
                   calibrated=("angle_offsets_deg", "extinction_ratio", "gain", "vignetting", "psf", "geometry"))
    return read_capture(path)


@pytest.mark.parametrize("method,options", [("caps", {"iterations": 3}), ("caps-naive", {}),
                                            ("caps-iccp", {"iterations": 2})])
def test_true_rig_beats_the_ideal_model(rig_capture, method, options):
    ideal, ideal_record = reconstruct(rig_capture, method, calibration="ideal", true_warps=True, **options)
    truth, truth_record = reconstruct(rig_capture, method, calibration="truth", **options)
    own, own_record = reconstruct(rig_capture, method, **options)  # meta.json calibration_file
    scores = {name: score(out.image, rig_capture.gt) for name, out in
              (("ideal", ideal), ("truth", truth), ("own", own))}
    assert scores["truth"]["psnr_mean"] > scores["ideal"]["psnr_mean"] + 1.0, scores
    assert scores["truth"]["aop_rmse_deg"] < scores["ideal"]["aop_rmse_deg"], scores
    assert ideal_record["calibration"] is None and truth_record["calibration"]["source"].startswith("truth")
    assert own_record["calibration"]["source"].endswith("calibration.json")
    assert own_record["calibration"]["format_version"] == 1 and "gain" in own_record["calibration"]["calibrated"]
    assert own_record["registration"]["source"].startswith("calibration")
    # the file holds the true rig and geometry: the same model as "truth"
    np.testing.assert_allclose(own.image, truth.image, atol=1e-5)


def test_true_warps_and_an_explicit_psf_win_over_the_calibration(rig_capture):
    _, record = reconstruct(rig_capture, "caps", true_warps=True, iterations=1, psf_sigma=0.5,
                            calibration="truth")
    assert record["registration"]["source"] == "true (meta.json)"
    assert record["params"]["psf"]["type"] == "gaussian"
    _, record = reconstruct(rig_capture, "caps", iterations=1, calibration="truth")
    assert record["params"]["psf"]["type"] == "per aperture"


@pytest.fixture(scope="module")
def plain_capture(tmp_path_factory):
    capture = simulate_capture(polarized_scene(SIZE, 2), make_sensor("gaussian", sigma=0.01), seed=4)
    path = tmp_path_factory.mktemp("plain") / "cap"
    write_capture(path, capture)
    write_rig_json(path.parent / "ideal.json", RigModel.ideal())
    return read_capture(path)


@pytest.mark.parametrize("method,options", [("caps", {"iterations": 2}), ("caps-naive", {})])
def test_no_or_ideal_calibration_changes_nothing(plain_capture, method, options):
    base, record = reconstruct(plain_capture, method, true_warps=True, **options)
    assert record["calibration"] is None
    ideal_file = str(plain_capture.path.parent / "ideal.json")
    for calibration in ("ideal", ideal_file):
        out, _ = reconstruct(plain_capture, method, true_warps=True, calibration=calibration, **options)
        assert np.array_equal(out.image, base.image), calibration


def test_bad_calibration_input_names_the_option(plain_capture, tmp_path):
    (tmp_path / "other.json").write_text(json.dumps({"format": "something-else", "version": 1}))
    (tmp_path / "broken.json").write_text("{not json")
    small = write_rig_json(tmp_path / "small.json", RigModel.ideal(), geometry=random_geometry(SIZE // 2, 0))
    for path in (tmp_path / "missing.json", tmp_path / "other.json", tmp_path / "broken.json", small):
        with pytest.raises(InputError, match="--calibration"):
            reconstruct(plain_capture, "caps-naive", calibration=str(path))
    with pytest.raises(InputError, match="--calibration"):
        reconstruct(plain_capture, "caps-naive", calibration="truth")  # no true rig in meta.json
    plain_capture.meta["calibration_file"] = "nowhere.json"
    try:
        with pytest.raises(InputError, match="--calibration"):
            reconstruct(plain_capture, "caps-naive")
    finally:
        del plain_capture.meta["calibration_file"]


def test_cli_reconstruct_with_a_calibration(rig_capture, tmp_path):
    from typer.testing import CliRunner

    from capssim.cli import app

    runner = CliRunner()
    result = runner.invoke(app, ["reconstruct", str(rig_capture.path), "-m", "caps-naive", "--calibration", "truth",
                                 "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "array model: calibration truth" in result.output
    record = json.loads((rig_capture.path / "recon" / "caps-naive.json").read_text())
    assert record["calibration"]["source"].startswith("truth")
    bad = runner.invoke(app, ["reconstruct", str(rig_capture.path), "-m", "caps-naive", "--calibration",
                              str(tmp_path / "missing.json"), "--no-progress"])
    assert bad.exit_code != 0 and "--calibration" in (bad.output + str(bad.exception))
