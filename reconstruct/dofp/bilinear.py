"""Two-step bilinear demosaicking of a colour-polarization DoFP mosaic (the method ``dofp-bilinear``).

Reference: the common baseline of colour-polarization demosaicking comparisons, as implemented
in polanalyser (Maeda, ``polanalyser.demosaicing`` with ``COLOR_PolarRGB``) and used as
"Bilinear" in Morimatsu et al., ICIP 2020 and Qiu et al., 2021:

1. Colour. Split the mosaic ``(H, W)`` into its four polarizer sub-mosaics
   ``mosaic[dr::2, dc::2]`` (``(H/2, W/2)`` each, one per angle; each is an RGGB Bayer image)
   and demosaick each by bilinear interpolation: G from its 4 direct neighbours (kernel
   ``[[0,1,0],[1,4,1],[0,1,0]]/4``), R and B from their 2 or 4 neighbours (kernel
   ``[[1,2,1],[2,4,2],[1,2,1]]/4``).
2. Polarization. Put each sub-mosaic's RGB back at its own lattice ``(2i + dr, 2j + dc)`` of the
   full grid and fill the other three pixels of every 2x2 cell by bilinear interpolation of that
   lattice (kernel ``[[1,2,1],[2,4,2],[1,2,1]]/4`` on the full grid).

Both steps use normalized convolution (:func:`capssim.reconstruct.filters.normalized_interpolation`),
which equals the plain kernels in the interior and averages the available samples at the borders.
Float end to end. Exactness: constant images are reproduced exactly everywhere; linear ramps are
reproduced exactly except in a border band of 4 pixels (the bilinear kernels need both neighbours;
``tests/reconstruction/test_dofp_methods.py`` checks this). The registered method is
:mod:`capssim.reconstruct.methods.dofp_bilinear`; the learned ``cpdnet`` starts from this demosaicking.
"""

from __future__ import annotations

import numpy as np
import torch

from ..filters import normalized_interpolation
from ..run_context import stage_factory
from .mosaic import (
    KERNEL_BILINEAR_QUINCUNX,
    KERNEL_BILINEAR_RECT,
    angle_offsets,
    as_output,
    bayer_masks,
    check_mosaic,
    split_submosaics,
    stack_12,
)

__all__ = ["bilinear_bayer", "bilinear_polarization", "demosaic_dofp_bilinear", "dofp_unobserved"]


def bilinear_bayer(raw: torch.Tensor) -> torch.Tensor:
    """Bilinear demosaicking of RGGB images: ``(..., h, w)`` -> ``(..., 3, h, w)``."""
    h, w = raw.shape[-2:]
    masks = bayer_masks(h, w, device=raw.device, dtype=raw.dtype)
    red = normalized_interpolation(raw, masks[0], KERNEL_BILINEAR_RECT)
    green = normalized_interpolation(raw, masks[1], KERNEL_BILINEAR_QUINCUNX)
    blue = normalized_interpolation(raw, masks[2], KERNEL_BILINEAR_RECT)
    return torch.stack([red, green, blue], dim=-3)


def bilinear_polarization(sub_rgb: torch.Tensor, layout="sony") -> torch.Tensor:
    """``(4 [angle], C, h, w)`` half-resolution images -> ``(4, C, 2h, 2w)`` full resolution.

    Angle p's samples are placed at its lattice ``(2i + dr_p, 2j + dc_p)`` and the lattice is
    filled by bilinear interpolation.
    """
    n, c, h, w = sub_rgb.shape
    full = sub_rgb.new_zeros((n, c, 2 * h, 2 * w))
    mask = sub_rgb.new_zeros((n, 1, 2 * h, 2 * w))
    for p, (dr, dc) in enumerate(angle_offsets(layout)):
        full[p, :, dr::2, dc::2] = sub_rgb[p]
        mask[p, :, dr::2, dc::2] = 1
    return normalized_interpolation(full, mask, KERNEL_BILINEAR_RECT)


def demosaic_dofp_bilinear(mosaic, *, layout="sony", device: str | torch.device | None = None, timer=None):
    """Two-step bilinear demosaicking of a DoFP mosaic ``(H, W)`` -> ``(12, H, W)`` (``c = 3p + k``).

    ``mosaic``: float numpy array or tensor on [0, 1], even sides >= 12. A numpy input gives a
    float32 numpy result, a tensor input a tensor on the same (or the given) device. ``layout``:
    the 2x2 polarizer cell (``'sony'``, ``'0-45-135-90'`` or ``[[a, b], [c, d]]`` degrees).
    ``timer``: optional :class:`capssim.reconstruct.registry.StageTimer` to record the two stages.
    """
    stage = stage_factory(timer)
    x = check_mosaic(mosaic, device=device)
    with stage("bayer_bilinear"):
        sub_rgb = bilinear_bayer(split_submosaics(x, layout))  # (4, 3, H/2, W/2)
    with stage("polarization_bilinear"):
        out = stack_12(bilinear_polarization(sub_rgb, layout))
    return as_output(out, mosaic)


def dofp_unobserved(saturated, layout="sony", *, reach: int = 3) -> np.ndarray:
    """``(12, H, W)`` bool: pixels with no unsaturated sample of their channel within ``reach`` pixels.

    ``saturated`` ``(H, W)`` is the DoFP mosaic's saturation mask (H, W multiples of 4); a
    channel ``c = 3 p + k`` is sampled at the Bayer-``k`` sites of angle ``p``'s sub-mosaic,
    one or two per 4x4 period, so ``reach`` 3 (a 7x7 window) finds one everywhere in a clean mosaic,
    borders included.
    """
    from scipy.ndimage import maximum_filter

    sat = np.asarray(saturated, dtype=bool)
    h, w = sat.shape
    sites = np.zeros((4, 3, h, w), dtype=bool)
    colour = bayer_masks(h // 2, w // 2).numpy().astype(bool)
    for p, (dr, dc) in enumerate(angle_offsets(layout)):
        sites[p, :, dr::2, dc::2] = colour
    usable = (sites & ~sat).reshape(12, h, w)
    return ~maximum_filter(usable, size=(1, 2 * reach + 1, 2 * reach + 1), mode="constant")
