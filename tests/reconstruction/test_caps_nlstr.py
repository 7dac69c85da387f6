"""Nonlocal sparse tensor regularization (paper 3.3, section 4 steps 1-2, eq. 29)."""

import numpy as np
import pytest
import torch

from capssim.errors import InputError
from capssim.reconstruct.filters import sliding_window_sum
from capssim.reconstruct.priors.nlstr import (
    NLSTRParameters,
    NonlocalSparseTensor,
    reference_positions,
    shrink_core,
)
from capssim.reconstruct.priors.nlstr_blocks import (
    gram_maps,
    mode_products,
    principal_channels,
    unpack_grams,
    weighted_block_sums,
    window_sums_at,
)
from capssim.reconstruct.priors.nlstr_prior import MatchSchedule, NLSTRPrior
from capssim.reconstruct.solvers.interfaces import no_stage


def piecewise_scene(c=12, h=48, w=56, seed=0):
    """Piecewise-smooth multichannel image: smooth ramps plus rectangles, channel gains differ."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    base = 0.3 + 0.2 * xx + 0.1 * yy
    base = base + 0.25 * ((yy > 0.3) & (xx > 0.4)) - 0.15 * ((yy < 0.2) & (xx < 0.5))
    gains = 0.6 + 0.4 * rng.random(c)
    return torch.as_tensor(np.stack([g * base for g in gains]), dtype=torch.float64)


def test_reference_positions_cover_any_size():
    assert reference_positions(16, 8, 4).tolist() == [0, 4, 8]
    assert reference_positions(18, 8, 4).tolist() == [0, 4, 8, 10]
    assert reference_positions(8, 8, 4).tolist() == [0]
    with pytest.raises(InputError):
        reference_positions(6, 8, 4)


@pytest.mark.parametrize("size", [1, 2, 3, 5, 8])
def test_box_sum_exact(size):
    x = torch.rand(7, 19, dtype=torch.float64)
    for dim in (0, 1):
        if x.shape[dim] >= size:
            assert torch.allclose(sliding_window_sum(x, size, dim=dim), x.unfold(dim, size, 1).sum(-1))


def test_block_matching_equals_brute_force():
    torch.manual_seed(1)
    z = torch.rand(3, 20, 27, dtype=torch.float64)
    prm = NLSTRParameters(block=4, stride=3, search_radius=3)
    nl = NonlocalSparseTensor(tuple(z.shape), prm, dtype=torch.float64)
    m = nl.match(z, 10)
    nx = nl.ref_x.numel()
    for yi, ry in enumerate(nl.ref_y.tolist()):
        for xi, rx in enumerate(nl.ref_x.tolist()):
            k = yi * nx + xi
            ref = z[:, ry:ry + 4, rx:rx + 4]
            dists = sorted(float(((ref - z[:, y:y + 4, x:x + 4]) ** 2).mean())
                           for y in range(max(0, ry - 3), min(16, ry + 3) + 1)
                           for x in range(max(0, rx - 3), min(23, rx + 3) + 1))[:10]
            assert np.allclose(m.distances[k].tolist(), dists, atol=1e-12)
            assert (m.pos_y[k, 0], m.pos_x[k, 0]) == (ry, rx)  # the reference itself first
    assert torch.allclose(m.weights.sum(1), torch.ones(m.weights.shape[0], dtype=torch.float64))


def test_group_gram_from_maps_equals_direct():
    torch.manual_seed(2)
    c, h, w, b = 4, 20, 22, 4
    z = torch.rand(c, h, w, dtype=torch.float64)
    nl = NonlocalSparseTensor((c, h, w), NLSTRParameters(block=b, stride=2, search_radius=2), dtype=torch.float64)
    maps = gram_maps(z, b, nl._tri_c)  # the whole image is one region
    nx = w - b + 1
    rng = np.random.default_rng(0)
    pos = [(int(rng.integers(0, h - b + 1)), int(rng.integers(0, w - b + 1))) for _ in range(5)]
    sums = sum(maps[y * nx + x] for y, x in pos)[None]
    gram_hw, gram_c = unpack_grams(sums, b, nl._tri_c, c)
    blocks = torch.stack([z[:, y:y + b, x:x + b].permute(1, 2, 0) for y, x in pos])  # (P, b, b, c)
    direct_h = sum(blk.reshape(b, -1) @ blk.reshape(b, -1).T for blk in blocks)
    direct_w = sum(blk.transpose(0, 1).reshape(b, -1) @ blk.transpose(0, 1).reshape(b, -1).T for blk in blocks)
    direct_c = sum(blk.reshape(-1, c).T @ blk.reshape(-1, c) for blk in blocks)
    assert torch.allclose(gram_hw[0], direct_h) and torch.allclose(gram_hw[1], direct_w)
    assert torch.allclose(gram_c[0], direct_c)


def test_mode_products_are_orthonormal_transforms():
    torch.manual_seed(3)
    k, b, c = 5, 8, 12
    t = torch.rand(k, b, b, c, dtype=torch.float64)
    ph = torch.linalg.qr(torch.randn(k, b, b, dtype=torch.float64))[0]
    pw = torch.linalg.qr(torch.randn(k, b, b, dtype=torch.float64))[0]
    pc = torch.linalg.qr(torch.randn(k, c, c, dtype=torch.float64))[0]
    core = mode_products(t, ph, pw, pc, transpose=True)
    ref = torch.einsum("kia,kjb,kcd,kijc->kabd", ph, pw, pc, t)  # C = R x1 Ph^T x2 Pw^T x3 Pc^T
    assert torch.allclose(core, ref)
    back = mode_products(core, ph, pw, pc, transpose=False)
    assert torch.allclose(back, t)
    assert torch.allclose(core.square().sum(), t.square().sum())


def test_shrink_core_eq23():
    alpha = torch.tensor([[1.0, 0.01, -0.5, 0.0]])
    beta = torch.tensor([[1.0, 0.0, -0.2, 0.0]])
    core, parts = shrink_core(alpha, beta, 0.002, 0.02)
    # element-wise: t = c2/(a-b)^2, lam = c1/|a|, C = soft((2 t b + a)/(1 + 2t), lam/(1 + 2t))
    t = 0.02 / ((alpha - beta) ** 2 + 1e-8)
    lam = 0.002 / (alpha.abs() + 1e-8)
    v = (2 * t * beta + alpha) / (1 + 2 * t)
    expected = torch.sign(v) * torch.clamp(v.abs() - lam / (1 + 2 * t), min=0)
    assert torch.allclose(core, expected)
    assert core[0, 1] == 0 and core[0, 3] == 0          # small / zero coefficients are removed
    assert abs(core[0, 0] - 1.0) < 0.01                 # large consistent coefficient kept
    assert all(torch.isfinite(v) for v in parts.values())
    core_b, _ = shrink_core(alpha, beta, 0.002, 0.02, adaptive="block")
    assert torch.isfinite(core_b).all()


def test_nlstr_reduces_noise_on_piecewise_smooth_image():
    clean = piecewise_scene().float()
    gen = torch.Generator().manual_seed(0)
    noisy = clean + 0.03 * torch.randn(clean.shape, generator=gen)
    nl = NonlocalSparseTensor(tuple(clean.shape), NLSTRParameters())
    x, stats = nl.estimate(noisy, nl.match(noisy, 40))
    mse_in = float((noisy - clean).square().mean())
    mse_out = float((x - clean).square().mean())
    assert mse_out < 0.25 * mse_in, (mse_in, mse_out)
    assert 0 < stats["zero_fraction"] < 1


@pytest.mark.parametrize("shape,prm", [((12, 36, 44), NLSTRParameters()),
                                       ((12, 108, 116), NLSTRParameters()),
                                       ((4, 21, 30), NLSTRParameters(stride=3)),
                                       ((12, 8, 8), NLSTRParameters())])
def test_sizes_not_multiple_of_block(shape, prm):
    torch.manual_seed(4)
    z = torch.rand(shape)
    nl = NonlocalSparseTensor(shape, prm)
    x, _ = nl.estimate(z, nl.match(z, 40))
    assert x.shape == shape and torch.isfinite(x).all()
    assert float((x - z).abs().mean()) < 0.2


def test_strips_give_the_same_result():
    # float64: in float32 the vectorized sums differ in the last bit between regions
    gen = torch.Generator().manual_seed(1)
    z = piecewise_scene(h=64, w=40) + 0.02 * torch.randn(12, 64, 40, generator=gen, dtype=torch.float64)
    one = NonlocalSparseTensor(tuple(z.shape), NLSTRParameters(strip_mb=1024.0), dtype=torch.float64)
    many = NonlocalSparseTensor(tuple(z.shape), NLSTRParameters(strip_mb=2.0**-20), dtype=torch.float64)  # 1 byte
    assert len(one.strips) == 1 and len(many.strips) > 3
    m1, m2 = one.match(z, 20), many.match(z, 20)
    assert torch.equal(m1.pos_y, m2.pos_y) and torch.equal(m1.pos_x, m2.pos_x)
    x1, _ = one.estimate(z, m1)
    x2, _ = many.estimate(z, m2)
    assert torch.allclose(x1, x2, atol=1e-10)


@pytest.mark.parametrize("value", [0.0, 1e-6, 0.5])
def test_constant_images_stay_constant(value):
    z = torch.full((12, 24, 24), value)
    nl = NonlocalSparseTensor(tuple(z.shape), NLSTRParameters())
    x, _ = nl.estimate(z, nl.match(z, 40))
    assert torch.isfinite(x).all()
    assert torch.allclose(x, z, atol=1e-6 + 1e-4 * value)


def test_parameter_validation():
    with pytest.raises(InputError):
        NonlocalSparseTensor((12, 16, 16), NLSTRParameters(block=8, stride=9))
    with pytest.raises(InputError):
        NonlocalSparseTensor((12, 6, 16), NLSTRParameters())
    with pytest.raises(InputError):
        NonlocalSparseTensor((12, 16, 16), NLSTRParameters(adaptive="bogus"))
    for bad in (MatchSchedule(rematch_min_gap=5, rematch_max_gap=2), MatchSchedule(rematch_change=0),
                MatchSchedule(n_similar=0), MatchSchedule(n_similar_step=-1)):
        with pytest.raises(InputError):
            bad.validate()


def test_the_prior_owns_its_matching_schedule():
    """Blocks are matched at the first iteration, then when the change predicts a relative change of
    ``rematch_change`` (within the gaps), with ``n_similar_step`` fewer blocks each time; ``begin``
    starts over."""
    z = piecewise_scene(c=4, h=24, w=24)
    nl = NonlocalSparseTensor(tuple(z.shape), NLSTRParameters(), dtype=torch.float64)
    schedule = MatchSchedule(n_similar=12, n_similar_step=5, n_similar_min=4, rematch_change=0.02,
                             rematch_min_gap=2, rematch_max_gap=4)
    prior = NLSTRPrior(nl, schedule)
    changes = [0.02, 0.5, 0.001, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]
    rows = []
    for i, change in enumerate(changes):
        x, fields = prior.estimate(z, mu=0.5, iteration=i, stage=no_stage)
        rows.append((fields["n_similar"], fields["rematched"], prior.after_step(iteration=i, change=change)))
    # iteration 0 matches 12 (gap 1 -> 2), 2 matches 7 (gap 20 -> 4), 6 matches 4 (gap 1 -> 2), 8 matches 4
    assert [r[1] for r in rows] == [True, False, True, False, False, False, True, False, True]
    assert [r[0] for r in rows] == [12, 12, 7, 7, 7, 7, 4, 4, 4]
    assert [r[2] for r in rows if r[2]] == [{"next_match": 3}, {"next_match": 7}, {"next_match": 9},
                                            {"next_match": 11}]
    assert schedule.next_gap(0.0) == 4 and schedule.next_gap(1.0) == 2
    prior.begin()
    _, fields = prior.estimate(z, mu=1.0, iteration=0, stage=no_stage)
    assert fields["rematched"] and fields["n_similar"] == 12
    assert torch.equal(x, nl.estimate(z, nl.match(z, 4))[0])



def test_sliding_window_sum_never_aliases_and_checks_size():
    """A window of 1 returns a copy (callers may write into it); a window longer than the axis is a
    clear error."""
    x = torch.rand(5, 11, 7, dtype=torch.float64)
    out = sliding_window_sum(x, 1, dim=1)
    out.zero_()
    assert x.abs().sum() > 0
    with pytest.raises(InputError, match="size"):
        sliding_window_sum(x, 8, dim=-1)


def test_weighted_block_sums_equal_the_gathered_sum():
    torch.manual_seed(6)
    c, h, w, b = 3, 17, 19, 4
    z = torch.rand(c, h, w, dtype=torch.float64)
    nl = NonlocalSparseTensor((c, h, w), NLSTRParameters(block=b, stride=3, search_radius=2), dtype=torch.float64)
    m = nl.match(z, 6)
    u = weighted_block_sums(z.permute(1, 2, 0).reshape(h * w, c).contiguous(), nl._group_matrix(m), b, w)
    for k in (0, 7, nl.n_ref - 1):
        expected = sum(float(m.weights[k, p]) * z[:, m.pos_y[k, p]:m.pos_y[k, p] + b, m.pos_x[k, p]:m.pos_x[k, p] + b]
                       for p in range(6))
        assert torch.allclose(u[k], expected.permute(1, 2, 0))


def test_dictionary_gap_reuses_dictionaries_between_updates():
    clean = piecewise_scene(h=24, w=28).float()
    nl = NonlocalSparseTensor(tuple(clean.shape), NLSTRParameters())
    m = nl.match(clean, 10)
    fresh, _ = nl.estimate(clean, m)
    reused, _ = nl.estimate(clean, m, reuse_bases=True)
    assert torch.allclose(fresh, reused)                      # same z, same groups: the same dictionaries
    with pytest.raises(InputError):
        nl.estimate(clean, nl.match(clean, 8), reuse_bases=True)  # new groups: nothing to reuse
    schedule = MatchSchedule(n_similar=10, rematch_min_gap=10, rematch_max_gap=10, dictionary_gap=3)
    prior = NLSTRPrior(nl, schedule)
    flags = []
    for i in range(7):
        _, fields = prior.estimate(clean, mu=0.5, iteration=i, stage=no_stage)
        prior.after_step(iteration=i, change=0.01)
        flags.append(fields["new_dictionaries"])
    assert flags == [True, False, False, True, False, False, True]
    with pytest.raises(InputError):
        MatchSchedule(dictionary_gap=0).validate()


@pytest.mark.parametrize("size", [8, 6, 5])
def test_window_sums_at_any_reference_grid_equal_the_sliding_sums(size):
    x = torch.rand(6, 40, 3, dtype=torch.float64)
    grids = ([0, 4, 8, 12], [0, 4, 8, 10], [0, 3, 6, 9, 12], [0, 6, 12, 18, 24, 30, 32], [0, 5, 10, 15, 20],
             [0, 4, 5, 12], [0], [3, 7], [0, 7, 14, 21, 28, 32])  # strides sharing a divisor with size or not,
    for grid in grids:                                              # a last start flush with the side, none
        starts = torch.tensor(grid)
        expected = sliding_window_sum(x, size, dim=1).index_select(1, starts)
        assert torch.allclose(window_sums_at(x, size, starts, dim=1), expected), grid
        assert torch.allclose(window_sums_at(x.transpose(1, 2), size, starts, dim=2), expected.transpose(1, 2))


def test_principal_channels_keep_block_distances_in_their_subspace_and_all_channels_when_asked():
    gen = torch.Generator().manual_seed(4)
    basis = torch.linalg.qr(torch.randn(12, 12, generator=gen, dtype=torch.float64))[0]
    energy = torch.tensor([4.0, 2.0, 1.0] + [1e-4] * 9, dtype=torch.float64)   # three strong components
    z = (basis * energy) @ torch.randn(12, 30 * 20, generator=gen, dtype=torch.float64)
    z = (z + 0.5).reshape(12, 30, 20)
    assert principal_channels(z, 0) is z and principal_channels(z, 12) is z
    p = principal_channels(z, 3)
    assert p.shape == (3, 30, 20)
    full = (z[:, :8, :8] - z[:, 10:18, 5:13]).square().sum()
    projected = (p[:, :8, :8] - p[:, 10:18, 5:13]).square().sum()
    assert projected <= full and projected > 0.999 * full  # the three components hold the differences
    with pytest.raises(InputError):
        NLSTRParameters(match_components=-1).validate()


def test_matching_on_principal_channels_finds_the_same_blocks_of_a_low_rank_image():
    gen = torch.Generator().manual_seed(5)
    mix = torch.rand(12, 2, generator=gen)
    z = torch.einsum("ck,khw->chw", mix, torch.rand(2, 40, 48, generator=gen))  # rank 2 across channels
    all_channels = NonlocalSparseTensor((12, 40, 48), NLSTRParameters()).match(z, 10)
    two = NonlocalSparseTensor((12, 40, 48), NLSTRParameters(match_components=2)).match(z, 10)
    agree = ((all_channels.pos_y == two.pos_y) & (all_channels.pos_x == two.pos_x)).float().mean()
    assert agree > 0.99


@pytest.mark.parametrize("shape,stride", [((12, 40, 48), 4), ((3, 24, 16), 2), ((2, 26, 18), 2), ((3, 40, 48), 8)])
def test_tiled_grid_gives_the_same_estimate_as_index_lists(shape, stride):
    gen = torch.Generator().manual_seed(2)
    z = torch.rand(shape, generator=gen, dtype=torch.float64)
    nl = NonlocalSparseTensor(shape, NLSTRParameters(stride=stride, strip_mb=2.0**-20), dtype=torch.float64)
    assert nl.tiled and len(nl.strips) > 1
    matches = nl.match(z, 10)
    x_tiled, _ = nl.estimate(z, matches)
    nl.tiled = False
    x_index, _ = nl.estimate(z, matches)
    torch.testing.assert_close(x_tiled, x_index, rtol=0, atol=1e-12)


def test_irregular_grids_are_not_tiled():
    assert not NonlocalSparseTensor((3, 42, 40), NLSTRParameters()).tiled   # 42 - 8 not a multiple of 4
    assert not NonlocalSparseTensor((3, 40, 40), NLSTRParameters(stride=3)).tiled  # 3 does not divide 8


def test_gram_maps_of_a_window_equal_the_whole_images_in_float32():
    # the dictionaries are computed in rectangles: a window's maps must be the whole image's numbers, bit for bit
    gen = torch.Generator().manual_seed(3)
    z = torch.rand(12, 61, 203, generator=gen)
    tri = tuple(torch.triu_indices(12, 12))
    whole = gram_maps(z, 8, tri).view(54, 196, -1)
    window = gram_maps(z[:, 9:50, 17:130], 8, tri).view(34, 106, -1)
    assert torch.equal(whole[9:43, 17:123], window)


def test_basis_tiles_cover_every_group_once_and_give_the_same_estimate():
    gen = torch.Generator().manual_seed(4)
    z = torch.rand(12, 90, 250, generator=gen)
    nl = NonlocalSparseTensor(tuple(z.shape), NLSTRParameters(strip_mb=1024.0))
    many = NonlocalSparseTensor(tuple(z.shape), NLSTRParameters(strip_mb=0.05))
    assert len(nl.basis_tiles) == 1 and len(many.basis_tiles) > 6
    groups = torch.cat([t.groups for t in many.basis_tiles])
    assert torch.equal(groups.sort().values, torch.arange(nl.n_ref))
    m = nl.match(z, 16)
    x1, s1 = nl.estimate(z, m, terms=True)
    nl.basis_tiles = many.basis_tiles  # same strips and grid, dictionaries in many rectangles
    x2, s2 = nl.estimate(z, m, terms=True)
    assert torch.equal(x1, x2) and s1 == s2
