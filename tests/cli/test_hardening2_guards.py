"""Issue 34, class 1: the resource guard covers demosaic, mtf, evaluate and train; training configs have a schema.

Every row names its class. A refused command exits 2 with exactly one ``error:`` line and no traceback,
before its work starts: the image sizes come from the file headers (the test images are a few hundred
bytes whose headers claim 20000 x 20000 pixels), and the function that would decode the image or build
the model is replaced by one that fails the test.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from support.fuzz import refused_before_work

from capssim.runtime.resources import MEMORY_LIMIT_ENV, check_image_memory, image_header_shape

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
HUGE = 20000


def huge_png(path: Path, side: int = HUGE) -> Path:
    """An 8 x 8 grey PNG whose IHDR (with a valid CRC) says ``side x side``."""
    import cv2

    cv2.imwrite(str(path), np.zeros((8, 8), np.uint8))
    data = bytearray(path.read_bytes())
    data[16:24] = struct.pack(">II", side, side)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    path.write_bytes(bytes(data))
    return path


def huge_tiff(path: Path, side: int = HUGE) -> Path:
    """An 8 x 8 uint8 TIFF (no shape metadata) whose ImageWidth, ImageLength and RowsPerStrip tags say ``side``."""
    import tifffile

    tifffile.imwrite(path, np.zeros((8, 8), np.uint8), metadata=None)
    data = bytearray(path.read_bytes())
    assert data[:2] == b"II"
    ifd = struct.unpack_from("<I", data, 4)[0]
    for i in range(struct.unpack_from("<H", data, ifd)[0]):
        entry = ifd + 2 + 12 * i
        if struct.unpack_from("<H", data, entry)[0] in (256, 257, 278):  # -> LONG side
            struct.pack_into("<HII", data, entry + 2, 4, 1, side)
    path.write_bytes(bytes(data))
    return path


def train_config(model: str, extra: str = "", *, kind: str = "dofp", data: str = "") -> Callable[[Path], None]:
    """Writes ``train.yaml`` (``model``, ``input: kind``, ``data`` with ``dataset.yaml`` and ``data``, ``extra``)."""
    def setup(root: Path) -> None:
        (root / "dataset.yaml").write_text("seed: 0\n")
        (root / "train.yaml").write_text(f"model: {model}\ninput: {kind}\ndata: {{dataset: dataset.yaml{data}}}\n"
                                         f"{extra}")
    return setup


def evaluate_capture(gt_side: int, recon_side: int) -> Callable[[Path], None]:
    def setup(root: Path) -> None:
        (root / "cap" / "recon").mkdir(parents=True)
        huge_tiff(root / "cap" / "gt.tiff", gt_side)
        huge_tiff(root / "cap" / "recon" / "caps.tiff", recon_side)
    return setup


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    args: list  #: the command line; ``{root}`` is the test's folder
    fragments: tuple = ()  #: words the one error line holds
    forbid: str = ""  #: "module:function" of the command's work: it must not run
    env: dict = field(default_factory=lambda: {MEMORY_LIMIT_ENV: "1"})
    setup: Callable[[Path], None] = field(default=lambda root: None)


LIMIT = ("memory limit 1 GiB", MEMORY_LIMIT_ENV)
TRAIN = ["train", "{root}/train.yaml", "-o", "{root}/run"]
TRAINER = "capssim.reconstruct.training.trainer:train"
ROWS = [
    Row(1, "demosaic of a PNG of 20000x20000 px", ["demosaic", "{root}/big.png", "-o", "{root}/out"],
        ("RAW", "20000x20000", *LIMIT), "capssim.cli.demosaic:read_raw_mosaic",
        setup=lambda root: huge_png(root / "big.png")),
    Row(1, "demosaic of a TIFF of 20000x20000 px", ["demosaic", "{root}/big.tiff", "-o", "{root}/out"],
        ("RAW", "20000x20000", *LIMIT), "capssim.cli.demosaic:read_raw_mosaic",
        setup=lambda root: huge_tiff(root / "big.tiff")),
    Row(1, "mtf of a PNG of 20000x20000 px", ["mtf", "{root}/big.png", "--cycles", "32"],
        ("IMAGE", "20000x20000", *LIMIT), "capssim.cli.evaluate:_read_star_image",
        setup=lambda root: huge_png(root / "big.png")),
    Row(1, "evaluate with a gt.tiff of 20000x20000 px", ["evaluate", "{root}/cap"],
        ("CAPTURE", "gt.tiff", *LIMIT), "capssim.eval.evaluate:evaluate_capture", setup=evaluate_capture(HUGE, 8)),
    Row(1, "evaluate with a recon/caps.tiff of 20000x20000 px", ["evaluate", "{root}/cap"],
        ("CAPTURE", "caps.tiff", *LIMIT), "capssim.eval.evaluate:evaluate_capture", setup=evaluate_capture(8, HUGE)),
    Row(1, "train model.colour_blocks: 100000000", TRAIN, ("train.yaml", "'model'", "weights only", *LIMIT), TRAINER,
        setup=train_config("{network: cpdnet, colour_blocks: 100000000}")),
    Row(1, "train model.features: 512 (activations on the CPU)", TRAIN, ("train.yaml", "'model'", *LIMIT), TRAINER,
        setup=train_config("{network: cpdnet, features: 512}")),
    Row(1, "train model.features: 0", TRAIN, ("train.yaml", "'model.features'", "got 0", "integer >= 1"), TRAINER,
        env={}, setup=train_config("{network: cpdnet, features: 0}")),
    Row(1, "train model.features: -4", TRAIN, ("train.yaml", "'model.features'", "got -4"), TRAINER, env={},
        setup=train_config("{network: cpdnet, features: -4}")),
    Row(1, "train model.features: 2.5", TRAIN, ("train.yaml", "'model.features'", "got 2.5"), TRAINER, env={},
        setup=train_config("{network: cpdnet, features: 2.5}")),
    Row(1, "train model.blocks: -1 (edsr)", TRAIN, ("'model.blocks'", "got -1"), TRAINER, env={},
        setup=train_config("{network: edsr, blocks: -1}", kind="aperture")),
    Row(1, "train misspelt model key", TRAIN, ("'model.colour_block'", "Did you mean 'colour_blocks'?"), TRAINER,
        env={}, setup=train_config("{network: cpdnet, colour_block: 3}")),
    Row(1, "train misspelt top-level key", TRAIN, ("'schedul'", "Did you mean 'schedule'?"), TRAINER, env={},
        setup=train_config("{network: cpdnet}", "schedul: {steps: 3}\n")),
    Row(1, "train data.batch: eight", TRAIN, ("'data.batch'", "got 'eight'"), TRAINER, env={},
        setup=train_config("{network: cpdnet}", data=", batch: eight")),
    Row(1, "train optimizer.lr: 0", TRAIN, ("'optimizer.lr'", "got 0"), TRAINER, env={},
        setup=train_config("{network: cpdnet}", "optimizer: {lr: 0}\n")),
    Row(1, "train schedule.warmup past steps", TRAIN, ("'schedule.warmup'", "at most schedule.steps"), TRAINER, env={},
        setup=train_config("{network: cpdnet}", "schedule: {steps: 10, warmup: 20}\n")),
    Row(1, "train model that is a list", TRAIN, ("train.yaml", "'model'"), TRAINER, env={},
        setup=train_config("[cpdnet]")),
]




@pytest.mark.parametrize("row", ROWS, ids=lambda r: f"class{r.cls}-{r.name}")
def test_refused_before_work_in_one_line(row, tmp_path, capsys, monkeypatch):
    row.setup(tmp_path)
    refused_before_work(row.args, tmp_path, capsys, monkeypatch, fragments=row.fragments, forbid=row.forbid,
                        env=row.env)


def test_header_shapes_are_read_without_decoding(tmp_path):
    import cv2
    import tifffile

    cv2.imwrite(str(tmp_path / "grey.png"), np.zeros((6, 10), np.uint8))
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((6, 10, 3), np.uint16))
    tifffile.imwrite(tmp_path / "twelve.tiff", np.zeros((12, 6, 10), np.float32))
    assert image_header_shape(tmp_path / "grey.png") == (6, 10)
    assert image_header_shape(tmp_path / "rgb.png") == (6, 10, 3)
    assert image_header_shape(tmp_path / "twelve.tiff") == (12, 6, 10)
    assert image_header_shape(huge_tiff(tmp_path / "huge.tiff")) == (HUGE, HUGE)
    (tmp_path / "junk.png").write_bytes(b"not an image")
    assert image_header_shape(tmp_path / "junk.png") is None  # the reader reports it


def test_small_images_and_shipped_configs_pass_the_guards(tmp_path, monkeypatch):
    """The guards refuse by size, not by kind: a 64 px image and every shipped training config pass under 1 GiB."""
    from capssim.reconstruct.training.config import check_model_memory, load_train_config

    monkeypatch.setenv(MEMORY_LIMIT_ENV, "1")
    assert check_image_memory("RAW", huge_png(tmp_path / "small.png", 64), 1280, what="demosaicking", fix="") == (64, 64)
    configs = sorted(EXAMPLES.glob("train-*.yaml"))
    assert len(configs) >= 5
    for path in configs:
        config = load_train_config(path)
        if "gpu" not in path.name:  # the GPU configs' batch maps live on the GPU
            check_model_memory(config)
