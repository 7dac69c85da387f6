"""PSF blur, pixel integration and decimation fused into one strided convolution (paper D_spatial).

``Decimation(d, offsets) @ IntegrateDecimate(s) @ Convolve(K)`` keeps one sample in ``(s d)^2`` of the
blurred image. Its output pixel ``(i, j)`` of a plane with offset ``(oy, ox)`` is

    ``y[i, j] = sum_{t, u} K'[t, u] x_pad[S i + s oy + t, S j + s ox + u]``,  ``S = s d``,

with ``K' = K * box_s / s^2`` (the full convolution of the PSF with the ``s x s`` box, size
``kh + s - 1``) and ``x_pad`` the image with its border replicated by the kernel's half-size. So the
forward is one ``conv2d`` of stride ``S`` per distinct offset and the adjoint its
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
        big = integrated_kernels(k, int(integrate))
        kernel_of_plane = np.arange(planes) // (planes // k.shape[0])
        self.integrate, self.stride = int(integrate), stride
        self.pad = (k.shape[1] // 2, k.shape[2] // 2)
        # one strided conv per distinct offset: (row/col start, its planes, their kernels (n, 1, kh', kw'))
        self.groups = []
        for oy, ox in np.unique(per_plane, axis=0):
            members = np.flatnonzero((per_plane[:, 0] == oy) & (per_plane[:, 1] == ox))
            self.groups.append(((int(oy) * self.integrate, int(ox) * self.integrate), _as_slice(members),
                                torch.from_numpy(big[kernel_of_plane[members]][:, None].copy())))

    def _planes(self, t: torch.Tensor, members, key: str, like: torch.Tensor) -> torch.Tensor:
        if isinstance(members, slice):
            return t[members]
        return t.index_select(0, self._const(key, members, like))

    def _forward(self, x):
        h, w = self.input_shape[-2:]
        n = x.numel() // (h * w)
        ph, pw = self.pad
        ho, wo = h // self.stride, w // self.stride
        padded = F.pad(x.reshape(1, n, h, w), (pw, pw, ph, ph), mode="replicate")[0]
        out = x.new_empty(n, ho, wo)
        for g, ((ry, rx), members, kernels) in enumerate(self.groups):
            part = self._planes(padded, members, f"m{g}", x)[None, :, ry:, rx:]
            y = F.conv2d(part, self._const(f"k{g}", kernels, x), stride=self.stride, groups=part.shape[1])
            if isinstance(members, slice):
                out[members] = y[0, :, :ho, :wo]
            else:
                out.index_copy_(0, self._const(f"m{g}", members, x), y[0, :, :ho, :wo])
        return out.reshape(self.output_shape)

    def _adjoint(self, y):
        h, w = self.input_shape[-2:]
        ph, pw = self.pad
        ho, wo = h // self.stride, w // self.stride
        flat = y.reshape(-1, ho, wo)
        padded = y.new_zeros(flat.shape[0], h + 2 * ph, w + 2 * pw)
        for g, ((ry, rx), members, kernels) in enumerate(self.groups):
            part = self._planes(flat, members, f"m{g}", y).contiguous()[None]
            back = F.conv_transpose2d(part, self._const(f"k{g}", kernels, y), stride=self.stride,
                                      groups=part.shape[1])[0]
            bh, bw = back.shape[-2:]
            if isinstance(members, slice):
                padded[members, ry:ry + bh, rx:rx + bw] += back
            else:
                padded[:, ry:ry + bh, rx:rx + bw].index_add_(0, self._const(f"m{g}", members, y), back)
        return fold_replicated_border(padded, ph, pw).reshape(self.input_shape)


def _as_slice(members: np.ndarray):
    """``members`` as a ``slice`` when they are an arithmetic progression, else as an index tensor."""
    step = int(members[1] - members[0]) if members.size > 1 else 1
    if step > 0 and np.array_equal(members, members[0] + step * np.arange(members.size)):
        return slice(int(members[0]), int(members[-1]) + 1, step)
    return torch.from_numpy(members)
