"""The modules that moved into capssim's rooms keep working under their old dotted names (users' code)."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys

import pytest

import capssim
from capssim.captures.capture import read_capture, write_capture
from capssim.captures.capture_meta import SCHEMA
from capssim.eval.synthetic import texture_scene
from capssim.simulate import simulate_capture

#: old dotted name -> one public name that ``from <old name> import NAME`` must find
PUBLIC_NAME = {
    "capssim.array_geometry": "sub_image_matrix", "capssim.homography": "similarity",
    "capssim.psf": "gaussian_kernel_radius", "capssim.sensor": "make_sensor", "capssim.rig": "RigModel",
    "capssim.rig_checks": "check_vignetting", "capssim.rig_parts": "polarizer_reading",
    "capssim.camera_setup": "CameraSetup", "capssim.design": "DesignInputs",
    "capssim.measurement": "CameraArrayMeasurement", "capssim.capture": "read_capture",
    "capssim.capture_meta": "software_versions", "capssim.capture_schema": "MetaSchemaError",
    "capssim.imageio": "write_tiff", "capssim.output_paths": "describe_os_error", "capssim.schema": "ConfigError",
    "capssim.polarization": "stokes_from_intensities", "capssim.physical_validity": "ProjectionReport",
    "capssim.resources": "check_memory", "capssim.threads": "cpu_ids", "capssim.allocator": "reuse_freed_memory",
    "capssim.data_range": "warn_out_of_range",
    "capssim.eval.calibration": "calibrate_captures", "capssim.eval.calibration.calibrate": "load_calibration_set",
    "capssim.eval.calibration.flat_field": "fit_flat_field", "capssim.eval.calibration.geometry_fit": "fit_geometry",
    "capssim.eval.calibration.malus": "fit_malus", "capssim.eval.calibration.psf_fit": "fit_psf_sigmas",
    "capssim.eval.calibration.report": "write_report",
    "capssim.reconstruct.model.holdout": "HoldoutValidation",
    "capssim.reconstruct.model.polarization_filter": "filter_polarization",
    "capssim.reconstruct.model.polarization_evidence": "stokes_inconsistency_ratio",
}


def test_every_moved_module_is_named_here():
    assert sorted(PUBLIC_NAME) == sorted(capssim.MOVED_MODULES)


@pytest.mark.parametrize("old", sorted(PUBLIC_NAME))
def test_old_name_is_the_moved_module(old):
    new = capssim.MOVED_MODULES[old]
    module = importlib.import_module(old)
    assert module is importlib.import_module(new)
    assert module.__name__ == new and module.__spec__.name == new
    assert sys.modules[old] is module
    name = PUBLIC_NAME[old]
    namespace: dict = {}
    exec(f"from {old} import {name}", namespace)
    assert namespace[name] is getattr(module, name)
    if old.count(".") == 1:
        assert getattr(capssim, old.rsplit(".", 1)[1]) is module  # capssim.capture as an attribute


def test_old_names_in_a_fresh_interpreter():
    """``import capssim.capture`` first thing, and ``from capssim import sensor``, in a new process."""
    code = ("import capssim.capture, capssim.captures.capture as new; assert capssim.capture is new; "
            "from capssim.capture import read_capture; from capssim import sensor; "
            "from capssim.sensor import make_sensor; assert sensor.make_sensor is make_sensor; "
            "from capssim.rig import RigModel; "
            "assert RigModel.__module__ == 'capssim.camera.rig'")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_unknown_attribute_still_raises():
    with pytest.raises(AttributeError):
        capssim.no_such_module  # noqa: B018
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("capssim.no_such_module")


def test_file_formats_keep_their_names_when_code_moves(tmp_path):
    """A capture folder written before the rooms (``meta.json`` schema ``capssim.capture``) is still read: the
    schema names the file format, not the module that writes it."""
    assert SCHEMA == "capssim.capture"
    write_capture(tmp_path / "cap", simulate_capture(texture_scene(16, seed=0)[0], seed=0))
    meta = json.loads((tmp_path / "cap" / "meta.json").read_text())
    assert meta["schema"] == "capssim.capture"
    assert read_capture(tmp_path / "cap").caps_raw.shape == (4, 8, 8)
