"""Block matching of NLSTR (paper section 3.3) in tiles of fixed size, so its cost per pixel does not
depend on the image size (issue 35, item 3).

The distances of every reference block to the ``(2 R + 1)^2`` candidates of its search window are
the channel-summed squared differences per offset (:func:`.nlstr_blocks.offset_differences`),
box-summed along the width and then along the height (:func:`.nlstr_blocks.window_sums_at`),
then ``topk``. Each pass over a region recomputes a margin of ``2 R + b - s`` rows and columns, so
the work per pixel is that of the region's size: regions must not get thinner as the image grows.

Earlier versions matched the whole width in the strips of :func:`.nlstr_plan.plan_strips`,
whose height is ``strip_mb`` over the width: at 2048 px wide a strip held 2 reference rows, the margin
was 2.7x the useful work, and block matching grew from 10 % of the ``caps`` time at 512² to 30 % at
2048². Here a :class:`MatchTile` is about ``sqrt(strip_mb / MATCH_BYTES_PER_PIXEL)`` pixels on a
side whatever the image: a fixed working set, a fixed share of margin, time linear in the pixels.

The distances stay bit-identical to the strip version: the differences and the sums along the width
are the same numbers wherever a region starts; the sums along the height are rounded in float32
according to how :func:`.nlstr_blocks.window_sums_at` splits a strip's starts (chunks of ``s``, one
chunk of ``b`` for a strip of one reference row, or all windows when the strip touches an off-grid
last row), so each tile sums the rows of each strip of the plan as that strip did; the width keeps
the choice of the whole row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .nlstr_blocks import chunked_windows, offset_differences, principal_channels, window_sums_at

__all__ = ["MATCH_BYTES_PER_PIXEL", "MatchTile", "match_blocks", "plan_match_tiles"]

#: bytes per pixel of a matching tile per candidate offset: the offset maps (float32) and their box sums,
#: the distance and candidate tables; times ``(2 R + 1)^2`` and the item size over 4
MATCH_BYTES_PER_PIXEL = 6.0


@dataclass(frozen=True)
class MatchTile:
    """Reference rows ``[row0, row1)`` x columns ``[col0, col1)`` (indices into the reference grid) matched in
    one pass; ``runs`` are ``(first, stop, chunked)`` runs of the rows (tile-local) summed in one call each."""

    row0: int
    row1: int
    col0: int
    col1: int
    runs: tuple[tuple[int, int, bool], ...]


def _row_runs(strips, ref_y: torch.Tensor, block: int) -> list[tuple[int, int, bool, bool]]:
    """``(first, stop, chunked, mergeable)`` per strip: its reference rows and how it sums its rows."""
    runs = []
    for strip in strips:
        first, stop = int(strip.ref_rows[0]), int(strip.ref_rows[-1]) + 1
        rel = ref_y[first:stop] - ref_y[first]
        chunked = chunked_windows(block, rel, int(rel[-1]) + block)
        runs.append((first, stop, chunked, chunked and stop - first > 1))  # chunks of s: the same sums in any run
    return runs


def plan_match_tiles(strips, ref_y: torch.Tensor, ref_x: torch.Tensor, *, block: int, stride: int,
                     search_radius: int, item_bytes: int, budget_bytes: int) -> list[MatchTile]:
    """Tiles of about ``side x side`` HR pixels, ``side = sqrt(budget / (MATCH_BYTES_PER_PIXEL n_off item/4))``:
    bands of whole ``strips`` (their rows summed as they sum them) cut into columns of at least
    ``max(2, side / stride)`` reference columns (the whole row when narrower than two such columns)."""
    n_off = (2 * search_radius + 1) ** 2
    side = math.sqrt(budget_bytes / (MATCH_BYTES_PER_PIXEL * n_off * item_bytes / 4))
    per_tile = max(2, int(side // stride))
    nx = int(ref_x.numel())
    n_cols = max(1, nx // per_tile)
    cols = [round(i * nx / n_cols) for i in range(n_cols + 1)]
    bands, band = [], []
    for run in _row_runs(strips, ref_y, block):
        if band and int(ref_y[run[1] - 1] - ref_y[band[0][0]]) + block > side:
            bands.append(band)
            band = []
        band.append(run)
    bands.append(band)
    tiles = []
    for band in bands:
        row0, merged = band[0][0], []
        for first, stop, chunked, mergeable in band:
            if merged and mergeable and merged[-1][3]:
                merged[-1] = (merged[-1][0], stop - row0, True, True)
            else:
                merged.append((first - row0, stop - row0, chunked, mergeable))
        runs = tuple((a, b, c) for a, b, c, _ in merged)
        tiles.extend(MatchTile(row0, band[-1][1], c0, c1, runs) for c0, c1 in zip(cols[:-1], cols[1:]))
    return tiles


def _x_sums(zpad: torch.Tensor, tile: MatchTile, ref_y: torch.Tensor, ref_x: torch.Tensor, *, block: int,
            radius: int, x_chunked: bool) -> torch.Tensor:
    """Squared differences of the tile's rows summed over the width of its reference blocks: ``(n_off, rows, cols)``,
    ``rows`` the image rows of the tile's reference blocks, ``cols`` its reference columns."""
    b, r = block, radius
    ya, x0 = int(ref_y[tile.row0]), int(ref_x[tile.col0])
    height = int(ref_y[tile.row1 - 1]) + b - ya
    width = int(ref_x[tile.col1 - 1]) + b - x0
    sq = offset_differences(zpad[:, :, x0:x0 + width + 4 * r], ya, height, width, r)  # (n_off, height, width)
    return window_sums_at(sq, b, ref_x[tile.col0:tile.col1] - x0, dim=2, chunked=x_chunked)


def _y_sums(box: torch.Tensor, row0: int, run: tuple[int, int, bool], ref_y: torch.Tensor, block: int) -> torch.Tensor:
    """``box`` ``(n_off, rows, cols)`` of rows from ``ref_y[row0]`` summed over the height of the blocks of a run of
    reference rows, as its strip summed them: ``(n_off, run rows, cols)``."""
    first, stop, chunked = run
    ya = int(ref_y[row0])
    y0 = int(ref_y[row0 + first]) - ya
    rel = ref_y[row0 + first:row0 + stop] - ya - y0
    return window_sums_at(box[:, y0:y0 + int(rel[-1]) + block].contiguous(), block, rel, dim=1, chunked=chunked)


def _single_row(run: tuple[int, int, bool]) -> bool:
    """A strip of one reference row summed as one chunk of ``b`` rows: torch rounds that reduction differently
    across the lanes of a row, so it runs on whole rows as before (the others give the same sums in any tile)."""
    return run[2] and run[1] - run[0] == 1


class _Results:
    """The ``(K, P)`` outputs of :func:`match_blocks`, filled a block of reference rows x columns at a time."""

    def __init__(self, z: torch.Tensor, n_similar: int, ref_y: torch.Tensor, ref_x: torch.Tensor, block: int,
                 radius: int):
        self.c, self.h, self.w = z.shape
        self.b, self.ref_y, self.ref_x = block, ref_y, ref_x
        self.n_off = (2 * radius + 1) ** 2
        self.p = max(1, min(int(n_similar), self.n_off))
        offsets = torch.arange(-radius, radius + 1, device=z.device)
        self.dys = offsets[:, None].expand(-1, 2 * radius + 1).reshape(-1)
        self.dxs = offsets[None, :].expand(2 * radius + 1, -1).reshape(-1)
        n_ref = int(ref_y.numel() * ref_x.numel())
        self.pos_y = torch.empty(n_ref, self.p, dtype=torch.int64, device=z.device)
        self.pos_x = torch.empty_like(self.pos_y)
        self.dist = torch.empty(n_ref, self.p, dtype=z.dtype, device=z.device)

    def add(self, box: torch.Tensor, rows: tuple[int, int], cols: tuple[int, int]) -> None:
        """The best candidates of reference rows ``[rows)`` x columns ``[cols)`` from their box sums ``box``
        ``(n_off, rows, cols)``."""
        (r0, r1), (c0, c1), b, p, n_off = rows, cols, self.b, self.p, self.n_off
        ry = self.ref_y[r0:r1][:, None].expand(-1, c1 - c0).reshape(-1)
        rx = self.ref_x[c0:c1][None, :].expand(r1 - r0, -1).reshape(-1)
        groups = (torch.arange(r0, r1, device=box.device)[:, None] * self.ref_x.numel()
                  + torch.arange(c0, c1, device=box.device)[None, :]).reshape(-1)
        dist = box.permute(1, 2, 0).reshape(-1, n_off) / float(b * b * self.c)
        cy, cx = ry[:, None] + self.dys[None, :], rx[:, None] + self.dxs[None, :]
        valid = (cy >= 0) & (cy <= self.h - b) & (cx >= 0) & (cx <= self.w - b)
        dist = torch.where(valid, dist.clamp(min=0), torch.full_like(dist, float("inf")))
        dist[:, n_off // 2] = -1.0  # the reference itself always comes first
        best_d, best = torch.topk(dist, p, dim=1, largest=False, sorted=True)
        best_d[:, 0] = 0.0
        ok = torch.isfinite(best_d)
        self.pos_y[groups] = torch.where(ok, ry[:, None] + self.dys[best], ry[:, None].expand(-1, p))
        self.pos_x[groups] = torch.where(ok, rx[:, None] + self.dxs[best], rx[:, None].expand(-1, p))
        self.dist[groups] = best_d


def match_blocks(z: torch.Tensor, n_similar: int, tiles: list[MatchTile], ref_y: torch.Tensor,
                 ref_x: torch.Tensor, *, block: int, radius: int, components: int = 0
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``n_similar`` most similar blocks of every reference block of ``z`` ``(C, H, W)`` (reference first):
    top-left rows and columns ``(K, P)`` (int64) and mean squared distances ``(K, P)``, ``K`` the reference grid
    ``ref_y x ref_x`` row-major; candidates outside the image are replaced by the reference (distance ``inf``).

    ``tiles`` (:func:`plan_match_tiles`) come band by band; a band with strips of one reference row keeps their
    rows' width sums for the whole width ``(n_off, rows, Nx)`` until its last tile."""
    b, r = block, radius
    res = _Results(z, n_similar, ref_y, ref_x, block, radius)
    zpad = F.pad(principal_channels(z, components), (2 * r, 2 * r, 2 * r, 2 * r))
    x_chunked = chunked_windows(b, ref_x, z.shape[2])
    nx, wide = int(ref_x.numel()), None
    for i, tile in enumerate(tiles):
        box = _x_sums(zpad, tile, ref_y, ref_x, block=b, radius=r, x_chunked=x_chunked)
        singles = [run for run in tile.runs if _single_row(run)]
        if singles and wide is None:
            wide = box.new_empty(box.shape[0], box.shape[1], nx)
        if singles:
            wide[:, :, tile.col0:tile.col1] = box
        for run in tile.runs:
            if not _single_row(run):
                res.add(_y_sums(box, tile.row0, run, ref_y, b), (tile.row0 + run[0], tile.row0 + run[1]),
                        (tile.col0, tile.col1))
        del box
        if wide is not None and (i + 1 == len(tiles) or tiles[i + 1].row0 != tile.row0):
            for run in singles:
                res.add(_y_sums(wide, tile.row0, run, ref_y, b), (tile.row0 + run[0], tile.row0 + run[1]), (0, nx))
            wide = None
    return res.pos_y, res.pos_x, res.dist
