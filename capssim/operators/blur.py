"""Optical blur: 2-D convolution with a PSF kernel, border replicated (paper D_spatial).

The PSF kernels are pixel-integrated: each tap is the PSF's energy over one pixel of the
grid the kernel is applied on, so ``sigma -> 0`` gives the identity.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import InputError
from capssim.operators.base import LinearOperator


def fold_replicated_border(padded: torch.Tensor, pad: tuple[int, int, int, int]) -> torch.Tensor:
    """Adjoint of ``F.pad(x, pad, mode="replicate")`` with ``pad = (left, right, top, bottom)``:
    ``(N, H + top + bottom, W + left + right) -> (N, H, W)``. The border strips are summed onto the edge
    rows and columns they were copied from (in place)."""
    left, right, top, bottom = pad
    hp, wp = padded.shape[-2:]
    if left:
        padded[:, :, left] += padded[:, :, :left].sum(-1)
    if right:
        padded[:, :, wp - right - 1] += padded[:, :, wp - right:].sum(-1)
    if top:
        padded[:, top] += padded[:, :top].sum(-2)
    if bottom:
        padded[:, hp - bottom - 1] += padded[:, hp - bottom:].sum(-2)
    return padded[:, top:hp - bottom, left:wp - right].contiguous()


def stack_kernels(kernel) -> np.ndarray:
    """``(G, kh, kw)`` float64 from one odd 2-D kernel or a sequence/stack of them.

    Kernels of different odd sizes are zero-padded (centred) to the largest.
    """
    if isinstance(kernel, (list, tuple)):
        ks = [np.asarray(k, dtype=np.float64) for k in kernel]
    else:
        arr = np.asarray(kernel, dtype=np.float64)
        ks = [arr] if arr.ndim == 2 else list(arr) if arr.ndim == 3 else [arr]
    for k in ks:
        if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
            raise InputError("kernel", f"shape {k.shape}", "a 2-D kernel with odd height and width (or a stack of them)")
    kh, kw = max(k.shape[0] for k in ks), max(k.shape[1] for k in ks)
    out = np.zeros((len(ks), kh, kw))
    for g, k in enumerate(ks):
        top, left = (kh - k.shape[0]) // 2, (kw - k.shape[1]) // 2
        out[g, top:top + k.shape[0], left:left + k.shape[1]] = k
    return out


class Convolve(LinearOperator):
    """``(..., H, W) -> (..., H, W)`` correlation with an odd ``kernel``, border replicated.

    ``kernel``: one ``(kh, kw)`` kernel for every plane, or ``G`` kernels (a ``(G, kh, kw)``
    stack or a list of odd kernels of any sizes): plane ``p`` of the flattened leading axes
    uses kernel ``p // (planes // G)`` (e.g. one PSF per aperture of ``(4, 3, H, W)``).

    Forward = replicate-pad then valid ``conv2d``; adjoint = ``conv_transpose2d`` then the pad's
    adjoint (:func:`fold_replicated_border`).
    """

    name = "convolve"

    def __init__(self, kernel, shape: tuple[int, ...]):
        k = stack_kernels(kernel)
        planes = int(np.prod(shape[:-2])) if len(shape) > 2 else 1
        if planes % k.shape[0]:
            raise InputError("kernel", f"{k.shape[0]} kernels", f"a number of kernels dividing the {planes} planes")
        super().__init__(shape, shape)
        self.kernel = torch.as_tensor(k)[:, None]  # (G, 1, kh, kw)
        self.pad = (k.shape[1] // 2, k.shape[2] // 2)
        self.is_identity = k.shape[1:] == (1, 1) and bool(np.all(k[:, 0, 0] == 1.0))

    def _grouped_kernel(self, like, n: int, *, flipped: bool = False):
        # planes as channels of one grouped conv: much faster on CPU than a batch of 1-channel convs;
        # consecutive blocks of n // G planes share kernel g
        k = self._const("kf" if flipped else "k", torch.flip(self.kernel, (2, 3)) if flipped else self.kernel, like)
        if k.shape[0] == 1:
            return k.expand(n, 1, *k.shape[2:])
        return k.repeat_interleave(n // k.shape[0], dim=0)

    def _forward(self, x):
        if self.is_identity:
            return x.clone()
        h, w = self.input_shape[-2:]
        n = x.numel() // (h * w)
        ph, pw = self.pad
        padded = F.pad(x.reshape(1, n, h, w), (pw, pw, ph, ph), mode="replicate")
        return F.conv2d(padded, self._grouped_kernel(x, n), groups=n).reshape(self.output_shape)

    def _adjoint(self, y):
        if self.is_identity:
            return y.clone()
        h, w = self.input_shape[-2:]
        n = y.numel() // (h * w)
        ph, pw = self.pad
        # conv_transpose2d(y, k) written as a full correlation with the flipped kernel
        full = F.pad(y.reshape(1, n, h, w), (2 * pw, 2 * pw, 2 * ph, 2 * ph))
        padded = F.conv2d(full, self._grouped_kernel(y, n, flipped=True), groups=n).reshape(n, h + 2 * ph, w + 2 * pw)
        return fold_replicated_border(padded, (pw, pw, ph, ph)).reshape(self.input_shape)
