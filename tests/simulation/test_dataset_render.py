"""Rendered-scene samples with the real capssim.render (skipped where it is not installed),
and the example config."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from capssim.dataset import load_config
from capssim.dataset.generate import generate_dataset
from capssim.dataset.sample import generate_sample
from capssim.dataset.verify import verify_dataset

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "dataset-small.yaml"


def _render_or_skip():
    try:
        import capssim.render  # noqa: F401
    except ImportError as exc:
        pytest.skip(f"capssim.render not available: {exc}")


def test_rendered_sample_regenerates_byte_identically(tree_bytes, tmp_path):
    _render_or_skip()
    path = tmp_path / "config.yaml"
    path.write_text(textwrap.dedent("""
        seed: 9
        samples: 2
        defaults:
          sensor: {noise: gaussian, sigma: {uniform: [0.005, 0.01]}}
        sources:
          - scene: aop-wheel
            size: 16
            spp: 4
            scene_params: {level: {uniform: [0.5, 0.9]}, depth_m: {uniform: [1.5, 3.0]}}
            geometry_params: {roll_max_deg: {uniform: [0.1, 0.5]}}
    """))
    cfg = load_config(path)
    out = tmp_path / "out"
    result = generate_dataset(cfg, out, workers=0)
    assert result.complete and verify_dataset(out).ok
    meta_text = (out / "samples" / "000001" / "meta.json").read_text()
    assert '"kind": "rendered"' in meta_text and '"dataset"' in meta_text
    again = tmp_path / "again"
    again.mkdir()
    spec = cfg.sample_spec(1)
    generate_sample(spec, str(again))
    assert tree_bytes(again / spec["name"]) == tree_bytes(out / "samples" / spec["name"])


def test_example_config_is_valid(shared_data):
    _render_or_skip()
    cfg = load_config(EXAMPLE)
    kinds = {cfg.sample_spec(i)["params"]["source"]["type"] for i in range(cfg.samples)}
    assert kinds == {"gt", "scene"} and cfg.samples <= 10


@pytest.mark.slow
def test_example_config_generates_and_verifies(shared_data, tmp_path):
    _render_or_skip()
    out = tmp_path / "small"
    proc = subprocess.run([sys.executable, "-m", "capssim.cli.__main__", "dataset", str(EXAMPLE), "-o", str(out),
                           "--workers", "2", "--verify"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    assert verify_dataset(out).ok
