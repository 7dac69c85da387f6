"""Seamless blending of tiles: linear ramps over the overlap that form a partition of unity.

Along each axis a tile's weight is 1 inside its core, ramps linearly from 0 to 1 over the ``overlap`` band
centred on each border it shares with a neighbour, and is 0 beyond; the neighbour's ramp is the complement,
so the weights of all tiles sum to 1 at every pixel. Blending therefore keeps any image the tiles agree on
(a constant, a linear ramp) exactly, and where they differ it fades from one to the other without a step.
"""

from __future__ import annotations

import numpy as np

from .geometry import Tile, TileLayout

__all__ = ["TileBlender", "axis_weight", "tile_weight"]


def axis_weight(coords: np.ndarray, start: int, stop: int, length: int, overlap: int) -> np.ndarray:
    """Weights ``(n,)`` float64 of one tile along one axis at pixel ``coords`` (HR pixels).

    ``[start, stop)`` is the core on ``[0, length)``; borders at 0 and ``length`` do not ramp.
    """
    x = np.asarray(coords, dtype=np.float64) + 0.5  # pixel centres
    w = np.ones_like(x)
    if overlap == 0:
        w[(x < start) | (x > stop)] = 0.0
        return w
    half = overlap / 2.0
    if start > 0:
        w = np.minimum(w, np.clip((x - (start - half)) / overlap, 0.0, 1.0))
    if stop < length:
        w = np.minimum(w, np.clip(((stop + half) - x) / overlap, 0.0, 1.0))
    return w


def tile_weight(tile: Tile, hr_shape, overlap: int) -> np.ndarray:
    """The ``(rows, cols)`` float64 blending weight of ``tile`` over its window."""
    top, left, bottom, right = tile.window
    wy = axis_weight(np.arange(top, bottom), tile.core[0], tile.core[2], hr_shape[0], overlap)
    wx = axis_weight(np.arange(left, right), tile.core[1], tile.core[3], hr_shape[1], overlap)
    return wy[:, None] * wx[None, :]


class TileBlender:
    """Accumulates tiles ``(C, rows, cols)`` into one ``(C, H, W)`` float32 frame (call :meth:`add` per tile).

    Memory: about ``4 C + 12`` bytes per HR pixel of the frame (plus ``C`` with ``unobserved`` masks).

    The weights sum to 1 everywhere (partition of unity); :meth:`result` divides by the accumulated weight
    anyway, so rounding never shows. ``unobserved`` masks are taken from the tile of largest weight.
    """

    def __init__(self, layout: TileLayout, channels: int):
        self.layout = layout
        self.sum = np.zeros((channels, *layout.hr_shape), dtype=np.float32)  # float32: the frame is the big part
        self.weight = np.zeros(layout.hr_shape, dtype=np.float32)
        self.best = np.zeros(layout.hr_shape, dtype=np.float32)
        self.unobserved: np.ndarray | None = None

    def add(self, tile: Tile, image: np.ndarray, unobserved: np.ndarray | None = None) -> None:
        """Add ``image`` ``(C, rows, cols)`` of ``tile``'s window (and its bool mask of the same shape)."""
        top, left, bottom, right = tile.window
        w = tile_weight(tile, self.layout.hr_shape, self.layout.overlap).astype(np.float32)
        self.sum[:, top:bottom, left:right] += w[None] * np.asarray(image, dtype=np.float32)
        self.weight[top:bottom, left:right] += w
        if unobserved is not None:
            if self.unobserved is None:
                self.unobserved = np.zeros(self.sum.shape, dtype=bool)
            better = w > self.best[top:bottom, left:right]
            region = self.unobserved[:, top:bottom, left:right]
            region[:, better] = np.asarray(unobserved, dtype=bool)[:, better]
        self.best[top:bottom, left:right] = np.maximum(self.best[top:bottom, left:right], w)

    def result(self) -> np.ndarray:
        """The blended ``(C, H, W)`` float32 frame (in place: call once); every pixel must have been covered."""
        if np.any(self.weight <= 0):
            raise RuntimeError(f"{int(np.sum(self.weight <= 0))} pixels are covered by no tile")
        self.sum /= self.weight[None]
        return self.sum
