"""Confidence matrices for the data-term tests."""

from __future__ import annotations

import torch


def random_confidence(c, h, w, *, seed=0, dtype=torch.float64):
    """A symmetric positive semi-definite (C, C, H, W) with unit diagonal, as CAGF's: ``G G^T`` normalized."""
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, c, c, generator=g, dtype=dtype)
    m = a @ a.transpose(-1, -2)
    d = torch.diagonal(m, dim1=-2, dim2=-1).sqrt()
    m = m / (d[..., :, None] * d[..., None, :])
    return m.permute(2, 3, 0, 1).contiguous()
