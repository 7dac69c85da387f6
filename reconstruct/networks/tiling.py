"""Inference in overlapping tiles, so a network's activations stay bounded on large images."""

from __future__ import annotations

from typing import Callable

import torch


def tile_starts(length: int, tile: int, halo: int, step: int) -> list[tuple[int, int, int, int]]:
    """``(read_start, read_end, keep_start, keep_end)`` per tile along one axis; starts on multiples of ``step``."""
    if length <= tile:
        return [(0, length, 0, length)]
    out, keep = [], 0
    while keep < length:
        keep_end = min(length, keep + tile)
        read = max(0, (keep - halo) // step * step)
        read_end = min(length, keep_end + halo)
        out.append((read, read_end, keep, keep_end))
        keep = keep_end
    return out


@torch.no_grad()
def apply_tiled(fn: Callable[..., torch.Tensor], inputs: tuple[torch.Tensor, ...], *, scale: int = 1,
                tile: int = 256, halo: int = 16, step: int = 4) -> torch.Tensor:
    """``fn(*inputs)`` for ``(N, C, H, W)`` inputs, computed in tiles of ``tile`` input pixels.

    Each tile reads ``halo`` pixels more on every side (at least the network's receptive radius)
    and keeps its centre; tile reads start on multiples of ``step`` (the mosaic period). ``scale``:
    output pixels per input pixel. Equals the untiled result where the halo covers the receptive field.
    """
    h, w = inputs[0].shape[-2:]
    rows, cols = tile_starts(h, tile, halo, step), tile_starts(w, tile, halo, step)
    out = None
    for r0, r1, k0, k1 in rows:
        for c0, c1, q0, q1 in cols:
            y = fn(*(x[..., r0:r1, c0:c1] for x in inputs))
            if out is None:
                out = y.new_empty((*y.shape[:-2], h * scale, w * scale))
            out[..., k0 * scale:k1 * scale, q0 * scale:q1 * scale] = \
                y[..., (k0 - r0) * scale:(k1 - r0) * scale, (q0 - c0) * scale:(q1 - c0) * scale]
    return out
