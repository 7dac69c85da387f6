"""Shared helpers of the DoFP colour-polarization demosaicking baselines.

Geometry of the mosaic (docs: guides/captures.md, "Conventions", :func:`capssim.conventions.dofp_channel_map`):
the mosaic is ``(H, W)`` at the HR pitch; pixel ``(r, c)`` (row, col) sits behind the polarizer
``layout[r % 2][c % 2]`` and the colour filter ``RGGB[(r // 2) % 2][(c // 2) % 2]`` (quad Bayer,
4x4 period). Hence:

* the pixels with cell offset ``(dr, dc)`` all share one polarizer angle and form a
  half-resolution *sub-mosaic* ``mosaic[dr::2, dc::2]``, shape ``(H/2, W/2)``, which is a plain
  RGGB Bayer image (R at its (0, 0)) whatever the layout;
* sub-mosaic pixel ``(i, j)`` lies at full-resolution position ``(2i + dr, 2j + dc)``: each
  polarization lattice has its own sub-pixel offset, which the interpolation must respect.

Everything here is torch, device-agnostic and vectorized (no loops over pixels); images are
``(..., H, W)`` tensors. Filters are correlations (not convolutions, as MATLAB ``imfilter``),
the kernel centre on the output pixel, mirror-padded (see :func:`correlate`).
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
import torch

from capssim.conventions import BAYER_RGGB, POLARIZER_ANGLES_DEG, dofp_layout
from capssim.errors import InputError

log = logging.getLogger(__name__)

#: smallest mosaic side the DoFP methods accept (three 4x4 colour-polarization periods; the
#: 9-tap filters of the colour stage mirror-pad its half-resolution sub-mosaics by 4)
MIN_MOSAIC_SIZE = 12

#: bilinear interpolation kernel of a lattice with period 2 in both axes (R/B Bayer sites,
#: one polarizer angle of a 2x2 cell)
KERNEL_BILINEAR_RECT = ((0.25, 0.5, 0.25), (0.5, 1.0, 0.5), (0.25, 0.5, 0.25))
#: bilinear interpolation kernel of a quincunx lattice (Bayer G sites)
KERNEL_BILINEAR_QUINCUNX = ((0.0, 0.25, 0.0), (0.25, 1.0, 0.25), (0.0, 0.25, 0.0))


# -- input checking and conversion ---------------------------------------------------------------
def check_mosaic(mosaic, *, argument: str = "mosaic", device: torch.device | str | None = None,
                 dtype: torch.dtype | None = None) -> torch.Tensor:
    """Validate a DoFP mosaic and return it as a float tensor ``(H, W)``.

    Accepts a numpy array or a torch tensor: 2-D, floating point (raw DN must be converted
    first, e.g. with :meth:`capssim.camera.sensor.Sensor.to_float`), finite, both sides even and at
    least :data:`MIN_MOSAIC_SIZE`. Odd sides are rejected: the 2x2 polarizer cell would be cut
    (``capssim demosaic --trim-odd`` drops the last row/column instead). The tensor is float64
    when the input is float64 (or ``dtype`` says so), else float32.
    """
    if isinstance(mosaic, torch.Tensor):
        t = mosaic
    else:
        arr = np.asarray(mosaic)
        if arr.dtype == object:
            raise InputError(argument, "an object array", "a 2-D float array")
        t = torch.from_numpy(np.ascontiguousarray(arr))
    if t.ndim != 2:
        raise InputError(argument, f"shape {tuple(t.shape)}", "a 2-D mosaic (H, W): one value per pixel",
                         "A colour image is not a raw mosaic; pass the single-channel raw frame.")
    if not (t.is_floating_point()):
        raise InputError(argument, f"dtype {t.dtype}", "a float mosaic on [0, 1] of full scale",
                         "Convert raw DN first (e.g. DN / (2**bits - 1), or Sensor.to_float).")
    h, w = t.shape
    if h % 2 or w % 2:
        raise InputError(argument, f"size {h}x{w}", "an even height and width (whole 2x2 polarizer cells)",
                         "Drop the last row/column (capssim demosaic --trim-odd).")
    if h < MIN_MOSAIC_SIZE or w < MIN_MOSAIC_SIZE:
        raise InputError(argument, f"size {h}x{w}", f"at least {MIN_MOSAIC_SIZE}x{MIN_MOSAIC_SIZE} pixels")
    if dtype is None:
        dtype = torch.float64 if t.dtype == torch.float64 else torch.float32
    t = t.to(device=device if device is not None else t.device, dtype=dtype)
    if not bool(torch.isfinite(t).all()):
        raise InputError(argument, f"{int((~torch.isfinite(t)).sum())} NaN/inf values", "finite values")
    return t


def as_output(image: torch.Tensor, like) -> np.ndarray | torch.Tensor:
    """Return ``image`` as the caller gave its input: a tensor stays a tensor, else float32 numpy."""
    if isinstance(like, torch.Tensor):
        return image
    return image.detach().to("cpu", torch.float32).numpy()


# -- layout ------------------------------------------------------------------------------------
def angle_offsets(layout="sony") -> tuple[tuple[int, int], ...]:
    """Cell offset ``(dr, dc)`` of each polarizer angle, in the order (0, 45, 90, 135) deg."""
    cell = dofp_layout(layout)
    where = {cell[r][c]: (r, c) for r in range(2) for c in range(2)}
    return tuple(where[a] for a in POLARIZER_ANGLES_DEG)


def split_submosaics(mosaic: torch.Tensor, layout="sony") -> torch.Tensor:
    """``(..., H, W)`` -> ``(..., 4, H/2, W/2)``: the RGGB sub-mosaic of each angle (0, 45, 90, 135)."""
    return torch.stack([mosaic[..., dr::2, dc::2] for dr, dc in angle_offsets(layout)], dim=-3)


def merge_submosaics(subs: torch.Tensor, layout="sony") -> torch.Tensor:
    """Inverse of :func:`split_submosaics`: ``(..., 4, h, w)`` -> ``(..., 2h, 2w)``.

    Pixel ``(2i + dr_p, 2j + dc_p)`` takes ``subs[..., p, i, j]``. With a colour axis in
    ``...`` this builds the "RGB polarization mosaic": every pixel carries the colours of its
    own polarizer angle.
    """
    *lead, n, h, w = subs.shape
    if n != 4:
        raise ValueError(f"merge_submosaics: expected 4 sub-mosaics, got {n}")
    out = subs.new_empty((*lead, 2 * h, 2 * w))
    for p, (dr, dc) in enumerate(angle_offsets(layout)):
        out[..., dr::2, dc::2] = subs[..., p, :, :]
    return out


def polarization_masks(height: int, width: int, layout="sony", *, device=None,
                       dtype=torch.float32) -> torch.Tensor:
    """``(4, H, W)``: 1 where polarizer angle p (0, 45, 90, 135) is sampled, else 0."""
    masks = torch.zeros((4, height, width), device=device, dtype=dtype)
    for p, (dr, dc) in enumerate(angle_offsets(layout)):
        masks[p, dr::2, dc::2] = 1
    return masks


def bayer_masks(height: int, width: int, *, device=None, dtype=torch.float32) -> torch.Tensor:
    """``(3, h, w)`` RGGB site masks (R at (0, 0)); channel k is colour k (R, G, B)."""
    rows = torch.arange(height, device=device)[:, None] % 2
    cols = torch.arange(width, device=device)[None, :] % 2
    colour = torch.as_tensor(BAYER_RGGB, device=device)[rows, cols]
    return torch.stack([(colour == k) for k in range(3)]).to(dtype)


def clip_ceiling(mosaic: torch.Tensor) -> float:
    """Upper clip of intermediate estimates: 1 (full scale), or the mosaic maximum if larger."""
    return max(1.0, float(mosaic.max()))


def stack_12(images: Sequence[torch.Tensor] | torch.Tensor) -> torch.Tensor:
    """``(4 [angle], 3 [colour], H, W)`` -> ``(12, H, W)`` in the order ``c = 3*p + k``."""
    x = images if isinstance(images, torch.Tensor) else torch.stack(list(images))
    return x.reshape(12, *x.shape[-2:])


