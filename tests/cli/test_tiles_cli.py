"""Issue 35 items 1-2 on the command line: --tile, --memory-gb, --workers, --scheduler and a folder of
captures (bad values: one line, exit 2; a folder on 2 Dask workers equals the serial run; a rerun skips
finished frames)."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from support.fuzz import invoke

from capssim.captures.capture import write_capture
from capssim.files.imageio import read_tiff
from capssim.simulate import simulate_capture

FAST = ["--iterations", "2", "--true-warps", "--no-progress"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory, smooth_random_scene) -> Path:
    root = tmp_path_factory.mktemp("frames")
    for i in range(4):
        write_capture(root / f"cap{i}", simulate_capture(smooth_random_scene(128, seed=i), seed=i))
    return root


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    args: tuple
    fragment: str


ROWS = [
    Row(cls=12, name="tile below the smallest", args=("--tile", "16"), fragment="--tile"),
    Row(cls=1, name="memory budget zero", args=("--memory-gb", "0"), fragment="--memory-gb"),
    Row(cls=1, name="memory budget nan", args=("--memory-gb", "nan"), fragment="--memory-gb"),
    Row(cls=1, name="memory budget below the smallest tile", args=("--memory-gb", "0.1"), fragment="--memory-gb"),
    Row(cls=12, name="no workers", args=("--workers", "0"), fragment="--workers"),
    Row(cls=9, name="workers with a scheduler", args=("--workers", "2", "--scheduler", "tcp://x:1"),
        fragment="--scheduler"),
]


@pytest.mark.parametrize("row", ROWS, ids=lambda r: f"{r.cls}-{r.name}")
def test_bad_full_frame_options_give_one_line(row, folder):
    outcome, message = invoke(["reconstruct", folder / "cap0", *FAST, *row.args])
    assert outcome in ("error", "usage"), message
    assert row.fragment in message


@pytest.mark.processes
def test_a_folder_on_two_workers_equals_the_serial_run_and_resumes(folder, tmp_path):
    serial, dask = (shutil.copytree(folder, tmp_path / name) for name in ("serial", "dask"))
    assert invoke(["reconstruct", serial, *FAST])[0] == "ok"
    outcome, out = invoke(["reconstruct", dask, *FAST, "--workers", "2"])
    assert outcome == "ok", out
    for i in range(4):
        a = read_tiff(serial / f"cap{i}" / "recon" / "caps.tiff")
        b = read_tiff(dask / f"cap{i}" / "recon" / "caps.tiff")
        np.testing.assert_array_equal(a, b)
    (dask / "cap2" / "recon" / "caps.json").unlink()  # as if killed before cap2 was written
    outcome, out = invoke(["reconstruct", dask, *FAST])
    assert outcome == "ok" and out.count("already finished") == 3, out
    np.testing.assert_array_equal(read_tiff(dask / "cap2" / "recon" / "caps.tiff"),
                                  read_tiff(serial / "cap2" / "recon" / "caps.tiff"))


def test_tile_option_writes_a_tiled_record(folder, tmp_path):
    cap = shutil.copytree(folder / "cap1", tmp_path / "cap1")
    outcome, out = invoke(["reconstruct", cap, *FAST, "--tile", "64"])
    assert outcome == "ok", out
    record = json.loads((cap / "recon" / "caps.json").read_text())
    assert record["tiles"]["grid"] == [2, 2] and not (cap / "recon" / ".parts-caps").exists()
