"""CAGF confidence (paper eq. 12-14): guided-filter residual, pairwise confidence, alignment, resize."""

import numpy as np
import pytest
import torch

from capssim.reconstruct.model.cagf import (
    align_to_reference,
    box_mean,
    cagf_confidence,
    guided_filter_residual,
    pairwise_confidence,
    resize_to_hr,
    window_count,
)


def _brute_residual(a, g, k, radius, eps):
    """min over (a_k, b_k) of eq. 12 at pixel k by least squares on the window."""
    h, w = a.shape
    y, x = k
    rows = slice(max(0, y - radius), min(h, y + radius + 1))
    cols = slice(max(0, x - radius), min(w, x + radius + 1))
    gi, ai = g[rows, cols].ravel(), a[rows, cols].ravel()
    n = gi.size
    # unknowns (a, b); rows: sqrt(eps) a = 0 for each window pixel, a g + b = A
    mat = np.concatenate([np.stack([gi, np.ones(n)], 1), np.tile([[np.sqrt(eps), 0.0]], (n, 1))])
    rhs = np.concatenate([ai, np.zeros(n)])
    sol, *_ = np.linalg.lstsq(mat, rhs, rcond=None)
    return float(np.sum((mat @ sol - rhs) ** 2))


def test_residual_matches_least_squares_definition():
    rng = np.random.default_rng(0)
    a = rng.random((9, 11))
    g = 0.5 * a + 0.2 * rng.random((9, 11))
    r = guided_filter_residual(torch.as_tensor(a), torch.as_tensor(g), radius=2, eps=1e-3).numpy()
    for k in [(0, 0), (4, 5), (8, 10), (2, 9)]:
        assert r[k] == pytest.approx(_brute_residual(a, g, k, 2, 1e-3), rel=1e-6, abs=1e-12)


def test_box_mean_and_window_count_at_borders():
    x = torch.arange(20.0).reshape(4, 5)
    m = box_mean(x, 1)
    assert m[0, 0] == pytest.approx(float(x[:2, :2].mean()))
    assert window_count(4, 5, 1)[0, 0] == 4 and window_count(4, 5, 1)[1, 1] == 9


def test_zero_variance_guide_is_finite():
    target = torch.rand(8, 8, dtype=torch.float64)
    flat = torch.full((8, 8), 0.3, dtype=torch.float64)
    r = guided_filter_residual(target, flat, radius=1, eps=1e-4)
    assert torch.isfinite(r).all()
    var = box_mean(target**2, 1) - box_mean(target, 1) ** 2
    assert torch.allclose(r, window_count(8, 8, 1, dtype=torch.float64) * var, atol=1e-12)
    # a fully constant image (both zero variance, even zero) gives confidence 1, no NaN
    conf = pairwise_confidence(torch.zeros(3, 6, 6))
    assert torch.isfinite(conf).all() and torch.all(conf == 1)


def test_pairwise_confidence_properties():
    rng = np.random.default_rng(2)
    base = rng.random((24, 24))
    exclusive = base.copy()
    exclusive[8:16, 8:16] = rng.random((8, 8))  # texture only this channel has
    chans = torch.as_tensor(np.stack([base, 0.5 * base + 0.1, exclusive]), dtype=torch.float32)
    conf = pairwise_confidence(chans, nu=0.2, radius=4)
    assert conf.shape == (3, 3, 24, 24)
    assert torch.allclose(conf, conf.transpose(0, 1))
    assert torch.all(conf[0, 0] == 1) and torch.all((conf > 0) & (conf <= 1))
    # linearly related (slope 2 one way): only the eps a^2 term, n eps a^2 = 81e-4 * 4 -> exp(-0.16)
    assert conf[0, 1].min() > 0.84
    assert conf[0, 2, 12, 12] < 0.05                     # exclusive texture: low confidence
    assert conf[0, 2, 0, 0] > 0.9 * conf[0, 1, 0, 0]     # away from it: unaffected


def test_align_recovers_shift_and_resize_positions():
    # image 1 is image 0 shifted by +2 pixels in x: H_1 = T(2, 0) @ H_0
    h0 = np.eye(3)
    h1 = np.array([[1.0, 0, 2.0], [0, 1, 0], [0, 0, 1]])
    xs = np.arange(16, dtype=np.float32)
    img0 = np.tile(xs, (8, 1))
    # image 1 pixel p shows the reference at p - 2, whose value (a ramp) is p - 2
    img1 = np.tile(xs - 2, (8, 1))
    images = torch.as_tensor(np.stack([img0, img1]))
    aligned, wts = align_to_reference(images, np.stack([h0, h1]), reference=0)
    inner = slice(0, 14)
    assert torch.allclose(aligned[1][:, inner], aligned[0][:, inner], atol=1e-5)
    assert wts[1][:, 14:].sum() == 0 and wts[1][:, :14].min() == 1  # samples beyond the border
    # resize: HR pixel X reads the reference grid at (X - 0.5) / 4 for a Bayer R sub-image
    s0 = np.array([[0.25, 0, -0.125], [0, 0.25, -0.125], [0, 0, 1]])
    lr = torch.as_tensor(np.tile(np.arange(8, dtype=np.float32), (8, 1)))
    hr = resize_to_hr(lr, s0, (32, 32))
    assert hr[0, 16].item() == pytest.approx((16 - 0.5) / 4, abs=1e-5)


def test_cagf_confidence_shape():
    rng = np.random.default_rng(3)
    images = torch.as_tensor(rng.random((16, 6, 6)), dtype=torch.float32)
    from capssim.camera.array_geometry import lr_homographies
    from capssim.conventions import LR_IMAGE_CHANNELS

    hm = lr_homographies(np.stack([np.eye(3)] * 4))
    conf = cagf_confidence(images, hm, torch.tensor(LR_IMAGE_CHANNELS), 12, (24, 24))
    assert conf.shape == (12, 12, 24, 24) and torch.isfinite(conf).all()
