"""The imperfect-rig model (capssim.camera.rig) and the operators built from it: exact adjoints, ideal = today."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.homography import random_aperture_homographies
from capssim.camera.psf import gaussian_psf_kernel
from capssim.camera.rig import (
    RigModel,
    analyzer_row,
    normalised_raw_coordinates,
    polarizer_reading,
    radial_vignetting,
    read_rig_json,
    vignetting_design,
    write_rig_json,
)
from capssim.camera.rig_checks import check_vignetting
from capssim.errors import InputError
from capssim.operators import (
    BayerSplit,
    Convolve,
    Multiply,
    adjointness_error,
    analyzer_matrix,
    caps_raw_operator,
    lr_observation_operator,
    lr_sampling_operator,
)

HR = (32, 40)


def _geometry(seed: int = 3) -> ArrayGeometry:
    h, _ = random_aperture_homographies(np.random.default_rng(seed), HR)
    return ArrayGeometry(h, HR)


def _polarized_twelve(phi_deg: float, level: float = 0.4) -> np.ndarray:
    """``(12,)`` channel values of uniform light fully polarized at ``phi_deg``."""
    angles = np.repeat([0.0, 45.0, 90.0, 135.0], 3)
    return level * (1 + np.cos(np.radians(2 * (angles - phi_deg))))


def test_ideal_rig_gives_todays_operators_exactly():
    geo, kernel = _geometry(), gaussian_psf_kernel(0.5)
    x = torch.rand(12, *HR, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    ideal = caps_raw_operator(HR, geo.aperture_homographies, kernel)(x)
    with_rig = caps_raw_operator(HR, geo.aperture_homographies, kernel, rig=RigModel.ideal())(x)
    assert torch.equal(ideal, with_rig)
    assert np.array_equal(RigModel.ideal().analyzer_matrix(), analyzer_matrix())
    er = RigModel().with_overrides(extinction_ratio=150.0)
    assert np.allclose(er.analyzer_matrix(), analyzer_matrix(extinction_ratio=150.0), atol=1e-15)


@pytest.mark.parametrize("theta", [0.0, 1.7, -2.0, 44.0, 91.3, 134.0, 137.5])
@pytest.mark.parametrize("phi", [0.0, 30.0, 100.0])
def test_polarizer_reading_follows_malus_law(theta, phi):
    x = _polarized_twelve(phi)[::3]  # one colour: I(0, 45, 90, 135)
    assert polarizer_reading(theta) @ x == pytest.approx(0.8 * math.cos(math.radians(theta - phi)) ** 2, abs=1e-12)
    er = 120.0
    expected = 0.8 * (er * math.cos(math.radians(theta - phi)) ** 2 + math.sin(math.radians(theta - phi)) ** 2) / (er + 1)
    assert analyzer_row(theta, er) @ x == pytest.approx(expected, abs=1e-12)


def test_unpolarized_light_reads_half_s0_whatever_the_imperfection():
    rig = RigModel.preset("realistic", seed=4)
    assert np.allclose(rig.analyzer_matrix() @ np.full(12, 0.3), 0.3, atol=1e-12)


def test_vignetting_polynomial_is_one_at_centre_and_falls_to_the_corner():
    coef = radial_vignetting(0.2)
    u, v = normalised_raw_coordinates((9, 9))
    values = vignetting_design(u, v) @ coef
    assert values[4, 4] == pytest.approx(1.0, abs=1e-12)
    assert values[0, 0] == pytest.approx(0.8, abs=1e-12) and values[-1, -1] == pytest.approx(0.8, abs=1e-12)
    with pytest.raises(InputError, match="vignetting"):
        radial_vignetting(1.5)


def test_lr_observation_with_rig_equals_bayer_split_of_raw():
    rig = RigModel.preset("realistic", seed=1)
    geo = _geometry()
    x = torch.rand(12, *HR, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    raw = caps_raw_operator(HR, geo.aperture_homographies, gaussian_psf_kernel(0.5), rig=rig)(x)
    lr = lr_observation_operator(geo, gaussian_psf_kernel(0.5), rig=rig)(x)
    split = BayerSplit((4, HR[0] // 2, HR[1] // 2))(raw)
    torch.testing.assert_close(split.reshape(lr.shape), lr, rtol=1e-12, atol=1e-12)


def test_flat_field_multiplies_uniform_light():
    rig = RigModel().with_overrides(gain=[1.05, 0.95, 1.0, 1.02], vignetting_corner=0.2)
    x = torch.full((12, *HR), 0.25, dtype=torch.float64)
    raw = caps_raw_operator(HR, np.tile(np.eye(3), (4, 1, 1)), np.ones((1, 1)), rig=rig)(x)
    assert np.allclose(raw.numpy(), 0.25 * rig.flat_field((HR[0] // 2, HR[1] // 2)), atol=1e-12)


@pytest.mark.parametrize("name", ["caps_raw", "lr_observation", "lr_sampling", "convolve_stack", "multiply"])
def test_rig_operators_are_exactly_adjoint(name):
    rig = RigModel.preset("realistic", seed=2)
    geo, kernel = _geometry(), gaussian_psf_kernel(0.5)
    kernels = [gaussian_psf_kernel(s) for s in (0.3, 0.6, 1.1, 0.0)]
    op = {
        "caps_raw": lambda: caps_raw_operator(HR, geo.aperture_homographies, kernel, rig=rig),
        "lr_observation": lambda: lr_observation_operator(geo, kernel, rig=rig),
        "lr_sampling": lambda: lr_sampling_operator(geo, kernel, psf_kernels=kernels,
                                                    flat=rig.lr_flat_field((HR[0] // 2, HR[1] // 2))),
        "convolve_stack": lambda: Convolve(kernels, (4, 3, *HR)),
        "multiply": lambda: Multiply(np.random.default_rng(0).random((3, *HR))),
    }[name]()
    assert adjointness_error(op) < 1e-12


def test_convolve_stack_applies_one_kernel_per_block_of_planes():
    kernels = [gaussian_psf_kernel(0.4), gaussian_psf_kernel(1.0)]
    x = torch.rand(2, 3, 16, 16, dtype=torch.float64)
    out = Convolve(kernels, (2, 3, 16, 16))(x)
    for g in range(2):
        torch.testing.assert_close(out[g], Convolve(kernels[g], (3, 16, 16))(x[g]))
    with pytest.raises(InputError, match="kernel"):
        Convolve(kernels * 2 + kernels[:1], (2, 3, 16, 16))


def test_rig_file_round_trip_and_bad_files(tmp_path):
    rig = RigModel.preset("realistic", seed=5)
    geo = _geometry()
    path = write_rig_json(tmp_path / "rig.json", rig, geometry=geo, calibrated=["angles"],
                          uncertainty={"angle_offsets_deg": [0.01] * 4})
    back = read_rig_json(path)
    assert np.allclose(back.rig.analyzer_matrix(), rig.analyzer_matrix(), atol=1e-15)
    assert np.allclose(back.rig.flat_field((8, 8)), rig.flat_field((8, 8)))
    assert np.allclose(back.geometry.aperture_homographies, geo.aperture_homographies)
    assert back.calibrated == ("angles",) and back.rig.psf == rig.psf
    data = json.loads(path.read_text())
    data["version"] = 99
    (tmp_path / "v.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match="version"):
        read_rig_json(tmp_path / "v.json", argument="--calibration")
    data["version"], data["rig"]["gain"] = 1, [1.0, 1.0]
    (tmp_path / "g.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match="gain"):
        read_rig_json(tmp_path / "g.json")
    with pytest.raises(InputError, match="--calibration"):
        read_rig_json(tmp_path / "missing.json", argument="--calibration")


@pytest.mark.parametrize("bad", [
    {"angle_offsets_deg": [0, 0, 0, 30]},
    {"extinction_ratio": [[0.5, 2, 2]] * 4},
    {"gain": [1, 1, float("nan"), 1]},
    {"psf": [{"type": "gaussian", "sigma_hr_px": 0.5}]},
    {"colour": 1},
])
def test_bad_rig_values_name_their_key(bad):
    with pytest.raises(InputError, match="rig"):
        RigModel.from_dict(bad)


def test_realistic_preset_is_reproducible_and_within_its_ranges():
    a, b = RigModel.preset("realistic", seed=7), RigModel.preset("realistic", seed=7)
    assert np.array_equal(a.analyzer_matrix(), b.analyzer_matrix())
    assert np.all(np.abs(a.angle_offsets_deg) <= 2) and np.all(np.abs(a.gain - 1) <= 0.05)
    assert np.all((a.extinction_ratio >= 30) & (a.extinction_ratio <= 300))
    corner = a.flat_field((64, 64))[:, 0, 0] / a.gain
    assert np.all((corner > 0.7) & (corner < 0.9))
    with pytest.raises(InputError, match="rig"):
        RigModel.preset("perfect")


@pytest.mark.parametrize("constant, aperture, phrase", [(2e3, 2, "<= 1000"), (-0.5, 1, ">= 0.001")])
def test_a_flat_field_out_of_its_bounds_names_the_aperture_and_the_bound(constant, aperture, phrase):
    """``check_vignetting`` refuses a flat field above the gain ceiling or below the floor, naming which aperture,
    the value it reaches and the bound it broke; an in-bounds one passes."""
    vignetting = np.zeros((4, 15))
    vignetting[:, 0] = 1.0
    check_vignetting(np.ones(4), vignetting)  # no vignetting: accepted
    vignetting[aperture, 0] = constant
    with pytest.raises(InputError) as info:
        check_vignetting(np.ones(4), vignetting, where="rig.vignetting")
    message = str(info.value)
    assert "rig.vignetting" in message and f"aperture {aperture}'s flat field reaching {constant:.3g}" in message
    assert phrase in message
