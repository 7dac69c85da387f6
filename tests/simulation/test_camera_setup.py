"""One camera set-up value (capssim.camera.camera_setup.CameraSetup): simulate, render, the dataset writer and
calibration captures write the same meta.json "setup" block; old meta.json files load; bad values
give one-line errors; the command-line options are declared once."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from capssim.camera.camera_setup import SEED_RULE, CameraSetup, sensor_from_mapping
from capssim.camera.psf import DEFAULT_PSF, PSF
from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_capture, write_capture
from capssim.errors import InputError
from capssim.files.imageio import write_tiff
from capssim.simulate import simulate_capture

#: one set-up, as a user writes it in YAML (a dataset's defaults, a suite) or in Python
SETUP = {"sensor": {"noise": "gaussian", "sigma": 0.01}, "psf_sigma_hr_px": 0.7, "dofp_layout": "0-45-135-90",
         "extinction_ratio": 200, "rig": {"preset": "realistic", "seed": 3}}


def _written_block(capture, folder) -> dict:
    """The "setup" block of ``capture`` as written to and read back from ``folder/meta.json``."""
    write_capture(folder, capture)
    return json.loads((folder / "meta.json").read_text())["setup"]


@pytest.fixture(scope="module")
def setup() -> CameraSetup:
    return CameraSetup.from_mapping(SETUP)


def test_simulate_render_and_the_dataset_writer_write_one_setup_block(setup, scene64, tmp_path):
    pytest.importorskip("mitsuba")
    from capssim.dataset import load_config
    from capssim.dataset.generate import generate_dataset
    from capssim.render import render_capture

    blocks = {"simulate": _written_block(simulate_capture(scene64[:, :32, :32], setup, seed=1), tmp_path / "sim"),
              "render": _written_block(render_capture("siemens-star", size=32, spp=4, setup=setup,
                                                      record_timing=False), tmp_path / "render")}
    write_tiff(tmp_path / "gt.tiff", np.ascontiguousarray(scene64[:, 32:, 32:]))
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump({"seed": 5, "samples": 2, "defaults": SETUP, "sources": [
        {"gt": "gt.tiff", "size": 32}, {"scene": "siemens-star", "size": 32, "spp": 4}]}))
    generate_dataset(load_config(config), tmp_path / "dataset", workers=0)
    for index in (0, 1):
        meta = json.loads((tmp_path / "dataset" / "samples" / f"{index:06d}" / "meta.json").read_text())
        blocks[f"dataset sample {index} ({meta['kind']})"] = meta["setup"]
    expected = json.loads(json.dumps(setup.to_meta()))
    assert expected["sensor"]["noise"] == "gaussian" and expected["psf"] == {"type": "gaussian", "sigma_hr_px": 0.7}
    assert expected["rig"] is not None and expected["seed_rule"] == SEED_RULE
    for name, block in blocks.items():
        assert block == expected, name
    # the raw frames follow the set-up: a rendered capture's meta.json["psf"] is none, its set-up's the optics
    render_meta = json.loads((tmp_path / "render" / "meta.json").read_text())
    assert render_meta["psf"]["type"] == "none" and render_meta["render"]["optics_psf"] == expected["psf"]


def test_calibration_captures_write_the_setup_block(setup, tmp_path):
    from capssim.dataset.calibration_captures import make_calibration_captures

    index = make_calibration_captures(tmp_path / "set", setup=setup, size=32, polarizer_angles=3)
    expected = json.loads(json.dumps(setup.to_meta()))
    for entry in index["captures"]:
        assert read_capture(tmp_path / "set" / entry["folder"]).meta["setup"] == expected, entry["folder"]
    assert index["rig"] == setup.rig.to_dict()


def test_the_setup_drives_the_measurement(setup, scene64):
    """Simulating from the set-up value or from its parts gives the same bytes (one camera model)."""
    gt = scene64[:, :32, :32]
    from_setup = simulate_capture(gt, setup, seed=4)
    from_parts = simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=4, psf=PSF.gaussian(0.7),
                                  dofp_layout=[[0, 45], [135, 90]], extinction_ratio=200.0, rig=setup.rig)
    assert np.array_equal(from_setup.caps_raw, from_parts.caps_raw)
    assert np.array_equal(from_setup.dofp_raw, from_parts.dofp_raw)
    assert from_setup.setup == from_parts.setup == setup
    assert from_setup.meta["sensor"]["model"] == "gaussian" and from_setup.meta["dofp_layout_name"] == "0-45-135-90"


def test_an_old_meta_json_without_the_block_still_loads(setup, scene64, tmp_path):
    folder = tmp_path / "old"
    write_capture(folder, simulate_capture(scene64[:, :32, :32], setup, seed=1))
    meta = json.loads((folder / "meta.json").read_text())
    del meta["setup"]
    (folder / "meta.json").write_text(json.dumps(meta))
    old = read_capture(folder)
    assert "setup" not in old.meta and old.setup == setup
    # an old rendered capture: its set-up's PSF is the optics PSF the renderer applied
    meta.update(kind="rendered", psf={"type": "none", "note": "in gt.tiff"},
                render={"optics_psf": {"type": "gaussian", "sigma_hr_px": 0.7}})
    assert CameraSetup.from_meta(meta) == setup
    meta["render"]["optics_psf"] = {"type": "airy", "f_number": 2.0, "wavelength_nm": 550.0, "hr_pixel_um": 2.4}
    assert CameraSetup.from_meta(meta).psf == PSF.airy(2.0, 550.0, 2.4)


@pytest.mark.parametrize("mapping, match", [
    ({"sensor": {"noise": "gauss"}}, r"setup\.sensor\.noise: got 'gauss'; expected one of none, gaussian"),
    ({"sensor": {"noise": "gaussian"}}, r"setup\.sensor\.sigma: .*--sigma 0\.01"),
    ({"sensor": {"noise": "poisson-gaussian", "preset": "nikon"}}, r"setup\.sensor\.preset: got 'nikon'.*imx250myr"),
    ({"sensor": {"noise": "gaussian", "sigma": 0.01, "gain": 2}}, r"setup\.sensor: got keys \['gain', 'sigma'\]"),
    ({"sensor": {"noise": "gaussian", "model": "none"}}, r"setup\.sensor\.model: .*remove 'model'"),
    ({"psf_sigma_hr_px": -1}, r"setup\.psf_sigma_hr_px: got -1; expected a finite number >= 0"),
    ({"psf_sigma_hr_px": 0.5, "psf": {"type": "none"}}, r"setup\.psf_sigma_hr_px: .*Give one of"),
    ({"psf": {"type": "disc"}}, r"setup\.psf\.type: got disc"),
    ({"dofp_layout": "0-45-90-90"}, r"setup\.dofp_layout: got .*each of 0, 45, 90, 135 degrees once"),
    ({"extinction_ratio": 0.5}, r"setup\.extinction_ratio: got 0\.5; expected a number >= 1"),
    ({"rig": {"preset": "perfect"}}, r"setup\.rig: got 'perfect'; expected a preset name"),
    ({"rig": {"gain": [1, 2]}}, r"setup\.rig\.gain: got shape \(2,\)"),
    ({"psf_sigma": 0.5}, r"setup\.psf_sigma: got an unknown key; expected one of sensor, psf_sigma_hr_px"),
    ({"seed_rule": "mine"}, r"setup\.seed_rule: got 'mine'"),
])
def test_bad_values_give_one_line_errors(mapping, match):
    with pytest.raises(InputError, match=match) as info:
        CameraSetup.from_mapping(mapping)
    assert "\n" not in str(info.value)


def test_defaults_and_round_trips():
    default = CameraSetup()
    assert default == CameraSetup.from_mapping({}) == CameraSetup.from_meta({"setup": default.to_meta()})
    assert default.psf == DEFAULT_PSF and default.noise == "none" and default.rig is None
    preset = sensor_from_mapping({"noise": "poisson-gaussian"})
    assert preset.preset == "imx250myr" and preset.read_noise_e == 2.5
    for mapping in (SETUP, {"sensor": {"noise": "poisson-gaussian", "preset": "python1300", "exposure": 0.5},
                            "psf": {"type": "airy", "f_number": 2.8, "wavelength_nm": 550.0, "hr_pixel_um": 2.4}}):
        value = CameraSetup.from_mapping(mapping)
        again = CameraSetup.from_mapping(json.loads(json.dumps(value.to_meta())))
        assert again == value and again.sensor == value.sensor
    assert CameraSetup.from_mapping({"sensor": {"noise": "gaussian", "sigma": 0.02}}) != CameraSetup()


def test_datasets_spell_the_sensor_as_the_setup_does():
    from capssim.camera.camera_setup import SENSOR_KEYS, SETUP_KEYS
    from capssim.dataset.config_specs import SENSOR_SPEC, SHARED_KEYS

    assert tuple(SENSOR_SPEC.fields) == SENSOR_KEYS
    assert set(SHARED_KEYS) - {"pose"} <= set(SETUP_KEYS)


def test_the_command_line_declares_the_setup_options_once():
    import typer

    from capssim.cli import app
    from capssim.cli._setup_options import SETUP_PARAMETERS, SetupOptions

    assert [p.name for p in SETUP_PARAMETERS] == list(SetupOptions.__dataclass_fields__)
    assert SetupOptions().camera_setup() == CameraSetup()  # the options' defaults are the set-up's
    root = typer.main.get_command(app)
    expected = None
    for name in ("simulate", "render", "calibration-captures"):
        command = root.commands[name]
        flags = {opt for param in command.params for opt in param.opts
                 if param.name in {p.name for p in SETUP_PARAMETERS}}
        expected = flags if expected is None else expected
        assert flags == expected and {"--noise", "--psf-sigma-hr-px", "--dofp-layout", "--rig"} <= flags, name
    dofp = root.commands["bench"].commands["dofp"]
    assert any("--psf-sigma-hr-px" in param.opts for param in dofp.params)
