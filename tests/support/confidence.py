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


def per_pixel_matrix(direction, c, h, w, *, dtype=torch.float64):
    """The ``(H, W, C, C)`` matrix of a per-pixel linear map ``direction`` ``(C, H, W) -> (C, H, W)``, read column by
    column from its response to each unit channel (for the symmetric / positive semi-definite checks)."""
    cols = []
    for j in range(c):
        e = torch.zeros(c, h, w, dtype=dtype)
        e[j] = 1
        cols.append(direction(e))
    return torch.stack(cols, dim=1).permute(2, 3, 0, 1)
