"""Tile layout on the HR grid: cores that partition the frame, margins around them, the overlap to blend.

All lengths are HR pixels (the ``(2H, 2W)`` reference grid, docs/architecture.md, "The camera, its grids and its channels"). Every core and every
window (core + margin) starts on a multiple of :data:`TILE_ALIGN` = 4 HR pixels: one RGGB cell of every
aperture (2 raw pixels) and the NLSTR reference stride, so a tile's sub-images keep their Bayer sites and
its block grid is the whole frame's. The margin holds what a pixel of the core depends on: the NLSTR
search window and block, the CAGF window, the PSF and the warp's reach (:func:`default_margin`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from capssim.errors import InputError

from ..model.window_capture import WINDOW_ALIGN

__all__ = ["TILE_ALIGN", "MIN_TILE", "Tile", "TileLayout", "default_margin", "plan_tiles", "split_axis"]

#: alignment of every tile edge, HR pixels (one Bayer cell of every aperture; the NLSTR stride)
TILE_ALIGN = WINDOW_ALIGN
#: the smallest tile core side, HR pixels (below it the margins cost more than the core)
MIN_TILE = 64


def _round_up(value: float, step: int = TILE_ALIGN) -> int:
    return int(math.ceil(value / step) * step)


def default_margin(*, block: int = 8, search_radius: int = 7, cagf_radius: int = 4, psf_radius: int = 4,
                   warp_reach: int = 8) -> int:
    """The margin around a tile's core, HR pixels, rounded up to :data:`TILE_ALIGN`.

    Parameters
    ----------
    block, search_radius : int
        NLSTR block side and block-matching search radius (HR pixels).
    cagf_radius : int
        CAGF window radius in sub-image pixels (4 HR pixels each).
    psf_radius : int
        PSF kernel radius, HR pixels.
    warp_reach : int
        How far the warps of one tile's apertures may stray from the tile's shared offset, HR pixels.

    Returns
    -------
    int
        ``block + search_radius + 4 cagf_radius + psf_radius + warp_reach``, rounded up to a multiple of 4.
    """
    return _round_up(block + search_radius + 4 * cagf_radius + psf_radius + warp_reach)


def split_axis(length: int, tile: int) -> list[tuple[int, int]]:
    """Cut ``[0, length)`` into ``ceil(length / tile)`` near-equal cores ``[start, stop)`` aligned to 4.

    Parameters
    ----------
    length : int
        The frame side, HR pixels (a multiple of 4).
    tile : int
        The largest core side, HR pixels (>= 4).

    Returns
    -------
    list of (int, int)
        Consecutive cores covering ``[0, length)``; all but the last start and end on multiples of 4.
    """
    if tile < TILE_ALIGN:
        raise InputError("tile", tile, f"at least {TILE_ALIGN} HR pixels")
    cells = -(-length // TILE_ALIGN)
    count = max(1, -(-length // tile))
    bounds = [min(length, TILE_ALIGN * round(k * cells / count)) for k in range(count + 1)]
    bounds[-1] = length
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


@dataclass(frozen=True)
class Tile:
    """One tile: its core (what it contributes) and its window (what it reconstructs), HR pixels.

    ``core`` and ``window`` are ``(top, left, bottom, right)``, bottom/right exclusive; the window is the core
    grown by the margin and clipped to the frame. ``index`` is ``(row, col)`` in the layout.
    """

    index: tuple[int, int]
    core: tuple[int, int, int, int]
    window: tuple[int, int, int, int]

    @property
    def name(self) -> str:
        return f"tile_{self.index[0]:03d}_{self.index[1]:03d}"

    @property
    def shape(self) -> tuple[int, int]:
        """The window's ``(rows, cols)``."""
        return self.window[2] - self.window[0], self.window[3] - self.window[1]


@dataclass(frozen=True)
class TileLayout:
    """The tiles of one ``hr_shape`` frame, row by row, and their margin and blending overlap (HR pixels)."""

    hr_shape: tuple[int, int]
    tiles: tuple[Tile, ...]
    margin: int
    overlap: int

    @property
    def grid(self) -> tuple[int, int]:
        """``(rows, cols)`` of tiles."""
        return max(t.index[0] for t in self.tiles) + 1, max(t.index[1] for t in self.tiles) + 1

    @property
    def largest_window(self) -> tuple[int, int]:
        return max(t.shape[0] for t in self.tiles), max(t.shape[1] for t in self.tiles)

    def to_dict(self) -> dict:
        return {"hr_shape": list(self.hr_shape), "grid": list(self.grid), "margin": self.margin,
                "overlap": self.overlap, "tiles": [{"name": t.name, "core": list(t.core), "window": list(t.window)}
                                                   for t in self.tiles]}


def plan_tiles(hr_shape, tile: int, *, margin: int, overlap: int | None = None) -> TileLayout:
    """The tiles of an ``hr_shape`` frame with cores of at most ``tile`` x ``tile`` HR pixels.

    Parameters
    ----------
    hr_shape : tuple of int
        ``(2H, 2W)``, multiples of 4.
    tile : int
        The largest core side, HR pixels (``>= MIN_TILE``, or the frame's larger side for one tile).
    margin : int
        Pixels reconstructed around each core and dropped (multiple of 4, ``>= 0``).
    overlap : int, optional
        Width of the band where neighbours blend, centred on their common border (even, ``<= 2 margin``;
        default ``margin``).

    Returns
    -------
    TileLayout
    """
    hh, ww = (int(v) for v in hr_shape)
    if hh % TILE_ALIGN or ww % TILE_ALIGN:
        raise InputError("hr_shape", (hh, ww), f"multiples of {TILE_ALIGN} HR pixels")
    if tile < min(MIN_TILE, max(hh, ww)):
        raise InputError("--tile", tile, f"a tile side of at least {MIN_TILE} HR pixels",
                         f"Use --tile {MIN_TILE} or more.")
    if margin < 0 or margin % TILE_ALIGN:
        raise InputError("margin", margin, f"a multiple of {TILE_ALIGN} HR pixels, >= 0")
    overlap = margin if overlap is None else int(overlap)
    if overlap < 0 or overlap % 2 or overlap > 2 * margin:
        raise InputError("overlap", overlap, f"an even number of HR pixels in [0, 2 margin = {2 * margin}]")
    rows, cols = split_axis(hh, tile), split_axis(ww, tile)
    blended = [b - a for axis in (rows, cols) if len(axis) > 1 for a, b in axis]  # one tile wide: nothing to blend
    if overlap and blended and min(blended) < overlap:
        raise InputError("--tile", tile, f"tiles wider than the blending overlap ({overlap} HR px)",
                         "Use a larger --tile.")
    tiles = []
    for i, (top, bottom) in enumerate(rows):
        for j, (left, right) in enumerate(cols):
            window = (max(0, top - margin), max(0, left - margin), min(hh, bottom + margin), min(ww, right + margin))
            tiles.append(Tile((i, j), (top, left, bottom, right), window))
    return TileLayout((hh, ww), tuple(tiles), margin, overlap)
