"""Issue 60 ("Hardening, third round"), item 2: a capture describes its camera once.

The top-level keys of ``meta.json`` (``sensor``, ``psf``, ``dofp_layout``, ``extinction_ratio``, ``rig``)
are what ``reconstruct`` reads; the ``setup`` block repeats them and is what the error budget's
model-exact rung builds its camera from. Each row edits one ``setup`` field of a capture: the edit is
either refused (one line naming the file, the key and both values), or accepted, and then the
reconstruction's view of the camera and the model-exact rung's are the same.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from support.fuzz import edited_capture, invoke, one_line_error, set_key, small_gaussian_capture

from capssim.camera.rig import RigModel
from capssim.captures.capture import read_capture
from capssim.conventions import dofp_layout
from capssim.eval.error_budget.oracles import _measurement


@dataclass(frozen=True)
class Edit:
    name: str
    edit: Callable[[dict], None]  #: edits the parsed meta.json in place
    fragments: tuple = ()  #: words of the one-line refusal; empty: the edit is accepted

    def __str__(self):
        return self.name.replace(" ", "-")


def _drop(*keys):
    def edit(meta):
        for key in keys[:-1]:
            meta = meta[key]
        del meta[keys[-1]]
    return edit


def _both(*edits):
    def edit(meta):
        for one in edits:
            one(meta)
    return edit


RIG = RigModel.from_spec({"preset": "realistic", "seed": 3}).to_dict()

EDITS = [
    # contradictions: refused, naming the key and both values
    Edit("psf sigma 3 against 0.5", set_key("setup", "psf", "sigma_hr_px", value=3.0),
         ("'setup.psf.sigma_hr_px'", "got 3.0", "expected 0.5", "top-level psf.sigma_hr_px")),
    Edit("psf type none", set_key("setup", "psf", value={"type": "none"}), ("'setup.psf.type'", "got \"none\"")),
    Edit("psf_sigma_hr_px instead of psf", _both(_drop("setup", "psf"), set_key("setup", "psf_sigma_hr_px", value=2.0)),
         ("'setup.psf_sigma_hr_px'", "got 2.0", "expected 0.5")),
    Edit("extinction ratio 5 against ideal", set_key("setup", "extinction_ratio", value=5),
         ("'setup.extinction_ratio'", "got 5.0", "expected null")),
    Edit("sensor sigma", set_key("setup", "sensor", "sigma", value=0.2),
         ("'setup.sensor.sigma'", "got 0.2", "expected 0.01")),
    Edit("sensor bit depth", _both(set_key("setup", "sensor", "bit_depth", value=12),
                                   set_key("setup", "sensor", "white_level", value=4095.0)),
         ("'setup.sensor.bit_depth'", "got 12", "expected 16")),
    Edit("sensor of another model", set_key("setup", "sensor", value={"noise": "none"}),
         ("'setup.sensor.noise'", "got \"none\"", "expected \"gaussian\"", "top-level sensor.model")),
    Edit("dofp layout", set_key("setup", "dofp_layout", value="0-45-135-90"),
         ("'setup.dofp_layout'", "got \"0-45-135-90\"", "expected \"sony\"")),
    Edit("rig where the top level has none", set_key("setup", "rig", value=RIG), ("'setup.rig", "expected")),
    Edit("seed rule", set_key("setup", "seed_rule", value="mine"), ("'setup.seed_rule'", "got 'mine'")),
    Edit("unknown key", set_key("setup", "extinction", value=5), ("'setup.extinction'", "unknown key")),
    Edit("setup that is a list", set_key("setup", value=[1]), ("setup",)),
    # accepted: the key is derived from the top level, or both say the same
    Edit("psf removed", _drop("setup", "psf")),
    Edit("sensor removed", _drop("setup", "sensor")),
    Edit("extinction ratio removed", _drop("setup", "extinction_ratio")),
    Edit("dofp layout removed", _drop("setup", "dofp_layout")),
    Edit("rig removed", _drop("setup", "rig")),
    Edit("setup removed", _drop("setup")),
    Edit("setup null", set_key("setup", value=None)),
    Edit("extinction ratio 5 in both", _both(set_key("setup", "extinction_ratio", value=5),
                                             set_key("extinction_ratio", value=5.0))),
    Edit("psf sigma 1.5 in both", _both(set_key("setup", "psf", "sigma_hr_px", value=1.5),
                                        set_key("psf", "sigma_hr_px", value=1.5))),
    Edit("psf as psf_sigma_hr_px", _both(_drop("setup", "psf"), set_key("setup", "psf_sigma_hr_px", value=0.5))),
    Edit("the same rig in both", _both(set_key("setup", "rig", value=RIG), set_key("rig", value=RIG))),
    Edit("layout changed at the top level only", _both(_drop("setup", "dofp_layout"), _drop("dofp_layout_name"),
                                                      set_key("dofp_layout", value=[[0, 45], [135, 90]]))),
    Edit("extinction ratio 20 at the top level only", _both(_drop("setup", "extinction_ratio"),
                                                            set_key("extinction_ratio", value=20.0))),
]


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    return small_gaussian_capture(tmp_path_factory.mktemp("h3") / "capture")


@pytest.mark.parametrize("row", EDITS, ids=str)
def test_each_setup_edit_is_refused_or_agrees_with_the_reconstruction(row, capture_dir, tmp_path):
    folder = edited_capture(capture_dir, tmp_path / "cap", row.edit)
    if row.fragments:
        with pytest.raises(Exception) as info:
            read_capture(folder)
        message = one_line_error(info.value)
        assert str(folder / "meta.json") in message, message
        for fragment in row.fragments:
            assert fragment in message, (fragment, message)
        return
    capture = read_capture(folder)
    model = _measurement(capture, noise=True)  # the error budget's model-exact rung
    assert model.sensor == capture.sensor  # reconstruct: Capture.sensor, .psf, .dofp_layout, meta's ratio and rig
    assert model.psf == capture.psf
    assert np.array_equal(dofp_layout(model.dofp_layout), capture.dofp_layout)
    assert model.extinction_ratio == capture.extinction_ratio
    assert (model.rig.to_dict() if model.rig is not None else None) == (
        capture.rig.to_dict() if capture.rig is not None else None)


def test_the_rung_follows_an_edit_of_the_top_level(capture_dir, tmp_path):
    """Not vacuous: an edit the table accepts reaches both readers."""
    folder = edited_capture(capture_dir, tmp_path / "cap", EDITS[[e.name for e in EDITS].index(
        "extinction ratio 20 at the top level only")].edit)
    capture = read_capture(folder)
    assert capture.extinction_ratio == 20.0 and _measurement(capture, noise=True).extinction_ratio == 20.0


def test_a_folder_of_captures_names_the_capture_with_the_bad_setup(capture_dir, tmp_path):
    shutil.copytree(capture_dir, tmp_path / "many" / "a")
    edited_capture(capture_dir, tmp_path / "many" / "b", set_key("setup", "psf", "sigma_hr_px", value=3.0))
    outcome, message = invoke(["reconstruct", tmp_path / "many", "-m", "dofp-bilinear"])
    assert outcome == "error", message
    assert str(tmp_path / "many" / "b" / "meta.json") in message and "setup.psf.sigma_hr_px" in message, message
    assert not (tmp_path / "many" / "a" / "recon").exists()  # refused before any work
