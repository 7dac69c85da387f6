"""Pixel integration and decimation (paper D_spatial).

* :class:`PixelIntegration`: ``s x s`` box mean anchored at the top-left sample,
  ``y[i, j] = mean x[i..i+s-1, j..j+s-1]`` (border replicated), so that after
  :class:`Decimation` by ``s`` output pixel ``i`` integrates input pixels ``s*i .. s*i+s-1``.
* :class:`Decimation`: keeps every ``s``-th sample starting at a per-batch offset.
* :class:`IntegrateDecimate`: both at once (``avg_pool2d``), the fast path, equal to
  ``Decimation(s) @ PixelIntegration(s)`` when ``H`` and ``W`` divide by ``s``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import InputError
from capssim.operators.base import LinearOperator
from capssim.operators.blur import fold_replicated_border


def _check_factor(factor: int, shape: tuple[int, ...]) -> None:
    h, w = shape[-2:]
    if factor < 1 or h % factor or w % factor:
        raise InputError("shape", f"{h}x{w} with factor {factor}",
                         f"height and width divisible by the factor {factor}",
                         "Crop the image to a multiple of the factor.")


class PixelIntegration(LinearOperator):
    """Anchored ``s x s`` box mean, ``(..., H, W) -> (..., H, W)``."""

    name = "pixel_integration"

    def __init__(self, factor: int, shape: tuple[int, ...]):
        super().__init__(shape, shape)
        self.factor = int(factor)
        self.pad = (0, self.factor - 1, 0, self.factor - 1)  # (left, right, top, bottom), replicated
        self.kernel = torch.full((1, 1, self.factor, self.factor), 1.0 / self.factor**2, dtype=torch.float64)

    def _forward(self, x):
        h, w = self.input_shape[-2:]
        padded = F.pad(x.reshape(-1, 1, h, w), self.pad, mode="replicate")
        return F.conv2d(padded, self._const("k", self.kernel, x)).reshape(self.output_shape)

    def _adjoint(self, y):
        h, w = self.input_shape[-2:]
        padded = F.conv_transpose2d(y.reshape(-1, 1, h, w), self._const("k", self.kernel, y))
        return fold_replicated_border(padded[:, 0], self.pad).reshape(self.input_shape)


class Decimation(LinearOperator):
    """Keep samples ``(s*i + oy, s*j + ox)``: ``(B, ..., H, W) -> (B, ..., H/s, W/s)``.

    ``offsets`` is one ``(oy, ox)`` for all, or ``(B, 2)`` with one per batch element
    (dimension 0 of the input). The adjoint puts samples back and fills zeros.
    """

    name = "decimation"

    def __init__(self, factor: int, shape: tuple[int, ...], offsets: Sequence | None = None):
        _check_factor(factor, shape)
        s = int(factor)
        h, w = shape[-2:]
        super().__init__(shape, (*shape[:-2], h // s, w // s))
        off = np.zeros((1, 2), dtype=np.int64) if offsets is None else np.asarray(offsets, dtype=np.int64).reshape(-1, 2)
        if off.shape[0] not in (1, shape[0]) or off.min() < 0 or off.max() >= s:
            raise InputError("offsets", off.tolist(), f"one (oy, ox) or {shape[0]} of them, each in [0, {s})")
        self.factor = s
        rows = s * np.arange(h // s)[None, :, None] + off[:, 0, None, None]
        cols = s * np.arange(w // s)[None, None, :] + off[:, 1, None, None]
        plane = np.broadcast_to(rows * w + cols, (off.shape[0], h // s, w // s))
        self.per_batch = off.shape[0] > 1
        self.plane_index = torch.from_numpy(np.array(plane.reshape(off.shape[0], -1), copy=True))

    def _flat(self, t, hw):
        b = self.input_shape[0]
        return t.reshape(b, -1, hw)

    def _forward(self, x):
        h, w = self.input_shape[-2:]
        flat = self._flat(x, h * w)
        idx = self._const("p", self.plane_index, x)
        idx = idx[:, None, :].expand(flat.shape[0], flat.shape[1], -1)
        return torch.gather(flat, 2, idx).reshape(self.output_shape)

    def _adjoint(self, y):
        h, w = self.input_shape[-2:]
        hs, ws = self.output_shape[-2:]
        flat = self._flat(y, hs * ws)
        idx = self._const("p", self.plane_index, y)
        idx = idx[:, None, :].expand(flat.shape[0], flat.shape[1], -1)
        out = y.new_zeros(flat.shape[0], flat.shape[1], h * w)
        out.scatter_(2, idx, flat)
        return out.reshape(self.input_shape)


class IntegrateDecimate(LinearOperator):
    """``s x s`` pixel integration followed by decimation: ``(..., H, W) -> (..., H/s, W/s)``."""

    name = "integrate_decimate"

    def __init__(self, factor: int, shape: tuple[int, ...]):
        _check_factor(factor, shape)
        self.factor = int(factor)
        h, w = shape[-2:]
        super().__init__(shape, (*shape[:-2], h // self.factor, w // self.factor))

    def _forward(self, x):
        h, w = self.input_shape[-2:]
        return F.avg_pool2d(x.reshape(-1, 1, h, w), self.factor).reshape(self.output_shape)

    def _adjoint(self, y):
        s = self.factor
        up = y.repeat_interleave(s, dim=-2).repeat_interleave(s, dim=-1)
        return (up / (s * s)).reshape(self.input_shape)
