"""``capssim.runtime.allocator.reuse_freed_memory``: switches glibc malloc for a block, restores it, never changes results."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from capssim.camera.sensor import make_sensor
from capssim.reconstruct.registry import reconstruct
from capssim.runtime import allocator
from capssim.simulate import simulate_capture


def test_switches_once_and_restores():
    with allocator.reuse_freed_memory() as outer:
        assert outer == (allocator._glibc() is not None)
        assert allocator._State.active == outer
        with allocator.reuse_freed_memory() as inner:  # nested: the outer block keeps the switch
            assert inner == outer
        assert allocator._State.active == outer
    assert not allocator._State.active
    with allocator.reuse_freed_memory(enabled=False) as active:
        assert not active and not allocator._State.active


def test_environment_turns_it_off(monkeypatch):
    monkeypatch.setenv(allocator.ENV_VAR, "0")
    with allocator.reuse_freed_memory() as active:
        assert not active


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_found_on_linux_glibc():
    assert allocator._glibc() is not None


def test_caps_gives_the_same_image_with_and_without(smooth_random_scene, monkeypatch):
    capture = simulate_capture(smooth_random_scene(48, seed=5), make_sensor("gaussian", sigma=0.01), seed=5)
    switched, _ = reconstruct(capture, "caps", true_warps=True, iterations=3)
    monkeypatch.setattr(allocator, "_glibc", lambda: None)  # the allocator left as it is
    plain, _ = reconstruct(capture, "caps", true_warps=True, iterations=3)
    np.testing.assert_array_equal(switched.image, plain.image)
