"""Bilinear homography warp with an exact scatter-add adjoint (paper eq. 9-11, W_n).

Coordinates are ``(x=col, y=row)`` with pixel centres on integers, as in OpenCV. A
homography ``H`` maps *input* coordinates to *output* coordinates; output pixel ``p``
samples the input at ``H^-1 p`` by bilinear interpolation. Samples falling outside the
input are clamped to its border (replicate), which keeps the map linear and its adjoint
exact.
"""

from __future__ import annotations

import numpy as np
import torch

from capssim.errors import InputError
from capssim.operators.base import LinearOperator


def _as_homographies(homographies) -> np.ndarray:
    h = np.asarray(homographies, dtype=np.float64)
    if h.ndim == 2:
        h = h[None]
    if h.ndim != 3 or h.shape[1:] != (3, 3):
        raise InputError("homographies", f"array of shape {h.shape}", "shape (B, 3, 3) or (3, 3)")
    if not np.all(np.isfinite(h)):
        raise InputError("homographies", "non-finite values", "finite 3x3 matrices")
    det = np.linalg.det(h)
    if np.any(np.abs(det) < 1e-12):
        raise InputError("homographies", f"determinants {det}", "invertible matrices")
    return h


def bilinear_taps(homographies, in_hw: tuple[int, int], out_hw: tuple[int, int], *, index_dtype=torch.int64):
    """Flat input indices ``(4, B, Hout*Wout)`` (``index_dtype``) and weights (float64) of the bilinear warp.

    Index ``b * Hin * Win + row * Win + col`` addresses a batch of input planes. Computed in float64
    torch one batch element at a time, written into the preallocated results (no full-size
    temporaries: at 1024 px the 16 planes hold 16 M samples).
    """
    h = _as_homographies(homographies)
    hin, win = in_hw
    hout, wout = out_hw
    h_inv = torch.as_tensor(np.linalg.inv(h))                                    # (B, 3, 3) float64
    rows = torch.arange(hout, dtype=torch.float64)[:, None]
    cols = torch.arange(wout, dtype=torch.float64)[None, :]
    idx = torch.empty(4, h.shape[0], hout * wout, dtype=index_dtype)
    wts = torch.empty(4, h.shape[0], hout * wout, dtype=torch.float64)
    for b, a in enumerate(h_inv):
        w = a[2, 0] * cols + a[2, 1] * rows + a[2, 2]                              # row i of H^-1 (x, y, 1)^T
        w = torch.where(w.abs() < 1e-12, torch.full_like(w, 1e-12), w)
        sx = ((a[0, 0] * cols + a[0, 1] * rows + a[0, 2]) / w).clamp_(0.0, win - 1.0).reshape(-1)
        sy = ((a[1, 0] * cols + a[1, 1] * rows + a[1, 2]) / w).clamp_(0.0, hin - 1.0).reshape(-1)
        x0 = torch.floor(sx).clamp_(max=max(win - 2, 0))
        y0 = torch.floor(sy).clamp_(max=max(hin - 2, 0))
        fx, fy = sx - x0, sy - y0
        x0, y0 = x0.long(), y0.long()
        x1, y1 = (x0 + 1).clamp_(max=win - 1), (y0 + 1).clamp_(max=hin - 1)
        top, bottom = b * hin * win + y0 * win, b * hin * win + y1 * win
        idx[0, b], idx[1, b], idx[2, b], idx[3, b] = top + x0, top + x1, bottom + x0, bottom + x1
        gx, gy = 1 - fx, 1 - fy
        torch.mul(gx, gy, out=wts[0, b])
        torch.mul(fx, gy, out=wts[1, b])
        torch.mul(gx, fy, out=wts[2, b])
        torch.mul(fx, fy, out=wts[3, b])
    return idx, wts


class Warp(LinearOperator):
    """Per-batch homography warp: ``(B, C, Hin, Win) -> (B, C, Hout, Wout)``.

    ``homographies`` is ``(B, 3, 3)``: batch element b is warped by its own matrix, which
    maps input ``(x=col, y=row)`` to output coordinates. Forward is a 4-tap gather, the
    adjoint the matching ``index_add``.
    """

    name = "warp"

    def __init__(self, homographies, channels: int, in_hw: tuple[int, int], out_hw: tuple[int, int] | None = None):
        h = _as_homographies(homographies)
        out_hw = tuple(out_hw or in_hw)
        b = h.shape[0]
        super().__init__((b, channels, *in_hw), (b, channels, *out_hw))
        # (4, B*Nout) so each tap is one index_select over the flattened batch. One channel: int32 taps on
        # 1-D views halve the index traffic (forward 2-3x faster on CPU); several: int64 along dim 1
        # (int32 there makes index_add_ about 10x slower)
        int32 = channels == 1 and b * in_hw[0] * in_hw[1] < 2**31
        idx, wts = bilinear_taps(h, tuple(in_hw), out_hw, index_dtype=torch.int32 if int32 else torch.int64)
        self.index = idx.reshape(4, -1)
        self.weight = wts.reshape(4, -1)
        self.homographies = h

    def _forward(self, x):
        b, c, hin, win = self.input_shape
        idx = self._const("i", self.index, x)
        wts = self._const("w", self.weight, x)
        planes = _gathered_axis_last(x.permute(1, 0, 2, 3).reshape(c, b * hin * win))
        out = planes.index_select(-1, idx[0]) * wts[0]
        for t in range(1, 4):
            out.addcmul_(planes.index_select(-1, idx[t]), wts[t])
        return out.reshape(c, b, *self.output_shape[2:]).permute(1, 0, 2, 3).contiguous()

    def _adjoint(self, y):
        b, c, hin, win = self.input_shape
        idx = self._const("i", self.index, y)
        wts = self._const("w", self.weight, y)
        values = _gathered_axis_last(y.permute(1, 0, 2, 3).reshape(c, -1))
        out = y.new_zeros(c, b * hin * win)
        sums = _gathered_axis_last(out)
        for t in range(4):
            sums.index_add_(-1, idx[t], values * wts[t])
        return out.reshape(c, b, hin, win).permute(1, 0, 2, 3).contiguous()


def _gathered_axis_last(planes: torch.Tensor) -> torch.Tensor:
    """``(C, N)`` planes as the tensor the taps index along its last axis: one channel as a 1-D view
    (the ``int32`` taps of :class:`Warp` are fast there, and slow along dim 1 of a 2-D tensor)."""
    return planes[0] if planes.shape[0] == 1 else planes


def warp_image(image: torch.Tensor, homography, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
    """Warp a ``(C, H, W)`` image with one homography (input coords -> output coords)."""
    c, hh, ww = image.shape
    op = Warp(np.asarray(homography)[None], c, (hh, ww), out_hw)
    return op(image[None])[0]
