"""PSF blur, pixel integration and decimation fused into one strided convolution (paper D_spatial).

``Decimation(d, offsets) @ IntegrateDecimate(s) @ Convolve(K)`` keeps one sample in ``(s d)^2`` of the
blurred image. Its output pixel ``(i, j)`` of a plane with offset ``(oy, ox)`` is

    ``y[i, j] = sum_{t, u} K'[t, u] x_pad[S i + s oy + t, S j + s ox + u]``,  ``S = s d``,

with ``K' = K * box_s / s^2`` (the full convolution of the PSF with the ``s x s`` box, size
``kh + s - 1``) and ``x_pad`` the image with its border replicated by the kernel's half-size. Each
plane's offset shifts its kernel by ``(s oy, s ox)`` inside a common ``(kh + s - 1 + s (d - 1))``-wide
support, so the forward is one grouped ``conv2d`` of stride ``S`` over all planes and the adjoint its
``conv_transpose2d``, folded back through the replicated border: the same linear map as the three
operators (to rounding), at ``1 / S^2`` of the blur's work.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import InputError
from capssim.operators.base import LinearOperator
from capssim.operators.blur import fold_replicated_border, stack_kernels
from capssim.operators.sampling import _check_factor


def integrated_kernels(kernels: np.ndarray, factor: int) -> np.ndarray:
    """``(G, kh, kw)`` -> ``(G, kh + s - 1, kw + s - 1)``: each kernel convolved with the ``s x s`` box mean."""
    g, kh, kw = kernels.shape
    out = np.zeros((g, kh + factor - 1, kw + factor - 1))
    for a in range(factor):
        for b in range(factor):
            out[:, a:a + kh, b:b + kw] += kernels
    return out / factor**2


class BlurIntegrateDecimate(LinearOperator):
    """``(B, ..., H, W) -> (B, ..., H/S, W/S)``, ``S = integrate * decimate``: equal to
    ``Decimation(decimate, offsets) @ IntegrateDecimate(integrate) @ Convolve(kernel)``.

    ``kernel``: one odd kernel, or ``G`` of them shared by consecutive planes as in
    :class:`~capssim.operators.blur.Convolve`. ``offsets``: one ``(oy, ox)`` or one per batch element
    (dimension 0), each in ``[0, decimate)``, as in :class:`~capssim.operators.sampling.Decimation`.
    """

    name = "blur_integrate_decimate"

    def __init__(self, kernel, shape: tuple[int, ...], *, integrate: int, decimate: int,
                 offsets: Sequence | None = None):
        stride = int(integrate) * int(decimate)
        _check_factor(stride, shape)
        h, w = shape[-2:]
        super().__init__(shape, (*shape[:-2], h // stride, w // stride))
        k = stack_kernels(kernel)
        planes = int(np.prod(shape[:-2]))
        if planes % k.shape[0]:
            raise InputError("kernel", f"{k.shape[0]} kernels", f"a number of kernels dividing the {planes} planes")
        off = np.zeros((1, 2), dtype=np.int64) if offsets is None else np.asarray(offsets, dtype=np.int64).reshape(-1, 2)
        if off.shape[0] not in (1, shape[0]) or off.min() < 0 or off.max() >= decimate:
            raise InputError("offsets", off.tolist(), f"one (oy, ox) or {shape[0]} of them, each in [0, {decimate})")
        per_plane = np.repeat(np.broadcast_to(off, (shape[0], 2)), planes // shape[0], axis=0)  # (planes, 2)
        big = integrated_kernels(k, int(integrate))[np.arange(planes) // (planes // k.shape[0])]
        self.stride, self.pad = stride, (k.shape[1] // 2, k.shape[2] // 2)
        # each plane's offset moves its kernel inside a common support: one grouped conv for all planes
        reach = (int(decimate) - 1) * int(integrate)
        shifted = np.zeros((planes, 1, big.shape[1] + reach, big.shape[2] + reach))
        for p, (oy, ox) in enumerate(per_plane * int(integrate)):
            shifted[p, 0, oy:oy + big.shape[1], ox:ox + big.shape[2]] = big[p]
        self.kernels = torch.from_numpy(shifted)

    def _forward(self, x):
        h, w = self.input_shape[-2:]
        n = x.numel() // (h * w)
        ph, pw = self.pad
        padded = F.pad(x.reshape(1, n, h, w), (pw, pw, ph, ph), mode="replicate")
        y = F.conv2d(padded, self._const("k", self.kernels, x), stride=self.stride, groups=n)
        return y.reshape(self.output_shape)

    def _adjoint(self, y):
        ho, wo = self.output_shape[-2:]
        flat = y.reshape(1, -1, ho, wo)
        padded = F.conv_transpose2d(flat, self._const("k", self.kernels, y), stride=self.stride, groups=flat.shape[1])
        ph, pw = self.pad
        return fold_replicated_border(padded[0], (pw, pw, ph, ph)).reshape(self.input_shape)
