"""Issue 34, class 12 ("late checks and long messages"): model files, checkpoints, singular homographies and
shared scene parameters give ONE line that names the argument, never torch's or numpy's multi-line text.

Every row names its class. The command-line rows exit 2 with exactly one ``error:`` line and no traceback;
the library rows check the one-line message of the function the commands call. (The command-line rows for
the same class that need a capture, e.g. ``--threads 0``, are in tests/cli/test_hardening2_commands.py.)
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch
from support.fuzz import one_error_line, run_cli

from capssim.errors import InputError

#: words of torch's and numpy's own multi-line texts that must never reach the user
FOREIGN = ("weights_only", "PyTorch", "pytorch.org", "miniz", "Missing key", "Unexpected key", "size mismatch")


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    args: Callable[[Path], list]  #: the command line, given the test's folder (a copy of the template)
    fragments: tuple = ()  #: words the one error line holds






TRAIN = """name: t
model: {network: cpdnet, features: 4, colour_blocks: 1, polarization_blocks: 1}
input: dofp
data: {dataset: ds.yaml, crop: 16, batch: 2, validation: 1}
schedule: {steps: 1}
"""


@pytest.fixture(scope="module")
def template(tmp_path_factory, write_gt_folder) -> Path:
    """``cap/`` (a 32 px capture), broken model files, a training config and a run folder with a broken
    checkpoint."""
    from capssim.camera.sensor import make_sensor
    from capssim.captures.capture import write_capture
    from capssim.files.imageio import read_gt_scene
    from capssim.reconstruct.networks import MODEL_FORMAT, MODEL_VERSION
    from capssim.reconstruct.training.trainer import CHECKPOINT
    from capssim.simulate import prepare_ground_truth, simulate_capture

    folder = tmp_path_factory.mktemp("messages")
    write_gt_folder(folder / "gt", size=64, seed=1)
    image, _ = prepare_ground_truth(read_gt_scene(folder / "gt")[0], crop=32)
    write_capture(folder / "cap", simulate_capture(image, make_sensor("none"), seed=0))
    (folder / "garbage.pt").write_bytes(bytes(range(256)) * 8)  # a pickle opcode torch refuses
    (folder / "empty.pt").write_bytes(b"")
    (folder / "text.pt").write_text("hello\n")
    torch.save({"format": MODEL_FORMAT, "version": MODEL_VERSION, "network": "cpdnet", "params": {"features": 8},
                "state_dict": {"not.a.layer": torch.zeros(2)}}, folder / "tampered.pt")
    (folder / "ds.yaml").write_text("name: ds\n")
    (folder / "t.yaml").write_text(TRAIN)
    (folder / "run").mkdir()
    (folder / "run" / CHECKPOINT).write_bytes(bytes(range(256)) * 8)
    return folder


@pytest.fixture
def world(template, tmp_path) -> Path:
    shutil.copytree(template, tmp_path / "w")
    return tmp_path / "w"


def _cpdnet(weights: str) -> Callable[[Path], list]:
    return lambda w: ["reconstruct", w / "cap", "-m", "cpdnet", "--no-progress", "-p", f"weights={w / weights}"]


ROWS = [
    Row(12, "cpdnet weights of random bytes", _cpdnet("garbage.pt"), ("weights", "cannot be read")),
    Row(12, "cpdnet weights of an empty file", _cpdnet("empty.pt"), ("weights", "EOFError")),
    Row(12, "cpdnet weights of a text file", _cpdnet("text.pt"), ("weights", "cannot be read")),
    Row(12, "cpdnet weights whose state dict does not fit the network", _cpdnet("tampered.pt"),
        ("weights", "do not fit")),
    Row(12, "caps-sisr model of random bytes",
        lambda w: ["reconstruct", w / "cap", "-m", "caps-sisr", "--true-warps", "--no-progress", "-p",
                   f"model={w / 'garbage.pt'}"], ("model", "torch.jit.load failed")),
    Row(12, "train resuming an unreadable checkpoint",
        lambda w: ["train", w / "t.yaml", "-o", w / "run"], ("-o/--output", "checkpoint", "unreadable")),
    Row(12, "render --param depth_m=-1 blames depth_m",
        lambda w: ["render", "siemens-star", "-o", w / "o", "--size", "16", "--spp", "1", "--param", "depth_m=-1"],
        ("scene_params.depth_m", "[0.1, 1000]")),
    Row(12, "render --param fov_deg=0 blames fov_deg",
        lambda w: ["render", "textured", "-o", w / "o", "--size", "16", "--spp", "1", "--param", "fov_deg=0"],
        ("scene_params.fov_deg",)),
]


@pytest.mark.parametrize("row", ROWS, ids=[f"class{r.cls}-{r.name}" for r in ROWS])
def test_one_line_messages(row, world, capsys, monkeypatch):
    status, text = run_cli(row.args(world), capsys, monkeypatch)
    one_error_line(status, text, *row.fragments, skip_log_lines=True, forbidden=FOREIGN)
    assert not (world / "cap" / "recon").exists() and not (world / "o").exists()


# -- library rows: the message of the function the commands call ---------------------------------------------
def test_class12_singular_homographies_are_one_short_line():
    from capssim.operators.warp import _as_homographies

    stack = np.tile(np.eye(3) * 0.9962485294862956, (16, 1, 1))  # determinants that print over many lines
    stack[[3, 9]] = [[1, 2, 0], [2, 4, 0], [0, 0, 1]]
    with pytest.raises(InputError) as info:
        _as_homographies(stack)
    message = str(info.value)
    assert "\n" not in message and len(message) < 200, message
    assert "2 singular of 16" in message and "[3]" in message and "[9]" in message, message
    _as_homographies(stack[:3])  # the invertible ones pass


@pytest.mark.parametrize("key, value", [("depth_m", 0.0), ("depth_m", 1e9), ("fov_deg", 0.0), ("fov_deg", 180.0)])
def test_class12_shared_scene_parameters_name_the_parameter(key, value):
    """Every scene with ``depth_m`` or ``fov_deg`` refuses them out of range, naming the parameter (not the
    camera), and accepts its own default and the values the shipped dataset configs draw."""
    from capssim.render import list_scenes
    from capssim.render.scene_registry import get_scene

    having = [name for name, info in list_scenes().items() if key in info.defaults]
    assert having, key
    for name in having:
        scene = get_scene(name)
        with pytest.raises(InputError, match=rf"scene_params\.{key}"):
            scene.params({key: value})
        assert scene.params({})[key] == scene.info.defaults[key]
        scene.params({key: {"depth_m": 1.5, "fov_deg": 3.0}[key]})  # examples/dataset-*.yaml draw these


def test_class12_a_model_file_message_is_short_for_every_torch_failure(tmp_path):
    from capssim.reconstruct.networks import unreadable_reason

    long = RuntimeError("Error(s) in loading state_dict for CPDNet:\n\tMissing key(s) in state_dict: " + "a, " * 200)
    assert unreadable_reason(long) == "Error(s) in loading state_dict for CPDNet"
    assert unreadable_reason(EOFError()) == "EOFError"
    assert len(unreadable_reason(ValueError("x" * 500))) <= 120
