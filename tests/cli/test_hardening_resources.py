"""Issue 21, defect lists 1 and 6: the resource guard, and invalid values refused instead of accepted silently.

Every case is refused before anything large is allocated; limits are made small with
``CAPSSIM_MEMORY_LIMIT_GB`` rather than by allocating much.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from capssim.camera.camera_setup import CameraSetup
from capssim.camera.homography import random_aperture_homographies
from capssim.camera.psf import PSF
from capssim.camera.sensor import NoNoiseSensor
from capssim.captures.capture import Capture
from capssim.cli import app
from capssim.errors import InputError, ResourceError
from capssim.eval.metric_records import json_safe
from capssim.eval.metrics import check_thresholds, score
from capssim.reconstruct.model.observation_model import method_psf
from capssim.reconstruct.priors.nlstr import NLSTRParameters, NonlocalSparseTensor
from capssim.render.pinhole_array import RigTolerances
from capssim.render.settings import RenderSettings
from capssim.runtime.resources import MEMORY_LIMIT_ENV, available_memory_bytes, check_memory, memory_limit
from capssim.simulate import prepare_ground_truth, simulate_capture

runner = CliRunner()


@pytest.fixture
def small_limit(monkeypatch):
    """A 16 MiB memory limit."""
    monkeypatch.setenv(MEMORY_LIMIT_ENV, str(16 / 1024))


def _gt(size: int = 32) -> np.ndarray:
    rng = np.random.default_rng(0)
    return (0.2 + 0.6 * rng.random((12, size, size))).astype(np.float32)


# -- the guard itself ------------------------------------------------------------------
def test_limit_from_available_memory_and_from_the_environment(monkeypatch):
    monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
    available = available_memory_bytes()
    assert available is None or available > 0
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "2")
    assert memory_limit()[0] == 2 * 2**30
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "inf")
    check_memory("x", 1e30, what="anything", fix="")
    for bad in ("-1", "abc", "0"):
        monkeypatch.setenv(MEMORY_LIMIT_ENV, bad)
        with pytest.raises(InputError, match=MEMORY_LIMIT_ENV):
            memory_limit()


def test_message_names_option_estimate_limit_and_override(small_limit):
    with pytest.raises(ResourceError) as info:
        check_memory("--size", 2**40, what="a big render", fix="Use a smaller --size.")
    text = str(info.value)
    assert text.startswith("--size:") and "1 TiB" in text and "16 MiB" in text and MEMORY_LIMIT_ENV in text
    assert "smaller --size" in text


# -- NLSTR -----------------------------------------------------------------------------
def test_nlstr_search_radius_past_the_image_is_refused():
    with pytest.raises(ResourceError, match="search_radius.*at most 64"):
        NonlocalSparseTensor((12, 64, 64), NLSTRParameters(search_radius=1000))


def test_nlstr_working_set_past_the_limit_is_refused(small_limit):
    with pytest.raises(ResourceError, match="search_radius: NLSTR on a 64x64 image"):
        NonlocalSparseTensor((12, 64, 64), NLSTRParameters(search_radius=48))
    with pytest.raises(ResourceError, match="block 32, stride 1"):
        NonlocalSparseTensor((12, 64, 64), NLSTRParameters(block=32, stride=1))


def test_nlstr_matching_checks_its_group_size(monkeypatch):
    nl = NonlocalSparseTensor((12, 32, 32), NLSTRParameters(search_radius=16))
    monkeypatch.setenv(MEMORY_LIMIT_ENV, str(nl.working_set_bytes(1) / 2**30 * 1.01))
    assert nl.working_set_bytes(5000) > 1.01 * nl.working_set_bytes(1)
    with pytest.raises(ResourceError, match="n_similar 5000"):
        nl.match(torch.zeros(12, 32, 32), 5000)


def test_nlstr_parameters_must_be_integers():
    for bad in (dict(block=8.5), dict(search_radius="7"), dict(stride=True), dict(strip_mb=float("nan"))):
        with pytest.raises(InputError):
            NLSTRParameters(**bad).validate()


# -- PSF -------------------------------------------------------------------------------
@pytest.mark.parametrize("psf", [PSF.none(), PSF.gaussian(0.5), PSF.gaussian(2.3), PSF.airy(1.65, 550, 2.4),
                                 PSF.airy(8.0, 550, 2.4), PSF.from_spec({"type": "kernel", "kernel": np.ones((3, 5))})])
def test_kernel_radius_without_building_it(psf):
    assert psf.kernel_radius() == max(psf.kernel().shape) // 2
    psf.check_extent((64, 64))


def test_psf_wider_than_the_image_is_refused():
    with pytest.raises(ResourceError, match="gaussian PSF's kernel side.*7001.*at most 64"):
        PSF.gaussian(1000).check_extent((64, 64), option="--psf-sigma-hr-px")
    with pytest.raises(ResourceError, match="airy PSF's kernel side"):
        PSF.airy(1000, 550, 2.4).check_extent((64, 64))


def test_psf_blur_past_the_memory_limit_is_refused(small_limit):
    with pytest.raises(ResourceError, match="blurring a 64x64 image"):
        PSF.gaussian(8).check_extent((64, 64))


def test_simulate_refuses_a_huge_psf_before_building_it():
    with pytest.raises(ResourceError, match="psf"):
        simulate_capture(_gt(), NoNoiseSensor(), psf=PSF.gaussian(1000))


# -- render settings -------------------------------------------------------------------
def test_render_size_past_the_memory_limit_is_refused():
    with pytest.raises(ResourceError, match="size: a 100000x100000 render needs about"):
        RenderSettings(size=100000).checked()


def test_render_refuses_a_huge_airy_psf():
    with pytest.raises(ResourceError, match="airy"):
        RenderSettings(size=64, setup=CameraSetup(psf=PSF.airy(1000, 550, 2.4))).checked()


@pytest.mark.parametrize("max_spp", [0, -4, 1 << 20, 2.5, True])
def test_render_max_spp_is_checked(max_spp):
    with pytest.raises(InputError, match="max_spp"):
        RenderSettings(size=64, max_spp=max_spp).checked()


@pytest.mark.parametrize("params", [{"converge": "maybe"}, {"converge": 1}, {"baseline_m": True},
                                    {"tilt_max_deg": "0.1"}, {"roll_max_deg": float("nan")}])
def test_geometry_values_are_type_checked(params):
    with pytest.raises(InputError, match="geometry"):
        RigTolerances.from_params(params)
    with pytest.raises(InputError):
        RenderSettings(size=64, geometry_params=params).checked()
    assert RigTolerances.from_params({"converge": False, "baseline_m": 0.1}).converge is False


# -- simulation inputs -------------------------------------------------------------------
@pytest.mark.parametrize("ranges", [dict(scale_max=2.0), dict(scale_max=0.5), dict(scale_max=float("nan")),
                                    dict(rotation_max_deg=90.0), dict(shift_max_px=1000.0), dict(shift_max_px=-1.0)])
def test_pose_ranges_are_checked(ranges):
    with pytest.raises(InputError):
        random_aperture_homographies(np.random.default_rng(0), (64, 64), **ranges)


def test_ground_truth_outside_unit_range_is_refused(caplog):
    gt = _gt()
    gt[3, 4, 5] = 1.7
    with pytest.raises(InputError, match=r"values in \[0.2.*, 1.7\].*Rescale"):
        prepare_ground_truth(gt)
    with caplog.at_level("WARNING", logger="capssim.simulate"):
        simulate_capture(gt, NoNoiseSensor())  # over-exposure, on purpose: the sensor saturates
    assert "above full scale (max 1.7)" in caplog.text
    gt[3, 4, 5] = -0.1
    with pytest.raises(InputError, match="-0.1"):
        prepare_ground_truth(gt)
    caplog.clear()
    with caplog.at_level("WARNING", logger="capssim.simulate"):
        simulate_capture(gt, NoNoiseSensor())  # the Python API keeps it: the sensor clips it to black
    assert "below 0 (min -0.1)" in caplog.text


def test_simulate_cli_refuses_a_ground_truth_above_full_scale(tmp_path):
    import tifffile

    gt = _gt()
    gt[0, 0, 0] = 2.5
    tifffile.imwrite(tmp_path / "gt.tiff", gt)
    result = runner.invoke(app, ["simulate", str(tmp_path / "gt.tiff"), "-o", str(tmp_path / "cap")])
    assert isinstance(result.exception, InputError) and "2.5" in str(result.exception)
    assert not (tmp_path / "cap").exists()


# -- reconstruction's psf_sigma ----------------------------------------------------------
@pytest.fixture(scope="module")
def capture32() -> Capture:
    return simulate_capture(_gt(), NoNoiseSensor(), seed=0)


def test_psf_sigma_minus_one_is_the_capture_psf_and_other_negatives_are_refused(capture32):
    kernel, record = method_psf(capture32, -1.0)
    assert record["source"] == "capture meta.json" and np.array_equal(kernel, capture32.psf_kernel())
    kernel, record = method_psf(capture32, 0.7)
    assert record["sigma_hr_px"] == 0.7
    for bad in (-2.0, -0.5, float("nan"), float("-inf"), "abc"):
        with pytest.raises(InputError, match="psf_sigma.*-1 \\(the capture's PSF"):
            method_psf(capture32, bad)
    with pytest.raises(ResourceError, match="psf_sigma"):
        method_psf(capture32, 1000.0)


# -- scoring thresholds and JSON ---------------------------------------------------------
def test_thresholds_are_checked_and_json_has_no_bare_nan():
    for bad in (dict(min_s0=float("nan")), dict(min_s0=-1.0), dict(min_s0=3.0), dict(min_dolp=float("inf")),
                dict(min_dolp=1.5)):
        with pytest.raises(InputError):
            check_thresholds(**bad)
    gt = _gt(48)
    with pytest.raises(InputError, match="min_s0"):
        score(gt, gt, min_s0=float("nan"))
    safe = json_safe({"a": float("nan"), "b": [np.float32(1.5), float("inf")], "c": {"d": np.int64(3)}})
    assert safe == {"a": None, "b": [1.5, None], "c": {"d": 3}}
    json.dumps(safe, allow_nan=False)


def test_evaluate_cli_refuses_nan_min_s0(tmp_path):
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--min-s0", "nan"])
    assert isinstance(result.exception, InputError) and "min_s0" in str(result.exception)
    assert not (tmp_path / "metrics.json").exists()


def test_demosaic_cli_refuses_bad_dolp_max(tmp_path):
    raw = tmp_path / "raw.png"
    raw.write_bytes(b"")
    for bad in ("-1", "0", "nan", "2"):
        result = runner.invoke(app, ["demosaic", str(raw), "-o", str(tmp_path / "out"), "--dolp-max", bad])
        assert isinstance(result.exception, InputError) and "--dolp-max" in str(result.exception)
    assert not (tmp_path / "out").exists()


# -- dataset sample counts ----------------------------------------------------------------
@pytest.mark.parametrize("dry_run", [True, False])
def test_dataset_refuses_a_sample_count_the_disk_cannot_hold(tmp_path, dry_run):
    import tifffile

    tifffile.imwrite(tmp_path / "gt.tiff", _gt(64))
    config = tmp_path / "c.yaml"
    config.write_text("seed: 0\nsamples: 1000000000\nsources:\n  - gt: gt.tiff\n    size: 32\n")
    args = ["dataset", str(config), "-o", str(tmp_path / "ds")] + (["--dry-run"] if dry_run else [])
    result = runner.invoke(app, args)
    assert isinstance(result.exception, ResourceError), result.output
    message = str(result.exception)
    assert message.startswith("samples:") and "1000000000 samples" in message and "TiB on disk" in message
    assert not (tmp_path / "ds").exists()


def test_dataset_refuses_more_local_workers_than_the_machine_can_start(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "gt.tiff", _gt(64))
    config = tmp_path / "c.yaml"
    config.write_text("seed: 0\nsamples: 2\nsources:\n  - gt: gt.tiff\n    size: 32\n")
    result = runner.invoke(app, ["dataset", str(config), "-o", str(tmp_path / "ds"), "--workers", "100000"])
    assert isinstance(result.exception, ResourceError), result.output
    assert str(result.exception).startswith("--workers:") and "per core" in str(result.exception)
    assert not (tmp_path / "ds").exists()


def test_freed_memory_the_process_keeps_counts_as_available(monkeypatch):
    """Inside reuse_freed_memory a freed large block stays in the process's heap; the system no longer counts
    it as available, the guard does (else NLSTR's re-check refuses mid-run what the process already holds)."""
    import torch

    import capssim.runtime.resources as resources
    from capssim.runtime.allocator import _glibc, held_free_bytes, reuse_freed_memory

    monkeypatch.setattr(resources, "held_free_bytes", lambda: 0)
    system = available_memory_bytes()
    if system is None:
        pytest.skip("the platform does not report its available memory")
    monkeypatch.setattr(resources, "held_free_bytes", lambda: 5 * 2**40)
    assert available_memory_bytes() - system == pytest.approx(5 * 2**40, abs=2**30)  # the system moves a little

    if _glibc() is None or not hasattr(_glibc(), "mallinfo2"):
        return  # held_free_bytes is 0 off glibc 2.33+
    block = 64 * 2**20
    with reuse_freed_memory() as active:
        if not active:
            pytest.skip("CAPSSIM_REUSE_FREED_MEMORY=0")
        x = torch.ones(block // 4)
        # measured with the block held: a heap that already keeps more than the block free may serve it
        # from there, so the free count before the allocation need not be below the count after the free
        held = held_free_bytes()
        del x
        assert held_free_bytes() - held >= block * 0.9
