"""How NLSTR (:mod:`.nlstr`) cuts its work so the working set stays within ``strip_mb``.

* **Strips** of whole reference rows bound the cores and the aggregation (eq. 22-23, 29): a strip's groups are
  consecutive, their blocks ``(n Nx, b, b, C)`` are built and shrunk together.
* **Basis tiles**, rectangles of reference blocks, bound the dictionaries (eq. 21): the Gram maps of the block
  corners the groups of a rectangle can reach (its rows and columns plus the search radius). A rectangle has
  about :func:`basis_tile_side` pixels on each axis whatever the image size, so the maps' halo is the same share of
  the work at every size (whole-width strips thin out as the width grows, and were mostly halo at 2048 px).

Block matching plans its own tiles (:mod:`.nlstr_matching`) from the strips.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .nlstr_parameters import NLSTRParameters


@dataclass
class Strip:
    """Consecutive reference rows processed together, and the block rows their matches can reach."""
    ref_rows: torch.Tensor     # indices into the reference-row list
    y_lo: int                  # first candidate block row
    y_hi: int                  # last candidate block row (inclusive)


@dataclass
class BasisTile:
    """A rectangle of reference blocks whose dictionaries are computed together, and the block corners its
    groups can reach (the Gram maps' region)."""
    groups: torch.Tensor       # global group indices, row-major
    y_lo: int                  # first candidate block row
    y_hi: int                  # last candidate block row (inclusive)
    x_lo: int                  # first candidate block column
    x_hi: int                  # last candidate block column (inclusive)


def map_planes(block: int, channels: int) -> int:
    """Planes of the Gram maps: ``b(b+1)/2`` per spatial mode (two) and ``C(C+1)/2`` for the channels."""
    return block * (block + 1) + channels * (channels + 1) // 2


def plan_strips(shape, params: NLSTRParameters, ref_y: torch.Tensor) -> list[Strip]:
    """Group reference rows into strips whose blocks fit in ``strip_mb``. The budget per row still counts a
    whole-width row of Gram maps, as when the dictionaries were computed in strips: block matching's tiles follow
    these strips and must sum their rows as before, so the plan is kept as it was."""
    c, h, w = shape
    b, s, r = params.block, params.stride, params.search_radius
    per_row = (w - b + 1) * map_planes(b, c) * 4 + 15 * c * w * 4
    rows_budget = max(1, params.strip_bytes // max(per_row, 1))
    # a strip of n reference rows spans about n*s + 2r block rows
    n_rows = max(1, int((rows_budget - 2 * r) // s))
    strips = []
    ny = ref_y.numel()
    for start in range(0, ny, n_rows):
        rows = torch.arange(start, min(ny, start + n_rows), device=ref_y.device)
        ya, yb = int(ref_y[rows[0]]), int(ref_y[rows[-1]])
        strips.append(Strip(rows, max(0, ya - r), min(h - b, yb + r)))
    return strips


def basis_tile_side(params: NLSTRParameters, channels: int, item_bytes: int) -> int:
    """Side (HR pixels, halo included) of a square region whose Gram maps and their temporaries (about 3x the
    maps) fit in ``strip_mb``."""
    return int((params.strip_bytes / (3 * map_planes(params.block, channels) * item_bytes)) ** 0.5)


def plan_basis_tiles(shape, params: NLSTRParameters, ref_y: torch.Tensor, ref_x: torch.Tensor, *,
                     item_bytes: int) -> list[BasisTile]:
    """Cut the reference grid into rectangles of about :func:`basis_tile_side` pixels on both axes (the halo of
    ``R`` block positions and ``b - 1`` pixels included), near-equal along each axis."""
    c, h, w = shape
    b, s, r = params.block, params.stride, params.search_radius
    per_tile = max(4, (basis_tile_side(params, c, item_bytes) - b - 2 * r) // s + 1)  # a floor for tiny strip_mb
    nx = ref_x.numel()

    def cuts(n: int) -> list[tuple[int, int]]:
        parts = max(1, -(-n // per_tile))
        edges = [round(i * n / parts) for i in range(parts + 1)]
        return [(edges[i], edges[i + 1]) for i in range(parts)]

    tiles = []
    cols_all = torch.arange(nx, device=ref_x.device)
    for r0, r1 in cuts(ref_y.numel()):
        for c0, c1 in cuts(nx):
            groups = (torch.arange(r0, r1, device=ref_x.device)[:, None] * nx + cols_all[None, c0:c1]).reshape(-1)
            tiles.append(BasisTile(groups, max(0, int(ref_y[r0]) - r), min(h - b, int(ref_y[r1 - 1]) + r),
                                   max(0, int(ref_x[c0]) - r), min(w - b, int(ref_x[c1 - 1]) + r)))
    return tiles


__all__ = ["BasisTile", "Strip", "basis_tile_side", "map_planes", "plan_basis_tiles", "plan_strips"]
