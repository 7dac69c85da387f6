"""Issue 34, the commands: classes 1 (demosaic, mtf, train), 9, 11 and 12.

Every row names its class. A refused command exits 2 with exactly one ``error:`` line and no traceback
(and, where the row says so, before its output exists); an accepted one exits 0 and, for out-of-range
data (class 11), warns once with the count of the values affected.
"""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import tifffile
from support.fuzz import one_error_line, run_cli


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    args: Callable[[Path], list]  #: the command line, given the test's folder (a copy of the template)
    fragments: tuple = ()  #: words the one error line (or the warning) holds
    ok: bool = False  #: exit 0 expected (with ``fragments`` in the output)
    absent: str = ""  #: a path (relative to the folder) that must not exist afterwards
    env: tuple = ()  #: (name, value) environment variables






def png_header(path: Path, height: int, width: int) -> Path:
    """A PNG whose header says ``height x width`` grey 8-bit, with one tiny IDAT: a few hundred bytes that
    would decode to ``height * width`` bytes."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))
    return path


def scaled_frame(folder: Path, name: str, scale: float = 1.0, offset: float = 0.0) -> None:
    """``folder/name`` (a float TIFF) times ``scale`` plus ``offset``."""
    raw = tifffile.imread(folder / name).astype(np.float32)
    tifffile.imwrite(folder / name, (raw * scale + offset).astype(np.float32), photometric="minisblack")


TRAIN = """name: t
model: {network: cpdnet, %s}
input: dofp
data: {dataset: ds.yaml, crop: 16, batch: 2, validation: 1}
schedule: {steps: 1}
"""


@pytest.fixture(scope="module")
def template(tmp_path_factory, write_gt_folder) -> Path:
    """``cap/`` (a 32 px capture, float frames), ``scored/`` (with dofp-bilinear), ``raw.png``, ``big.png``."""
    from capssim.camera.sensor import make_sensor
    from capssim.captures.capture import write_capture
    from capssim.files.imageio import read_gt_scene
    from capssim.reconstruct import run_method
    from capssim.simulate import prepare_ground_truth, simulate_capture

    folder = tmp_path_factory.mktemp("commands")
    write_gt_folder(folder / "gt", size=64, seed=1)
    image, _ = prepare_ground_truth(read_gt_scene(folder / "gt")[0], crop=32)
    write_capture(folder / "cap", simulate_capture(image, make_sensor("none"), seed=0))
    shutil.copytree(folder / "cap", folder / "scored")
    run_method(folder / "scored", "dofp-bilinear")
    import cv2

    cv2.imwrite(str(folder / "raw.png"), (np.arange(32 * 32).reshape(32, 32) % 251).astype(np.uint8))
    png_header(folder / "big.png", 20000, 20000)
    (folder / "ds.yaml").write_text("name: ds\n")
    (folder / "garbage.pth").write_bytes(bytes(range(256)) * 4)
    return folder


@pytest.fixture
def world(template, tmp_path) -> Path:
    shutil.copytree(template, tmp_path / "w")
    return tmp_path / "w"


def _no_gt(w: Path) -> Path:
    (w / "cap" / "gt.tiff").unlink()
    return w / "cap"


def _singular(w: Path) -> Path:
    meta = json.loads((w / "cap" / "meta.json").read_text())
    meta["aperture_homographies"][1] = [[1, 0, 0], [2, 0, 0], [0, 0, 1]]
    (w / "cap" / "meta.json").write_text(json.dumps(meta))
    return w / "cap"


def _train(w: Path, model: str) -> Path:
    (w / "t.yaml").write_text(TRAIN % model)
    return w / "t.yaml"


CAPS = ["-m", "caps", "--iterations", "1", "--true-warps", "--no-progress"]
ROWS = [
    # -- class 1: the resource guard, estimated before allocating --------------------------------------------
    Row(1, "demosaic of a 20000x20000 PNG under a 1 GB limit", lambda w: ["demosaic", w / "big.png", "-o", w / "o"],
        ("RAW", "20000x20000"), absent="o", env=(("CAPSSIM_MEMORY_LIMIT_GB", "1"),)),
    Row(1, "mtf of a 20000x20000 PNG under a 1 GB limit", lambda w: ["mtf", w / "big.png", "--cycles", "36"], ("IMAGE", "20000x20000"),
        env=(("CAPSSIM_MEMORY_LIMIT_GB", "1"),)),
    Row(1, "train model.colour_blocks 100000000", lambda w: ["train", _train(w, "colour_blocks: 100000000"),
                                                              "-o", w / "run"], ("model",),
        env=(("CAPSSIM_MEMORY_LIMIT_GB", "1"),)),
    Row(1, "train model.features 0", lambda w: ["train", _train(w, "features: 0"), "-o", w / "run"],
        ("model.features",)),
    Row(1, "train model.features -4", lambda w: ["train", _train(w, "features: -4"), "-o", w / "run"],
        ("model.features",)),
    Row(1, "train model.features 2.5", lambda w: ["train", _train(w, "features: 2.5"), "-o", w / "run"],
        ("model.features",)),
    Row(1, "train misspelt model key", lambda w: ["train", _train(w, "featres: 8"), "-o", w / "run"],
        ("featres",)),
    # -- class 9: every option takes effect or is refused --------------------------------------------------
    Row(9, "-p track_psnr=true tracks PSNR against gt.tiff",
        lambda w: ["reconstruct", w / "cap", *CAPS, "-p", "track_psnr=true"], ("PSNR against gt.tiff",), ok=True),
    Row(9, "-p track_psnr=true without gt.tiff", lambda w: ["reconstruct", _no_gt(w), *CAPS, "-p", "track_psnr=true"],
        ("track_psnr", "gt.tiff"), absent="cap/recon/caps.tiff"),
    Row(9, "-p track_psnr=true with --tile", lambda w: ["reconstruct", w / "cap", *CAPS, "-p", "track_psnr=1",
                                                       "--tile", "64"], ("track_psnr", "--tile")),
    Row(9, "--iterations 1 with -p iterations=3", lambda w: ["reconstruct", w / "cap", *CAPS, "-p", "iterations=3"],
        ("--iterations", "iterations=3"), absent="cap/recon/caps.tiff"),
    Row(9, "--iterations 1 with -p iterations=1 (equal)",
        lambda w: ["reconstruct", w / "cap", *CAPS, "-p", "iterations=1"], ("cap/recon/caps.tiff",), ok=True),
    Row(9, "-p n_similar_min=100 -p n_similar=5",
        lambda w: ["reconstruct", w / "cap", *CAPS, "-p", "n_similar_min=100", "-p", "n_similar=5"],
        ("n_similar_min", "n_similar (5)"), absent="cap/recon/caps.tiff"),
    # -- class 11: out-of-range data, warned once with the count ---------------------------------------------
    Row(11, "float raw frames at 50x full scale",
        lambda w: [scaled_frame(w / "cap", "caps_raw.tiff", 50.0), "reconstruct", w / "cap", *CAPS][1:],
        ("caps_raw", "above the white level", "of 1024 values"), ok=True),
    Row(11, "float DoFP frame with negative values",
        lambda w: [scaled_frame(w / "cap", "dofp_raw.tiff", offset=-0.5), "reconstruct", w / "cap", "-m",
                   "dofp-bilinear", "--no-progress"][1:], ("dofp_raw", "below the black level", "of 1024 values"),
        ok=True),
    Row(11, "demosaic --black-level above every pixel", lambda w: ["demosaic", w / "raw.png", "-o", w / "o",
                                                                   "--black-level", "252"],
        ("--black-level", "250"), absent="o"),
    Row(11, "demosaic --black-level above some pixels", lambda w: ["demosaic", w / "raw.png", "-o", w / "o",
                                                                   "--black-level", "100"],
        ("below --black-level", "of 1024 values"), ok=True),
    Row(11, "demosaic of a float mosaic with negative values",
        lambda w: [tifffile.imwrite(w / "f.tiff", np.full((16, 16), -0.25, np.float32)), "demosaic", w / "f.tiff",
                   "-o", w / "o", "-m", "dofp-bilinear"][1:], ("256 of 256 values below black",), ok=True),
    Row(11, "evaluate a gt.tiff with negative values",
        lambda w: [scaled_frame(w / "scored", "gt.tiff", offset=-0.3), "evaluate", w / "scored"][1:],
        ("gt.tiff", "negative", "values"), ok=True),
    Row(11, "-p c1=1e300 (past the documented range)", lambda w: ["reconstruct", w / "cap", *CAPS, "-p", "c1=1e300"],
        ("c1", "(0, 2]"), absent="cap/recon/caps.tiff"),
    Row(11, "-p c2=1e30", lambda w: ["reconstruct", w / "cap", *CAPS, "-p", "c2=1e30"], ("c2",)),
    # -- class 12: checks before the first output, one-line messages -------------------------------------------
    Row(12, "-m caps -m dofp-eari -p c1=0.003: refused before recon/caps.tiff",
        lambda w: ["reconstruct", w / "cap", "-m", "caps", "-m", "dofp-eari", "--iterations", "1", "--true-warps",
                   "--no-progress", "-p", "c1=0.003"], ("-m dofp-eari", "c1"), absent="cap/recon/caps.tiff"),
    Row(12, "singular stored homography", lambda w: ["reconstruct", _singular(w), *CAPS], ("homograph",),
        absent="cap/recon/caps.tiff"),
    Row(12, "unreadable LPIPS weights", lambda w: ["evaluate", w / "scored", "--lpips-weights", w / "garbage.pth"],
        ("--lpips-weights", "not a torch weights file")),
    Row(12, "unreadable cpdnet weights", lambda w: ["reconstruct", w / "cap", "-m", "cpdnet", "--no-progress", "-p",
                                                    f"weights={w / 'garbage.pth'}"], ("weights",)),
    Row(12, "--threads 0", lambda w: ["reconstruct", w / "cap", "--threads", "0"], ("--threads",)),
    Row(12, "--threads -3 on demosaic", lambda w: ["demosaic", w / "raw.png", "-o", w / "o", "--threads", "-3"],
        ("--threads",)),
    Row(12, "render --param depth_m=0 blames depth_m",
        lambda w: ["render", "siemens-star", "-o", w / "o", "--size", "16", "--spp", "1", "--param", "depth_m=0"],
        ("depth_m",), absent="o"),
]


@pytest.mark.parametrize("row", ROWS, ids=[f"class{r.cls}-{r.name}" for r in ROWS])
def test_commands(row, world, capsys, monkeypatch):
    for name, value in row.env:
        monkeypatch.setenv(name, value)
    status, text = run_cli(row.args(world), capsys, monkeypatch)
    if row.ok:
        assert status == 0 and "Traceback" not in text, text
        for fragment in row.fragments:
            assert fragment in text, (fragment, text)
        warnings = [line for line in text.splitlines() if "out of range" in line]
        assert len(warnings) <= 1, text  # once, not once per method or per iteration
    else:
        one_error_line(status, text, *row.fragments, skip_log_lines=True)
    if row.absent:
        assert not (world / row.absent).exists(), row.absent


def test_valid_options_are_unchanged_by_the_checks(template, tmp_path):
    """The checks before the work change no number: ``caps`` through the command line equals the library's."""
    from typer.testing import CliRunner

    from capssim.captures.capture import read_capture
    from capssim.cli import app
    from capssim.reconstruct import reconstruct

    shutil.copytree(template / "cap", tmp_path / "cap")
    res = CliRunner().invoke(app, ["reconstruct", str(tmp_path / "cap"), *CAPS, "-p", "c1=0.003"])
    assert res.exit_code == 0, res.output
    direct, _ = reconstruct(read_capture(template / "cap", load_gt=False), "caps", iterations=1, true_warps=True,
                            c1="0.003")
    assert np.array_equal(tifffile.imread(tmp_path / "cap" / "recon" / "caps.tiff"), direct.image)
