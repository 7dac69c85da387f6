"""Shared fixtures: the optional ../shared/data folder, small synthetic scenes and folder builders.

The builders live in the package ``tests/support``; each is offered here as a fixture of the same name,
so a test asks for ``smooth_random_scene`` (say) as an argument instead of importing it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from support import confidence, datasets, networks, registration, scenes

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("CAPSSIM_SHARED_DATA", REPO.parent / "shared" / "data"))

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Several test workers share the cores: one compute thread each (torch, OpenMP/MKL, and the commands
    # the tests start), else torch's spinning OpenMP threads wait on each other (capssim.runtime.threads).
    # Measured on 2 cores, `make test`: 489 s with torch's default 2 threads per worker, 430 s with one.
    import torch

    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(_var, "1")
    torch.set_num_threads(1)


@pytest.fixture(scope="session", autouse=True)
def private_render_store(tmp_path_factory):
    """Suites rendered by the tests share their renders in a folder of this test session, not the user's
    cache (``CAPSSIM_RENDER_CACHE``, :mod:`capssim.eval.benchmarks.captures`)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("CAPSSIM_RENDER_CACHE", str(tmp_path_factory.mktemp("renders")))
        yield


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data``; tests using it skip cleanly when it is absent."""
    if not (SHARED_DATA / "gt").is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


def pytest_collection_modifyitems(config, items):
    """Every test that uses the ``shared_data`` fixture carries the ``shared_data`` marker
    (``-m "not shared_data"`` deselects them)."""
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.shared_data)


@pytest.fixture(scope="session")
def random_confidence():
    """:func:`support.confidence.random_confidence`: ``(C, H, W, *, seed=0) -> (C, C, H, W)`` symmetric PSD,
    unit diagonal (a CAGF-like confidence)."""
    return confidence.random_confidence


@pytest.fixture(scope="session")
def per_pixel_matrix():
    """:func:`support.confidence.per_pixel_matrix`: ``(direction, C, H, W) -> (H, W, C, C)``, a per-pixel linear
    map's matrix read from its response to each unit channel."""
    return confidence.per_pixel_matrix


@pytest.fixture(scope="session")
def smooth_random_scene():
    """:func:`support.scenes.smooth_random_scene`: ``(size=64, *, seed=0, dolp_max=0.6) -> (12, size, size)``."""
    return scenes.smooth_random_scene


@pytest.fixture(scope="session")
def natural_scene():
    """:func:`support.scenes.natural_scene`: ``() -> (12, 64, 64)`` astronaut crop under AoP/DoLP ramps."""
    return scenes.natural_scene


@pytest.fixture(scope="session")
def write_png_gt():
    """:func:`support.scenes.write_png_gt`: ``(folder, scene) -> folder`` of 8-bit PNGs."""
    return scenes.write_png_gt


@pytest.fixture(scope="session")
def write_gt_folder():
    """:func:`support.scenes.write_gt_folder`: ``(folder, size=32, seed=0) -> folder``."""
    return scenes.write_gt_folder


@pytest.fixture(scope="session")
def make_config():
    """:func:`support.datasets.make_config`: ``(tmp_path, samples=6, size=32, gt_size=40) -> config path``."""
    return datasets.make_config


@pytest.fixture(scope="session")
def tree_bytes():
    """:func:`support.datasets.tree_bytes`: ``(folder) -> {relative path: bytes}``."""
    return datasets.tree_bytes


@pytest.fixture(scope="session")
def records_by_index():
    """:func:`support.datasets.records_by_index`: ``(out) -> {index: record}``."""
    return datasets.records_by_index


@pytest.fixture(scope="session")
def tiny_denoiser_weights(tmp_path_factory) -> Path:
    """:func:`support.networks.tiny_denoiser_weights`: a small untrained denoiser's model file, made once."""
    return networks.tiny_denoiser_weights(tmp_path_factory.mktemp("denoiser"))


@pytest.fixture
def scene64() -> np.ndarray:
    return scenes.smooth_random_scene(64)


@pytest.fixture
def small_capture_dir(tmp_path) -> Path:
    """:func:`support.registration.small_capture` in ``tmp_path``: a 32x32 HR capture folder."""
    return registration.small_capture(tmp_path)


@pytest.fixture
def fake_registration(monkeypatch):
    """:func:`support.registration.counting_registration` bound to this test: ``(**record) -> calls``."""
    return lambda **record: registration.counting_registration(monkeypatch, **record)
