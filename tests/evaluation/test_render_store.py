"""The render store shared by every suite (``CAPSSIM_RENDER_CACHE``): a scene one suite rendered is not
rendered again by a suite with another cache folder; ``off`` keeps each suite's renders to itself."""

from __future__ import annotations

import numpy as np

from capssim.eval.benchmarks import captures
from capssim.simulate import simulate_capture

SCENE = {"name": "siemens-star", "source": "render", "size": 32}


def _counting_renderer(monkeypatch):
    calls = []

    def fake_render(name, *, size, spp, seed, setup, variant, record_timing, **extra):
        calls.append(name)
        gt = np.random.default_rng(seed).random((12, size, size)).astype(np.float32)
        return simulate_capture(gt, setup, seed=seed)

    monkeypatch.setattr(captures, "render_capture", fake_render)
    monkeypatch.setattr(captures, "rendered_scene_names", lambda: ["siemens-star"])
    return calls


def _render(cache_dir):
    return captures.CaptureFactory(cache_dir, lambda *args, **kwargs: None)._render(SCENE, 0)


def test_a_render_is_shared_by_suites_with_other_cache_folders(tmp_path, monkeypatch):
    calls = _counting_renderer(monkeypatch)
    monkeypatch.setenv(captures.RENDER_CACHE_ENV, str(tmp_path / "shared"))
    first, first_info = _render(tmp_path / "suite-a")
    second, second_info = _render(tmp_path / "suite-b")
    assert calls == ["siemens-star"] and not first_info["render_cached"] and second_info["render_cached"]
    assert np.array_equal(first.gt, second.gt)
    stored = [p for p in (tmp_path / "shared").iterdir()]
    assert len(stored) == 1 and not stored[0].name.startswith(".")  # no temporary folder left behind


def test_the_shared_store_can_be_turned_off(tmp_path, monkeypatch):
    calls = _counting_renderer(monkeypatch)
    monkeypatch.setenv(captures.RENDER_CACHE_ENV, "off")
    assert captures.shared_render_dir() is None
    _render(tmp_path / "suite-a")
    _render(tmp_path / "suite-b")
    _render(tmp_path / "suite-a")  # its own cache still holds it
    assert calls == ["siemens-star"] * 2


def test_the_default_store_is_the_user_cache(monkeypatch, tmp_path):
    monkeypatch.delenv(captures.RENDER_CACHE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert captures.shared_render_dir() == tmp_path / "capssim" / "renders"


def test_a_store_that_cannot_be_written_only_costs_the_sharing(tmp_path, monkeypatch):
    calls = _counting_renderer(monkeypatch)
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(captures.RENDER_CACHE_ENV, str(blocker / "renders"))
    _, info = _render(tmp_path / "suite-a")
    assert calls == ["siemens-star"] and not info["render_cached"]
