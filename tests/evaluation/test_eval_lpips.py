"""eval.lpips: runs only with local weights; clear errors otherwise (no downloads)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.errors import InputError
from capssim.eval.lpips import _CONVS, LPIPS
from capssim.eval.metrics import score


def _fake_weights(path, *, drop=None):
    """Random tensors in the torchvision-AlexNet + lpips-v0.1 key layout (not real weights)."""
    g = torch.Generator().manual_seed(0)
    state = {}
    for i, (cin, cout, k, _, _) in _CONVS.items():
        state[f"features.{i}.weight"] = torch.randn(cout, cin, k, k, generator=g) * 0.05
        state[f"features.{i}.bias"] = torch.zeros(cout)
    for k, c in enumerate((64, 192, 384, 256, 256)):
        state[f"lin{k}.model.1.weight"] = torch.rand(1, c, 1, 1, generator=g)
    if drop:
        state.pop(drop)
    torch.save(state, path)
    return path


def test_lpips_with_local_weights(smooth_random_scene, tmp_path):
    model = LPIPS.from_path(_fake_weights(tmp_path / "w.pth"))
    gt = smooth_random_scene(64)
    assert model.distance(gt[:3], gt[:3]) == pytest.approx(0.0, abs=1e-9)
    noisy = gt + np.random.default_rng(0).normal(0, 0.05, gt.shape).astype(np.float32)
    assert model.distance(noisy[:3], gt[:3]) > 0
    r = score(noisy, gt, lpips=model)
    assert set(r["lpips"]) == {"0", "45", "90", "135"} and r["lpips_mean"] > 0


def test_lpips_weights_errors(smooth_random_scene, tmp_path):
    with pytest.raises(InputError, match="lin4"):
        LPIPS.from_path(_fake_weights(tmp_path / "w.pth", drop="lin4.model.1.weight"))
    with pytest.raises(InputError, match="never downloads"):
        LPIPS.from_path(tmp_path / "absent.pth")
    (tmp_path / "junk.pth").write_text("not torch")
    with pytest.raises(InputError, match="unreadable"):
        LPIPS.from_path(tmp_path / "junk.pth")
    assert score(smooth_random_scene(32), smooth_random_scene(32))["lpips_mean"] is None
