"""Dataset-config and output helpers shared by the dataset tests (received as fixtures, tests/conftest.py)."""

from __future__ import annotations

import textwrap
from pathlib import Path

from capssim.dataset.manifest import read_manifest

from .scenes import write_gt_folder

CONFIG = """
name: test
seed: 11
samples: {samples}
defaults:
  sensor: {{noise: {{choice: [none, gaussian, poisson-gaussian]}}, sigma: {{log_uniform: [0.002, 0.02]}},
           preset: {{choice: [imx250myr, python1300]}}}}
  dofp_layout: {{choice: [sony, 0-45-135-90]}}
  pose: {{shift_max_px: {{uniform: [0.5, 2.0]}}}}
  extinction_ratio: {{choice: [null, 200]}}
sources:
  - gt: gt/a
    size: {size}
    crop_position: random
    augment: {{rot90: {{int_uniform: [0, 3]}}, flip: {{choice: [false, true]}}}}
  - gt: gt/b
    size: null
"""


def make_config(tmp_path: Path, samples: int = 6, size: int = 32, gt_size: int = 40) -> Path:
    """A dataset config of ``samples`` samples over two small PNG ground truths written under ``tmp_path/gt``."""
    if not (tmp_path / "gt").is_dir():
        write_gt_folder(tmp_path / "gt" / "a", size=gt_size, seed=1)
        write_gt_folder(tmp_path / "gt" / "b", size=size, seed=2)
    path = tmp_path / "config.yaml"
    path.write_text(textwrap.dedent(CONFIG.format(samples=samples, size=size)))
    return path


def tree_bytes(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder``, relative POSIX path -> bytes."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def records_by_index(out: Path) -> dict[int, dict]:
    """The manifest records of the dataset in ``out``, by sample index."""
    return read_manifest(out / "manifest.jsonl").records
