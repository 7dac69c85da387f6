"""Issue 34 ("Hardening, second round"), the capture files: classes 2, 6, 7 and 12 (``calibrate A A``).

Table-driven: each :class:`Row` names its class from the issue. A hand-edited ``meta.json``, rig
file or calibration file either exits 2 with one line naming the file and the key (never a
traceback), or gives a correct result and a warning. The valid files written by capssim keep
loading (the regression check covers their numbers).
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest
from support.fuzz import edited_capture, invoke, set_key, small_gaussian_capture

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.rig import RigModel, read_rig_json, write_rig_json
from capssim.captures.capture import read_capture
from capssim.errors import CaptureFormatError, InputError


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    edit: Callable  # edits the parsed file in place (or returns the new text)
    fragments: tuple = ()  # in the one-line message

    def __str__(self):
        return f"class{self.cls}-{self.name.replace(' ', '-')}"


def _nested(data):
    return "[" * 200_000 + "]" * 200_000


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    return small_gaussian_capture(tmp_path_factory.mktemp("h2") / "capture")


# -- meta.json (classes 6 and 7) ------------------------------------------------------------------------
META_ROWS = [
    Row(6, "nesting 200000 deep", _nested, ("meta.json", "nested more than")),
    Row(6, "calibration file a number", set_key("calibration_file", value=12345), ("'calibration_file'", "12345")),
    Row(6, "star cycles a word", set_key("scene", value={"star": {"cycles": "abc"}}), ("'scene.star.cycles'", "abc")),
    Row(6, "star cycles zero", set_key("scene", value={"star": {"cycles": 0}}), ("'scene.star.cycles'", ">= 1")),
    Row(6, "source star cycles negative", set_key("source", value={"star": {"cycles": -3}}), ("'source.star.cycles'",)),
    Row(6, "geometry a list", set_key("geometry", value=[1, 2]), ("'geometry'",)),
    Row(6, "seed a word", set_key("seed", value="seven"), ("'seed'",)),
    Row(6, "misspelt cfa key", set_key("cfaa", value="RGGB"), ("'cfaa'", "Did you mean 'cfa'")),
    Row(7, "unknown cfa", set_key("cfa", value="RGBW"), ("'cfa'", "BGGR")),
    Row(7, "cfa BGGR with RGGB lr_images", set_key("cfa", value="BGGR"), ("'lr_images[0].colour'", "cfa BGGR")),
    Row(7, "polarizer angles 0 30 60 90", set_key("polarizer_angles_deg", value=[0, 30, 60, 90]),
        ("'polarizer_angles_deg'", "[0, 45, 90, 135]")),
    Row(7, "layout name contradicts layout", set_key("dofp_layout_name", value="0-45-135-90"),
        ("'dofp_layout_name'", "contradict")),
    Row(7, "lr_images angle", set_key("lr_images", 5, "polarizer_deg", value=90), ("'lr_images[5].polarizer_deg'",)),
    Row(7, "lr_images aperture", set_key("lr_images", 5, "aperture", value=3), ("'lr_images[5].aperture'",)),
    Row(7, "lr_images site", set_key("lr_images", 5, "bayer_offset_rowcol", value=[1, 1]),
        ("'lr_images[5].bayer_offset_rowcol'",)),
    Row(7, "sr factor 3", set_key("geometry", "sr_factor", value=3), ("'geometry.sr_factor'", "2")),
    Row(7, "kind bogus", set_key("kind", value="bogus"), ("'kind'", "simulated")),
    Row(2, "extinction ratio 1", set_key("extinction_ratio", value=1.0), ("'extinction_ratio'",)),
    Row(2, "singular aperture homography", set_key("aperture_homographies", 1, value=[[0, 0, 0], [0, 0, 0], [0, 0, 1]]),
        ("'aperture_homographies[1]'", "singular")),
]


@pytest.mark.parametrize("row", META_ROWS, ids=str)
def test_meta_json_edit_is_refused_with_one_line(row, capture_dir, tmp_path):
    path = edited_capture(capture_dir, tmp_path / "c", row.edit)
    with pytest.raises(CaptureFormatError) as info:  # also a ConfigError: exit 2, one line
        read_capture(path)
    message = str(info.value)
    assert "\n" not in message and "meta.json" in message and str(path) in message, message
    for fragment in row.fragments:
        assert fragment in message, message
    for command in (["reconstruct", path, "-m", "dofp-bilinear", "--no-progress"], ["evaluate", path]):
        outcome, text = invoke(command)
        assert outcome == "error" and "meta.json" in text, (command, text)


def test_valid_meta_still_loads_and_old_files_without_new_keys(capture_dir, tmp_path):
    path = edited_capture(capture_dir, tmp_path / "c", lambda m: [m.pop(k) for k in ("cfa", "dofp_layout_name", "kind",
                                                                               "polarizer_angles_deg")])
    capture = read_capture(path)
    assert capture.cfa == "RGGB"
    path = edited_capture(capture_dir, tmp_path / "d", set_key("render", value={"any": ["provenance", 1]}))
    assert read_capture(path).meta["render"] == {"any": ["provenance", 1]}


# -- rig and calibration files (class 2, and class 6 for their syntax) ----------------------------------
def _rig_file(path: Path, edit) -> Path:
    write_rig_json(path, RigModel.preset("realistic", seed=0), geometry=ArrayGeometry.identity((32, 32)))
    data = json.loads(path.read_text())
    text = edit(data)
    path.write_text(text if isinstance(text, str) else json.dumps(data))
    return path


def _vignetting(value):
    def edit(data):
        coef = data["rig"]["vignetting"]["coefficients"]
        data["rig"]["vignetting"]["coefficients"] = [[value] * len(coef[0]) if value == 0 else
                                                     [value] + row[1:] for row in coef]
    return edit


def _homography(matrix):
    return set_key("geometry", "aperture_homographies", 2, value=matrix)


RIG_ROWS = [
    Row(2, "vignetting coefficient -1", _vignetting(-1.0), ("rig vignetting", "flat field")),
    Row(2, "all-zero vignetting", _vignetting(0), ("rig vignetting", "flat field")),
    Row(2, "extinction ratio below 1", set_key("rig", "extinction_ratio", value=[[0.5] * 3] * 4),
        ("extinction_ratio",)),
    Row(2, "gain zero", set_key("rig", "gain", value=[1, 0, 1, 1]), ("gain",)),
    Row(2, "singular homography", _homography([[0, 0, 0], [0, 0, 0], [0, 0, 1]]),
        ("geometry.aperture_homographies[2]", "singular")),
    Row(2, "horizon across the image", _homography([[1, 0, 0], [0, 1, 0], [-0.1, 0, 1]]),
        ("geometry.aperture_homographies[2]", "horizon")),
    Row(2, "non-finite homography", _homography([[1, 0, 0], [0, 1, 0], [0, 0, "inf"]]), ("geometry",)),
    Row(6, "nesting 200000 deep", _nested, ("nested more than",)),
    Row(6, "misspelt key", set_key("geometri", value=None), ("'geometri'", "Did you mean 'geometry'")),
    Row(6, "geometry size a word", set_key("geometry", "hr_height", value="big"), ("'geometry.hr_height'",)),
]


@pytest.mark.parametrize("row", RIG_ROWS, ids=str)
def test_impossible_rig_file_is_refused_by_simulate(row, tmp_path, write_gt_folder):
    rig = _rig_file(tmp_path / "rig.json", row.edit)
    with pytest.raises(InputError) as info:
        read_rig_json(rig, argument="--rig")
    message = str(info.value)
    assert "\n" not in message and "rig.json" in message, message
    for fragment in row.fragments:
        assert fragment in message, message
    gt = write_gt_folder(tmp_path / "gt", size=32, seed=1)
    outcome, text = invoke(["simulate", gt, "-o", tmp_path / "out", "--rig", rig])
    assert outcome == "error" and "rig.json" in text, text
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("row", [r for r in RIG_ROWS if r.cls == 2][:2] + [RIG_ROWS[4]], ids=str)
def test_impossible_calibration_file_is_refused_by_reconstruct(row, capture_dir, tmp_path):
    path = edited_capture(capture_dir, tmp_path / "c", set_key("calibration_file", value="calibration.json"))
    _rig_file(path / "calibration.json", row.edit)
    outcome, text = invoke(["reconstruct", path, "-m", "caps-naive", "--no-progress"])
    assert outcome == "error" and "calibration.json" in text, text
    assert not (path / "recon").exists()


def test_valid_rig_files_still_load(tmp_path):
    loaded = read_rig_json(_rig_file(tmp_path / "realistic.json", lambda d: None))
    assert loaded.geometry is not None and not loaded.rig.is_ideal
    for seed in range(20):  # every draw of the realistic preset is physically valid
        RigModel.preset("realistic", seed=seed)


# -- calibrate A A (class 12) ---------------------------------------------------------------------------
def test_calibrate_the_same_capture_twice_counts_it_once(tmp_path, caplog):
    from capssim.reconstruct.calibration.calibrate import load_calibration_set

    outcome, text = invoke(["calibration-captures", "-o", tmp_path / "set", "--size", 32, "--frames", 1,
                            "--polarizer-angles", 3])
    assert outcome == "ok", text
    flat = sorted(p for p in (tmp_path / "set").iterdir() if p.is_dir() and "flat" in p.name)[0]
    with caplog.at_level(logging.WARNING):
        groups = load_calibration_set([flat, flat])
    assert len(groups["flat"]) == 1 and "counted once" in caplog.text
    copy = tmp_path / "copy"
    shutil.copytree(flat, copy)
    assert len(load_calibration_set([flat, copy])["flat"]) == 1  # a copy is the same capture
    other = sorted(p for p in (tmp_path / "set").iterdir() if p.is_dir() and "flat" not in p.name)[0]
    assert sum(len(g) for g in load_calibration_set([flat, other]).values()) == 2  # distinct ones are kept
