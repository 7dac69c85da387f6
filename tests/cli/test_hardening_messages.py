"""Issue 21, "Every message a message" and "Leftovers": bad paths, seeds, scene parameters and
meta.json fields give one-line errors (exit 2, no traceback); killed writers' temporaries are
removed by the next run; a dataset dry run checks every sample; a shrunk dataset is refused."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_meta, write_capture
from capssim.cli import main
from capssim.dataset import load_config
from capssim.dataset.generate import generate_dataset
from capssim.errors import CaptureFormatError, InputError
from capssim.files.imageio import _HOST_TAG, atomic_directory, atomic_write_text, remove_stale_temporaries
from capssim.render.scene_base import _coerce_param
from capssim.simulate import simulate_capture


def run_cli(args: list[str], capsys, monkeypatch) -> tuple[int, str]:
    """``capssim ARGS`` in this process: exit status and stderr."""
    monkeypatch.setattr(sys, "argv", ["capssim", *map(str, args)])
    handlers = logging.root.handlers[:]
    try:
        with pytest.raises(SystemExit) as exit_info:
            main()
    finally:  # the CLI points logging at this test's captured stderr; give the old handlers back
        logging.root.handlers[:] = handlers
    return exit_info.value.code, capsys.readouterr().err


def assert_user_error(status: int, err: str, *fragments: str) -> None:
    assert status == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for fragment in fragments:
        assert fragment in lines[0], err


@pytest.fixture
def gt_dir(write_gt_folder, tmp_path) -> Path:
    return write_gt_folder(tmp_path / "gt", size=32, seed=1)


@pytest.fixture
def a_file(tmp_path) -> Path:
    path = tmp_path / "a-file"
    path.write_text("not a folder")
    return path


# -- output paths -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["simulate", "demosaic", "render", "dataset"])
def test_output_under_a_file_is_refused_before_any_work(command, gt_dir, a_file, tmp_path, capsys, monkeypatch):
    out = a_file / "out"
    args = {"simulate": ["simulate", gt_dir, "-o", out, "--crop", 16],
            "demosaic": ["demosaic", tmp_path / "missing.png", "-o", out],
            "render": ["render", "siemens-star", "-o", out, "--size", 16, "--spp", 1],
            "dataset": ["dataset", tmp_path / "missing.yaml", "-o", out]}[command]
    assert_user_error(*run_cli(args, capsys, monkeypatch), "-o/--output", str(a_file))


def test_output_in_a_system_folder_is_refused(gt_dir, capsys, monkeypatch):
    if not Path("/sys").is_dir():
        pytest.skip("no /sys on this system")
    assert_user_error(*run_cli(["simulate", gt_dir, "-o", "/sys/capssim-test"], capsys, monkeypatch),
                      "-o/--output", "/sys")


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root may write a read-only folder")
def test_output_in_a_read_only_folder_is_refused(gt_dir, tmp_path, capsys, monkeypatch):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        assert_user_error(*run_cli(["simulate", gt_dir, "-o", locked / "out"], capsys, monkeypatch),
                          "-o/--output", str(locked))
    finally:
        locked.chmod(0o700)


def test_preview_path_is_checked_before_rendering(a_file, tmp_path, capsys, monkeypatch):
    out = tmp_path / "cap"
    status, err = run_cli(["render", "siemens-star", "-o", out, "--size", 16, "--spp", 1,
                           "--preview", a_file / "p.png"], capsys, monkeypatch)
    assert_user_error(status, err, "--preview", str(a_file))
    assert not out.exists()


# -- seeds and scene parameters ------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["simulate", "render"])
def test_negative_seed_is_refused(command, gt_dir, tmp_path, capsys, monkeypatch):
    head = ["simulate", gt_dir] if command == "simulate" else ["render", "siemens-star"]
    status, err = run_cli([*head, "-o", tmp_path / "out", "--seed", -1], capsys, monkeypatch)
    assert_user_error(status, err, "--seed", "-1", str(2**63 - 1))


def test_scene_parameter_of_the_wrong_type_is_refused(tmp_path, capsys, monkeypatch):
    status, err = run_cli(["render", "polarization-star", "-o", tmp_path / "out", "--size", 16, "--spp", 1,
                           "--param", "cycles=abc"], capsys, monkeypatch)
    assert_user_error(status, err, "scene_params.cycles", "'abc'", "an integer")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value, default, expected", [("72", 72, 72), (36.0, 72, 36), ("0.5", 0.9, 0.5),
                                                      ("yes", True, True), ("off", True, False), ("gold", "x", "gold")])
def test_scene_parameters_are_coerced_to_their_defaults_type(value, default, expected):
    got = _coerce_param("scene_params.p", value, default)
    assert got == expected and type(got) is type(expected)


@pytest.mark.parametrize("value, default", [("abc", 72), (2.5, 72), ([1, 2], 72), ({"a": 1}, 0.5), ("nan", 0.5),
                                            (True, 72), ("maybe", True), (None, 1.0)])
def test_scene_parameters_of_the_wrong_type_are_input_errors(value, default):
    with pytest.raises(InputError, match="scene_params.p"):
        _coerce_param("scene_params.p", value, default)


# -- meta.json field types -----------------------------------------------------------------------------------
@pytest.fixture
def capture_dir(smooth_random_scene, tmp_path) -> Path:
    capture = simulate_capture(smooth_random_scene(16, seed=3), make_sensor("gaussian", sigma=0.01), seed=1)
    return write_capture(tmp_path / "cap", capture)


def _rewrite(capture_dir: Path, change) -> None:
    path = capture_dir / "meta.json"
    meta = json.loads(path.read_text())
    meta = change(meta)
    path.write_text(json.dumps(meta))


def _set(key, value, *, under=None):
    def change(meta):
        (meta[under] if under else meta)[key] = value
        return meta
    return change


@pytest.mark.parametrize("change, fragments", [
    (lambda meta: [meta], ("meta.json: got a list", "a JSON object")),
    (_set("files", None), ("key 'files': got None", "file names")),
    (_set("files", {"caps_raw": 3}), ("key 'files.caps_raw': got 3", "a non-empty string")),
    (_set("aperture_homographies", "abc"), ("aperture_homographies: got a string \"abc\"", "4 x 3 x 3")),
    (_set("aperture_homographies", [[1, 0, 0]]), ("aperture_homographies", "4 x 3 x 3 finite numbers")),
    (_set("hr_height", "32", under="geometry"), ("key 'geometry.hr_height': got '32'", "an integer")),
    (_set("raw_width", 7.5, under="geometry"), ("key 'geometry.raw_width': got 7.5", "an integer")),
    (_set("geometry", [1, 2]), ("key 'geometry': got [1, 2]", "hr_height")),
    (_set("lr_images", "x"), ("key 'lr_images': got 'x'", "16 lr_images entries")),
    (_set("sensor", "gaussian"), ("key 'sensor': got 'gaussian'", "'model'")),
    (_set("bit_depth", "twelve", under="sensor"), ("meta.json sensor", "twelve")),
    (_set("sigma", [1], under="sensor"), ("meta.json sensor", "sigma")),
    (_set("flavour", 1, under="sensor"), ("meta.json sensor", "flavour")),
    (_set("model", "fancy", under="sensor"), ("meta.json sensor", "fancy")),
    (_set("psf", {"type": "gaussian", "sigma_hr_px": "wide"}), ("meta.json psf", "wide")),
    (_set("seed", -3), ("key 'seed': got -3", "an integer >= 0")),
    (_set("extinction_ratio", "high"), ("key 'extinction_ratio'", "a finite number > 1")),
])
def test_meta_json_fields_of_the_wrong_type_are_capture_format_errors(capture_dir, change, fragments):
    read_meta(capture_dir)  # valid before the change
    _rewrite(capture_dir, change)
    with pytest.raises(CaptureFormatError) as info:
        read_meta(capture_dir)
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)


def test_meta_json_type_errors_reach_the_cli_as_one_line(capture_dir, capsys, monkeypatch):
    _rewrite(capture_dir, _set("files", None))
    status, err = run_cli(["reconstruct", capture_dir, "-m", "dofp-bilinear"], capsys, monkeypatch)
    assert_user_error(status, err, "meta.json", "'files'")


def test_homographies_that_disagree_are_still_refused(capture_dir):
    def change(meta):
        meta["lr_images"][5]["homography"][0][2] += 3.0
        return meta
    _rewrite(capture_dir, change)
    with pytest.raises(CaptureFormatError):
        read_meta(capture_dir)


# -- leftovers -----------------------------------------------------------------------------------------------
KILLED_WRITER = """
import os, signal, sys
from capssim.files.imageio import atomic_directory
with atomic_directory(sys.argv[1]) as tmp:
    (tmp / "half-written.tiff").write_bytes(b"x" * 100)
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_writers_temporary_folder_is_removed_by_the_next_run(tmp_path):
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(out)], capture_output=True)
    assert done.returncode == -9
    left = [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.tmp-")]
    assert len(left) == 1 and not out.exists()
    # a live writer's temporary (this process's parent) must survive
    live = tmp_path / left[0].replace(left[0].split("-")[2], str(os.getppid()), 1)
    live.mkdir()
    with atomic_directory(out) as tmp:
        (tmp / "meta.json").write_text("{}")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(["out", live.name]), names
    assert remove_stale_temporaries(out) == []


DRY_RUN = """
name: dry
seed: 1
samples: 3
sources:
  - gt: gt
    size: 16
  - scene: polarization-star
    size: {size}
    spp: {spp}
    scene_params: {{cycles: {cycles}}}
"""


@pytest.mark.parametrize("size, spp, cycles, fragments", [
    (16, 4, "{choice: [1, 2]}", ("scene_params.cycles", "[4, 1000]")),
    (16, 100000, 36, ("spp", "65536")),
    (4096, 4, 36, ("size",)),
])
def test_dry_run_checks_every_drawn_sample(size, spp, cycles, fragments, gt_dir, tmp_path, capsys, monkeypatch):
    config = tmp_path / "config.yaml"
    config.write_text(textwrap.dedent(DRY_RUN.format(size=size, spp=spp, cycles=cycles)))
    assert_user_error(*run_cli(["dataset", config, "--dry-run"], capsys, monkeypatch), *fragments)


def test_dry_run_checks_the_crop_of_ground_truth_sources(gt_dir, tmp_path, capsys, monkeypatch):
    config = tmp_path / "config.yaml"
    config.write_text("seed: 1\nsamples: 2\nsources:\n  - gt: gt\n    size: 64\n")
    assert_user_error(*run_cli(["dataset", config, "--dry-run"], capsys, monkeypatch),
                      "size of source", "at most the ground-truth size 32x32")
    config.write_text("seed: 1\nsamples: 2\nsources:\n  - gt: gt\n    size: 16\n")
    status, _ = run_cli(["dataset", config, "--dry-run"], capsys, monkeypatch)
    assert status == 0


def test_a_rerun_with_fewer_samples_is_refused_and_changes_nothing(gt_dir, tmp_path):
    config = tmp_path / "config.yaml"
    config.write_text("seed: 1\nsamples: 3\nsources:\n  - gt: gt\n    size: 16\n")
    out = tmp_path / "out"
    assert generate_dataset(load_config(config), out, workers=0).complete
    before = (out / "dataset.json").read_bytes(), (out / "manifest.jsonl").read_bytes()
    config.write_text("seed: 1\nsamples: 2\nsources:\n  - gt: gt\n    size: 16\n")
    with pytest.raises(InputError, match=r"samples: got 2; expected at least 3: samples 2 of"):
        generate_dataset(load_config(config), out, workers=0)
    assert ((out / "dataset.json").read_bytes(), (out / "manifest.jsonl").read_bytes()) == before
    assert sorted(p.name for p in (out / "samples").iterdir()) == ["000000", "000001", "000002"]
    # more samples is fine, and the folder, manifest and dataset.json agree
    config.write_text("seed: 1\nsamples: 4\nsources:\n  - gt: gt\n    size: 16\n")
    assert generate_dataset(load_config(config), out, workers=0).complete
    assert json.loads((out / "dataset.json").read_text())["samples"] == 4


def test_valid_seed_and_output_still_work(gt_dir, tmp_path, capsys, monkeypatch):
    out = tmp_path / "cap"
    status, err = run_cli(["simulate", gt_dir, "-o", out, "--crop", 16, "--seed", 2**63 - 1],
                          capsys, monkeypatch)
    assert status == 0, err
    assert json.loads((out / "meta.json").read_text())["seed"] == 2**63 - 1
    assert np.asarray(json.loads((out / "meta.json").read_text())["aperture_homographies"]).shape == (4, 3, 3)


def test_a_killed_file_writers_temporary_is_removed_and_files_in_system_folders_are_refused(tmp_path):
    target = tmp_path / "record.json"
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".record.json.tmp-{_HOST_TAG}-{int(done.stdout)}-abcd1234"
    stale.write_text("half")
    atomic_write_text(target, "{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["record.json"]
    if Path("/sys").is_dir():
        with pytest.raises(InputError, match="/sys"):
            atomic_write_text("/sys/capssim-test.json", "{}")


def test_option_placeholders_name_what_to_type_not_python_types():
    import re

    from typer.testing import CliRunner

    from capssim.cli import app

    commands = ["simulate", "render", "reconstruct", "evaluate", "demosaic", "dataset", "gt-check", "mtf", "design",
                "scenes"] + [f"bench {s}" for s in ("suite", "reconstruct", "registration", "dofp", "render", "dataset")]
    for command in commands:
        result = CliRunner().invoke(app, [*command.split(), "--help"], terminal_width=200)
        assert result.exit_code == 0, (command, result.output)
        options = [line for line in result.output.splitlines() if line.lstrip().startswith("-")]
        assert not [line for line in options if re.search(r"<\w+\[", line)], \
            f"capssim {command} --help shows a Python type as an option's placeholder"


@pytest.mark.parametrize("pair, flag", [("physical_projection=0", "--no-physical-projection"),
                                        ("device=cuda", "--device"), ("true_warps=1", "--true-warps"),
                                        ("progress=0", "--progress")])
def test_method_option_that_is_a_command_flag_names_the_flag(pair, flag, capture_dir, capsys, monkeypatch):
    status, err = run_cli(["reconstruct", capture_dir, "-m", "caps-naive", "-p", pair, "--no-progress"],
                          capsys, monkeypatch)
    assert_user_error(status, err, "--param", pair.split("=")[0], flag)


def test_every_keyword_of_reconstruct_is_a_named_command_flag():
    """A new keyword of ``registry.reconstruct`` given as ``-p KEY=...`` would clash with the flag passing it."""
    import inspect

    from capssim.cli.reconstruct import COMMAND_FLAGS
    from capssim.reconstruct.registry import reconstruct

    keywords = {name for name, p in inspect.signature(reconstruct).parameters.items() if p.kind is p.KEYWORD_ONLY}
    assert keywords == set(COMMAND_FLAGS)
