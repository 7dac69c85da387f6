"""Bilinear homography warp with an exact scatter-add adjoint (paper eq. 9-11, W_n).

Coordinates are ``(x=col, y=row)`` with pixel centres on integers, as in OpenCV. A
homography ``H`` maps *input* coordinates to *output* coordinates; output pixel ``p``
samples the input at ``H^-1 p`` by bilinear interpolation. Samples falling outside the
input are clamped to its border (replicate), which keeps the map linear and its adjoint
exact. The sample positions are float64 until cast to the image's dtype (float32: about
1e-4 px at 1024 px).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

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
    singular = np.flatnonzero(np.abs(det) < 1e-12)
    if singular.size:  # one line: the indices and determinants of the singular ones, never the whole array
        listed = ", ".join(f"[{i}] (determinant {det[i]:.3g})" for i in singular[:4])
        more = f" and {singular.size - 4} more" if singular.size > 4 else ""
        raise InputError("homographies", f"{singular.size} singular of {len(det)}: {listed}{more}",
                         "invertible 3x3 matrices (|determinant| >= 1e-12)")
    return h


def sampling_grid(homographies, in_hw: tuple[int, int], out_hw: tuple[int, int]) -> torch.Tensor:
    """Where each output pixel samples the input: ``(B, Hout, Wout, 2)`` float64 ``(x, y)`` of ``H^-1 p``,
    clamped to the input and normalized to ``[-1, 1]`` (``grid_sample``'s ``align_corners=True`` convention).

    Computed one batch element at a time into the preallocated result (at 1024 px the 16 planes
    of CAPS hold 16 M samples).
    """
    h = _as_homographies(homographies)
    hin, win = in_hw
    hout, wout = out_hw
    h_inv = torch.as_tensor(np.linalg.inv(h))                                    # (B, 3, 3) float64
    rows = torch.arange(hout, dtype=torch.float64)[:, None]
    cols = torch.arange(wout, dtype=torch.float64)[None, :]
    grid = torch.empty(h.shape[0], hout, wout, 2, dtype=torch.float64)
    for b, a in enumerate(h_inv):
        w = a[2, 0] * cols + a[2, 1] * rows + a[2, 2]                              # row i of H^-1 (x, y, 1)^T
        w = torch.where(w.abs() < 1e-12, torch.full_like(w, 1e-12), w)
        for axis, size in ((0, win), (1, hin)):
            coord = ((a[axis, 0] * cols + a[axis, 1] * rows + a[axis, 2]) / w).clamp_(0.0, size - 1.0)
            grid[b, :, :, axis] = coord.mul_(2.0 / max(size - 1, 1)).sub_(1.0)
    return grid


class Warp(LinearOperator):
    """Per-batch homography warp: ``(B, C, Hin, Win) -> (B, C, Hout, Wout)``.

    ``homographies`` is ``(B, 3, 3)``: batch element b is warped by its own matrix, which
    maps input ``(x=col, y=row)`` to output coordinates. Forward is ``grid_sample`` (bilinear,
    border padding) at :func:`sampling_grid`, the adjoint its input gradient (the same weights
    scattered back), on CPU and CUDA alike.
    """

    name = "warp"

    def __init__(self, homographies, channels: int, in_hw: tuple[int, int], out_hw: tuple[int, int] | None = None):
        h = _as_homographies(homographies)
        out_hw = tuple(out_hw or in_hw)
        super().__init__((h.shape[0], channels, *in_hw), (h.shape[0], channels, *out_hw))
        self.homographies = h

    def _grid(self, like: torch.Tensor) -> torch.Tensor:
        """:func:`sampling_grid` in ``like``'s dtype and device, made once per dtype and device."""
        key = ("grid", like.dtype, like.device)
        grid = self._cast_cache.get(key)
        if grid is None:
            grid = sampling_grid(self.homographies, self.input_shape[2:], self.output_shape[2:])
            grid = self._cast_cache[key] = grid.to(device=like.device, dtype=like.dtype)
        return grid

    def _forward(self, x):
        return F.grid_sample(x, self._grid(x), mode="bilinear", padding_mode="border", align_corners=True)

    def _adjoint(self, y):
        shape_only = y.new_zeros(()).expand(self.input_shape)  # the kernel reads the input's shape, not its values
        return torch.ops.aten.grid_sampler_2d_backward(y.contiguous(), shape_only, self._grid(y), _BILINEAR, _BORDER,
                                                       True, [True, False])[0]


#: ``grid_sampler_2d``'s codes for bilinear interpolation and border padding
_BILINEAR, _BORDER = 0, 1


def warp_image(image: torch.Tensor, homography, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
    """Warp a ``(C, H, W)`` image with one homography (input coords -> output coords)."""
    c, hh, ww = image.shape
    op = Warp(np.asarray(homography)[None], c, (hh, ww), out_hw)
    return op(image[None])[0]
