"""Block matching in fixed-size tiles (issue 35, item 3): the same matches, bit for bit, as the strip version
it replaced, and tiles whose size does not depend on the image (the timing is in ``capssim bench reconstruct``)."""

import pytest
import torch
import torch.nn.functional as F

from capssim.reconstruct.priors.nlstr import NLSTRParameters, NonlocalSparseTensor
from capssim.reconstruct.priors.nlstr_blocks import offset_differences, principal_channels, window_sums_at


def strip_matches(nl: NonlocalSparseTensor, z: torch.Tensor, n_similar: int):
    """The strip-by-strip block matching of capssim before issue 35, kept verbatim as the reference."""
    c, h, w = nl.shape
    b, r = nl.params.block, nl.params.search_radius
    n_off = (2 * r + 1) ** 2
    p = max(1, min(int(n_similar), n_off))
    zpad = F.pad(principal_channels(z, nl.params.match_components), (2 * r, 2 * r, 2 * r, 2 * r))
    dy_all = torch.arange(-r, r + 1)
    dys = dy_all[:, None].expand(-1, 2 * r + 1).reshape(-1)
    dxs = dy_all[None, :].expand(2 * r + 1, -1).reshape(-1)
    out_y = torch.empty(nl.n_ref, p, dtype=torch.int64)
    out_x = torch.empty_like(out_y)
    out_d = torch.empty(nl.n_ref, p, dtype=z.dtype)
    for strip in nl.strips:
        ry, rx, groups = nl._strip_refs(strip)
        ya, yb = int(nl.ref_y[strip.ref_rows[0]]), int(nl.ref_y[strip.ref_rows[-1]])
        sq = offset_differences(zpad, ya, yb + b - ya, w, r)
        box = window_sums_at(sq, b, nl.ref_x, dim=2)
        box = window_sums_at(box, b, nl.ref_y[strip.ref_rows] - ya, dim=1)
        dist = box.permute(1, 2, 0).reshape(-1, n_off) / float(b * b * c)
        cy, cx = ry[:, None] + dys[None, :], rx[:, None] + dxs[None, :]
        valid = (cy >= 0) & (cy <= h - b) & (cx >= 0) & (cx <= w - b)
        dist = torch.where(valid, dist.clamp(min=0), torch.full_like(dist, float("inf")))
        dist[:, n_off // 2] = -1.0
        best_d, best = torch.topk(dist, p, dim=1, largest=False, sorted=True)
        best_d[:, 0] = 0.0
        ok = torch.isfinite(best_d)
        out_y[groups] = torch.where(ok, ry[:, None] + dys[best], ry[:, None].expand(-1, p))
        out_x[groups] = torch.where(ok, rx[:, None] + dxs[best], rx[:, None].expand(-1, p))
        out_d[groups] = best_d
    return out_y, out_x, out_d


def _scene(shape, seed):
    gen = torch.Generator().manual_seed(seed)
    c, h, w = shape
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    base = torch.stack([torch.sin(6 * xx * (1 + k / c)) * torch.cos(4 * yy) for k in range(c)])
    return base + 0.05 * torch.rand(shape, generator=gen)


# (shape, strip_mb, params, dtype): one column of tiles; strips of several reference rows cut into column tiles
# of a few lane widths; strips of one reference row (summed on whole rows); off-grid last rows and columns
F32, F64 = torch.float32, torch.float64
CASES = [
    ((12, 72, 150), 64.0, {}, F32),
    ((12, 70, 57), 64.0, {"search_radius": 4}, F64),
    ((12, 64, 200), 8.0, {}, F32),
    ((12, 62, 238), 8.0, {"stride": 2}, F32),
    ((12, 41, 63), 2.0**-20, {"search_radius": 2}, F32),
    ((12, 45, 66), 0.02, {"stride": 8, "search_radius": 3}, F32),
    ((12, 40, 90), 0.05, {"match_components": 3, "search_radius": 3}, F32),
    ((4, 8, 40), 64.0, {"search_radius": 2}, F32),  # a single reference row
]


@pytest.mark.parametrize("shape, strip_mb, params, dtype", CASES)
def test_tiled_matching_equals_strip_matching(shape, strip_mb, params, dtype):
    z = _scene(shape, seed=shape[1]).to(dtype)
    nl = NonlocalSparseTensor(shape, NLSTRParameters(strip_mb=strip_mb, **params), dtype=dtype)
    got = nl.match(z, 16)
    want = strip_matches(nl, z, 16)
    assert torch.equal(got.pos_y, want[0]) and torch.equal(got.pos_x, want[1])
    assert torch.equal(got.distances, want[2])  # bit for bit: the weights and so caps's output are unchanged


def test_cases_cover_column_tiles_of_multi_row_strips():
    nl = NonlocalSparseTensor((12, 64, 200), NLSTRParameters(strip_mb=8.0))
    assert len({t.col0 for t in nl.match_tiles}) >= 2
    assert any(b - a > 1 and chunked for t in nl.match_tiles for a, b, chunked in t.runs)


def test_small_budgets_give_several_tiles_in_both_directions():
    nl = NonlocalSparseTensor((12, 41, 63), NLSTRParameters(strip_mb=2.0**-20, search_radius=2))
    assert len({t.col0 for t in nl.match_tiles}) > 3 and len({t.row0 for t in nl.match_tiles}) > 3
    covered = torch.zeros(nl.ref_y.numel(), nl.ref_x.numel(), dtype=torch.int64)
    for t in nl.match_tiles:
        covered[t.row0:t.row1, t.col0:t.col1] += 1
    assert bool((covered == 1).all())  # every reference block is matched exactly once


@pytest.mark.parametrize("width", [512, 1024, 2048, 2560])
def test_tile_size_does_not_depend_on_the_width(width):
    # the strips of the Gram maps get thinner as the width grows (strip_mb / width); the matching tiles must not
    nl = NonlocalSparseTensor((12, 64, width), NLSTRParameters())
    widths = {int(nl.ref_x[t.col1 - 1] - nl.ref_x[t.col0]) + nl.params.block for t in nl.match_tiles}
    assert max(widths) < 2 * min(widths) and 150 <= min(widths) and max(widths) <= 450
