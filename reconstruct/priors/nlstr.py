"""Nonlocal sparse tensor regularization (NLSTR), paper section 3.3 and section 4 steps 1-2.

The HR image ``Z = I - L`` (``(C, H, W)``, C = 12 for CAPS) is cut into overlapping
``b x b x C`` blocks ``R_k`` whose top-left corners lie on a grid of step ``stride``
(the last row/column of blocks always touches the border, so any size >= b works).
For each reference block:

1. **Block matching** (section 3.3): the ``P`` most similar blocks ``S^(k)`` in a
   ``(2 R + 1)^2`` window around it, by the channel-summed squared difference. Per offset,
   the squared differences of the image with its shifted copy (one pass for the pair
   ``+-o``: ``sq[-o](p) = sq[o](p - o)``), box-summed over the blocks of the reference
   grid, then ``topk``, in tiles of fixed size (:mod:`.nlstr_matching`: time linear in the pixels).
   With ``match_components = m > 0`` the
   differences are those of the image's ``m`` leading principal components of the channels
   (PCA-projected similarity, as in Tasdizen, "Principal neighborhood dictionaries for
   nonlocal means image denoising", IEEE TIP 18(12), 2009; here across channels): fewer
   channels to difference, an option of the ``fast`` preset, not the paper's.
2. **Dictionaries** (eq. 21, PCAT): the height-, width- and channel-mode PCA bases of
   the group are the eigenvectors of the mode Gram matrices ``S_(n) S_(n)^T``, summed
   over the ``P`` blocks. Each block's own 8x8 / 8x8 / CxC Gram matrix is read from
   per-position Gram maps computed for the whole image with box filters of products of
   shifted images (docs/architecture.md, "A reconstruction"); a group then only sums ``P`` small
   matrices. Batched ``torch.linalg.eigh`` gives the bases. The Gram matrices are not
   mean-centred: the complete orthonormal bases represent each block exactly.
3. **Tensor core** (eq. 22-23): ``alpha = R x1 Phi_h^T x2 Phi_w^T x3 Phi_c^T``,
   ``beta = U x1 ... `` with ``U = S x4 w`` the weighted sum of the similar blocks
   (eq. 19; ``w`` ~ ``exp(-d_p / h_k)``, ``d_p`` the per-element squared distance and
   ``h_k`` the group's mean distance), then
   ``C = soft((2 t beta + alpha) / (1 + 2 t), (lambda/mu) / (1 + 2 t))`` with the adaptive
   ``lambda/mu = c1 / |alpha|`` and ``t = eta/mu = c2 / |alpha - beta|^2``.
   ``adaptive="element"`` (default) takes these norms per coefficient (re-weighted l1,
   as in the NCSR-style rule the paper cites [17]); ``adaptive="block"`` takes the
   literal block norms ``||alpha||_1`` and ``||alpha - beta||_2^2`` (see
   docs/notes/solver.md for why the default is per coefficient).
4. **Aggregation** (eq. 29): ``X = (sum_k R_k^T 1)^-1 sum_k R_k^T (C x1 Phi_h x2 Phi_w
   x3 Phi_c)``: on a regular grid the blocks of every ``(b/s)``-th row and column tile the
   image and are added as reshaped images, else by ``index_add``.

Steps 3-4 run on chunks of about :data:`CHUNK_GROUPS` groups, whose temporaries stay in
the cache. Memory is bounded by ``strip_mb``: steps 3-4 process reference rows in whole-width strips,
and the dictionaries (step 2) are computed in rectangles of reference blocks of a fixed size (the Gram
maps' halo then costs the same share at every image size, where thin strips of a wide image were mostly
halo); the working set is estimated and checked (:mod:`capssim.resources`) before anything is
allocated. On CUDA the same code runs unchanged. The block-matching schedule across ADMM
iterations belongs to :class:`capssim.reconstruct.priors.nlstr_prior.NLSTRPrior`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from capssim.errors import InputError
from capssim.resources import check_memory, check_range

from .nlstr_blocks import (
    gather_blocks,
    gram_maps,
    group_matrix,
    mode_products,
    orthonormal_bases,
    row_segments,
    shrink_core,
    unpack_grams,
    weighted_block_sums,
)
from .nlstr_matching import match_blocks, plan_match_tiles
from .nlstr_parameters import NLSTRParameters
from .nlstr_plan import BasisTile, Strip, map_planes, plan_basis_tiles, plan_strips

log = logging.getLogger(__name__)

#: groups whose transform, shrinkage and inverse run together: their temporaries (~3 MB) stay in the
#: cache (at 1024 px an iteration's cores take 0.61 s in chunks of 512 against 0.78 s in whole strips)
CHUNK_GROUPS = 512


def reference_positions(size: int, block: int, stride: int) -> torch.Tensor:
    """Top-left coordinates ``0, s, 2s, ...`` plus ``size - block`` so blocks cover the image."""
    if size < block:
        raise InputError("image size", size, f"at least the block size {block}")
    pos = list(range(0, size - block + 1, stride))
    if pos[-1] != size - block:
        pos.append(size - block)
    return torch.tensor(pos, dtype=torch.int64)


@dataclass
class BlockMatches:
    """Result of block matching: for each of K reference blocks, P similar blocks.

    ``pos_y``/``pos_x`` ``(K, P)`` top-left corners (the reference itself first),
    ``distances`` ``(K, P)`` per-element mean squared differences (inf where a window
    had fewer than P candidates; those slots repeat the reference with weight 0),
    ``weights`` ``(K, P)`` normalized weights of ``U``.
    """

    pos_y: torch.Tensor
    pos_x: torch.Tensor
    distances: torch.Tensor
    weights: torch.Tensor

    @property
    def n_similar(self) -> int:
        return int(self.pos_y.shape[1])


def _triu(n: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    return tuple(torch.triu_indices(n, n, device=device))


class NonlocalSparseTensor:
    """The NLSTR operator for images of shape ``(C, H, W)`` (one instance per shape/device)."""

    def __init__(self, shape: tuple[int, int, int], params: NLSTRParameters = NLSTRParameters(), *, device="cpu",
                 dtype=torch.float32):
        params.validate()
        c, h, w = (int(v) for v in shape)
        b = params.block
        if h < b or w < b:
            raise InputError("image", f"{h}x{w}", f"at least one {b}x{b} block", "Use a smaller block size.")
        check_range("search_radius", params.search_radius, high=max(h, w), what="the block-matching search radius",
                    reason=f"the larger side of the {h}x{w} image: farther offsets hold no block",
                    fix=f"Use -p search_radius={min(params.search_radius, max(h, w))} or less (default 7).")
        self.params = params
        self.shape = (c, h, w)
        self.device = torch.device(device)
        self.dtype = dtype
        self.item_bytes = torch.tensor([], dtype=dtype).element_size()
        self.ref_y = reference_positions(h, b, params.stride).to(self.device)
        self.ref_x = reference_positions(w, b, params.stride).to(self.device)
        self.n_ref = int(self.ref_y.numel() * self.ref_x.numel())
        self.strips = plan_strips(self.shape, params, self.ref_y)
        self.basis_tiles = plan_basis_tiles(self.shape, params, self.ref_y, self.ref_x, item_bytes=self.item_bytes)
        self.match_tiles = plan_match_tiles(self.strips, self.ref_y, self.ref_x, block=b, stride=params.stride,
                                            search_radius=params.search_radius, budget_bytes=params.strip_bytes,
                                            item_bytes=self.item_bytes)
        self.check_resources(n_similar=1)
        # in-block pixel offsets (b*b,) in the flattened H*W image
        ii, jj = torch.meshgrid(torch.arange(b, device=self.device), torch.arange(b, device=self.device), indexing="ij")
        self.block_offsets = (ii * w + jj).reshape(-1)
        # aggregation weights sum_k R_k^T 1 (constant: depends only on the reference grid)
        count = torch.zeros(h * w, dtype=dtype, device=self.device)
        ref_flat = (self.ref_y[:, None] * w + self.ref_x[None, :]).reshape(-1)
        idx = (ref_flat[:, None] + self.block_offsets[None, :]).reshape(-1)
        count.index_add_(0, idx, torch.ones(idx.numel(), dtype=dtype, device=self.device))
        self.inv_count = (1.0 / count).reshape(h, w)
        self._tri_c = _triu(c, self.device)
        # reference grid 0, s, 2s, ... ending at the border with s dividing b: blocks of every (b/s)-th
        # row and column tile the image, so aggregation and reference gathers need no index lists
        self.tiled = b % params.stride == 0 and all(
            bool(torch.equal(pos, torch.arange(pos.numel(), device=self.device) * params.stride))
            for pos in (self.ref_y, self.ref_x))
        self._bases_cache: tuple | None = None  # (matches, every group's bases) of the last estimate
        self._groups_cache: tuple | None = None  # (matches, sparse group weights)

    # -- planning ------------------------------------------------------------------------
    def working_set_bytes(self, n_similar: int) -> int:
        """Peak bytes of one NLSTR step with ``n_similar`` blocks per group, about: the padded image,
        the matches ``(K, P)``, and the larger of: per matching tile (``m x v`` image pixels, ``n x u`` reference
        blocks) the offset maps ``((2R+1)^2, m, v)`` (x4) with the candidate tables ``(n u, (2R+1)^2)``, and the
        whole-width box sums ``((2R+1)^2, m, Nx)`` of a band of one-row strips; per strip of ``n`` reference rows
        (``m`` image rows) the groups' blocks ``(n Nx, b, b, C)`` (x10); per basis tile (``m x v`` pixels) the Gram
        maps ``(m-b+1, v-b+1, planes)`` (x3)."""
        c, h, w = self.shape
        b, r = self.params.block, self.params.search_radius
        item, n_off = self.item_bytes, (2 * r + 1) ** 2
        p, nx = max(1, min(int(n_similar), n_off)), int(self.ref_x.numel())
        rows = max(int(st.ref_rows.numel()) for st in self.strips)
        match = max(self._match_tile_bytes(tile, item) for tile in self.match_tiles)
        maps = max((t.y_hi - t.y_lo + 1) * (t.x_hi - t.x_lo + 1) for t in self.basis_tiles) * map_planes(b, c) * item * 3
        blocks = rows * nx * b * b * c * item * 10
        persistent = c * (h + 4 * r) * (w + 4 * r) * item + self.n_ref * (p * (16 + 2 * item) + b * b * 16)
        persistent += self.n_ref * b * b * c * item  # U of every group
        return int(persistent + 4 * h * w * c * item + max(match, maps, blocks))

    def _match_tile_bytes(self, tile, item: int) -> int:
        """Peak bytes of block matching in one tile (:meth:`working_set_bytes`)."""
        b, r = self.params.block, self.params.search_radius
        n_off, nx = (2 * r + 1) ** 2, int(self.ref_x.numel())
        height = int(self.ref_y[tile.row1 - 1] - self.ref_y[tile.row0]) + b
        width = int(self.ref_x[tile.col1 - 1] - self.ref_x[tile.col0]) + b
        refs = (tile.row1 - tile.row0) * (tile.col1 - tile.col0)
        wide = height * nx * n_off * item if any(run[2] and run[1] - run[0] == 1 for run in tile.runs) else 0
        return height * width * n_off * item * 4 + refs * n_off * (2 * item + 17) + wide

    def check_resources(self, *, n_similar: int) -> None:
        """Refuse (:class:`~capssim.errors.ResourceError`) a step whose working set is past the memory limit."""
        prm, (_, h, w) = self.params, self.shape
        check_memory("search_radius", self.working_set_bytes(n_similar), what=(
            f"NLSTR on a {h}x{w} image (block {prm.block}, stride {prm.stride}, search_radius {prm.search_radius}, "
            f"n_similar {n_similar})"), fix="Use a smaller -p search_radius (default 7), n_similar or block, or a "
                                            "larger stride.")

    def _strip_refs(self, strip: Strip) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reference coordinates of a strip and their global group indices."""
        nx = self.ref_x.numel()
        ry = self.ref_y[strip.ref_rows][:, None].expand(-1, nx).reshape(-1)
        rx = self.ref_x[None, :].expand(strip.ref_rows.numel(), -1).reshape(-1)
        groups = (strip.ref_rows[:, None] * nx + torch.arange(nx, device=self.device)[None, :]).reshape(-1)
        return ry, rx, groups

    def _check(self, z: torch.Tensor) -> None:
        if tuple(z.shape) != self.shape:
            raise InputError("z", f"shape {tuple(z.shape)}", f"shape {self.shape}")

    # -- step: block matching ------------------------------------------------------------
    def match(self, z: torch.Tensor, n_similar: int) -> BlockMatches:
        """The ``n_similar`` most similar blocks of every reference block (reference first), matched in the
        fixed-size tiles of :func:`~capssim.reconstruct.priors.nlstr_matching.plan_match_tiles`."""
        self._check(z)
        self.check_resources(n_similar=n_similar)
        out_y, out_x, out_d = match_blocks(z, n_similar, self.match_tiles, self.ref_y, self.ref_x,
                                           block=self.params.block, radius=self.params.search_radius,
                                           components=self.params.match_components)
        return BlockMatches(out_y, out_x, out_d, self._weights(out_d))

    def _weights(self, d: torch.Tensor) -> torch.Tensor:
        """``w ~ exp(-d / h_k)``, ``h_k`` the group's mean distance (times ``weight_bandwidth``)."""
        finite = torch.isfinite(d)
        others = finite.clone()
        others[:, 0] = False
        n_others = others.sum(1, keepdim=True).clamp(min=1)
        h = torch.where(others, d, torch.zeros_like(d)).sum(1, keepdim=True) / n_others
        h = h * self.params.weight_bandwidth + 1e-12
        w = torch.where(finite, torch.exp(-torch.where(finite, d, torch.zeros_like(d)) / h), torch.zeros_like(d))
        return w / w.sum(1, keepdim=True)

    # -- step: dictionaries, cores, aggregation ---------------------------------------
    def _group_matrix(self, matches: BlockMatches) -> torch.Tensor:
        """The groups' weights as a sparse ``(K, positions)`` matrix (cached for the last ``matches``)."""
        if self._groups_cache is None or self._groups_cache[0] is not matches:
            b, w = self.params.block, self.shape[2]
            n_columns = self.shape[1] * w - (b - 1) * (w + 1)  # one past the last block corner
            self._groups_cache = (matches, group_matrix(matches.pos_y * w + matches.pos_x, matches.weights, n_columns))
        return self._groups_cache[1]

    def _tile_bases(self, z: torch.Tensor, tile: BasisTile, py: torch.Tensor, px: torch.Tensor):
        """PCA bases ``Ph, Pw`` ``(k, b, b)`` and ``Pc`` ``(k, C, C)`` of a basis tile's groups (eq. 21), whose
        matches have corners ``py, px`` ``(k, P)``."""
        b = self.params.block
        maps = gram_maps(z[:, tile.y_lo:tile.y_hi + b, tile.x_lo:tile.x_hi + b], b, self._tri_c)  # (ny*nx, planes)
        local = (py - tile.y_lo) * (tile.x_hi - tile.x_lo + 1) + (px - tile.x_lo)                  # (k, P)
        sums = maps.index_select(0, local[:, 0])
        for j in range(1, local.shape[1]):
            sums.add_(maps.index_select(0, local[:, j]))
        del maps
        gram_hw, gram_c = unpack_grams(sums, b, self._tri_c, self.shape[0])
        k = py.shape[0]
        bases_hw = orthonormal_bases(gram_hw)
        return bases_hw[:k], bases_hw[k:], orthonormal_bases(gram_c)

    def _all_bases(self, z: torch.Tensor, matches: BlockMatches) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The dictionaries of every group, ``Ph, Pw`` ``(K, b, b)`` and ``Pc`` ``(K, C, C)``, basis tile by basis
        tile (the Gram maps are position-independent sums, so tiles give the whole image's numbers)."""
        c, b = self.shape[0], self.params.block
        ph = z.new_empty(self.n_ref, b, b)
        pw, pc = torch.empty_like(ph), z.new_empty(self.n_ref, c, c)
        for tile in self.basis_tiles:
            g = tile.groups
            for out, part in zip((ph, pw, pc), self._tile_bases(z, tile, matches.pos_y[g], matches.pos_x[g])):
                out.index_copy_(0, g, part)
        return ph, pw, pc

    def _reference_blocks(self, z_pixels: torch.Tensor, strip: Strip) -> torch.Tensor:
        """The strip's reference blocks ``(rows, Nx, b, b, C)`` as a strided view of ``z_pixels`` (tiled grid)."""
        c, _, w = self.shape
        b, s = self.params.block, self.params.stride
        y0, rows, nx = int(self.ref_y[strip.ref_rows[0]]), strip.ref_rows.numel(), self.ref_x.numel()
        return z_pixels.as_strided((rows, nx, b, b, c), (s * w * c, s * c, w * c, c, 1), y0 * w * c)

    def _add_tiles(self, num: torch.Tensor, blocks: torch.Tensor, strip: Strip) -> None:
        """``num`` ``(H, W, C)`` += the strip's ``blocks`` ``(k, b, b, C)`` at their grid positions (eq. 29's
        ``sum_k R_k^T``): the blocks of every ``(b/s)``-th row and column do not overlap, so each of the
        ``(b/s)^2`` phases is one reshaped image added into a slice."""
        c = self.shape[0]
        b, s = self.params.block, self.params.stride
        r, y0 = b // s, int(self.ref_y[strip.ref_rows[0]])
        grid = blocks.view(strip.ref_rows.numel(), self.ref_x.numel(), b, b, c)
        for p in range(min(r, grid.shape[0])):
            for q in range(min(r, grid.shape[1])):
                tiles = grid[p::r, q::r]
                ny, nx = tiles.shape[:2]
                top, left = y0 + p * s, q * s
                num[top:top + ny * b, left:left + nx * b] += tiles.permute(0, 2, 1, 3, 4).reshape(ny * b, nx * b, c)

    def _shrunk_blocks(self, refs: torch.Tensor, u: torch.Tensor, bases: tuple, acc: dict,
                       terms: bool) -> torch.Tensor:
        """Eq. 22-23 and the inverse transform for groups with reference blocks ``refs`` ``(R, n, b, b*C)`` (``R``
        rows of ``n`` groups; a strided view allowed) and weighted sums ``u`` ``(R*n, b, b*C)``: the blocks
        ``(R*n, b, b, C)`` of the shrunk cores. Chunks of whole rows, about :data:`CHUNK_GROUPS` groups, stack
        their ``R`` and ``U`` (one batched transform) and stay in the cache; the statistics of
        :func:`shrink_core` are added to ``acc``."""
        prm, c = self.params, self.shape[0]
        rows, per_row, b = refs.shape[:3]
        blocks = u.new_empty(rows * per_row, b, b, c)
        step = max(1, CHUNK_GROUPS // per_row)
        for r0 in range(0, rows, step):
            part = slice(r0 * per_row, min(rows, r0 + step) * per_row)
            ph, pw, pc = (basis[part] for basis in bases)
            chunk = refs[r0:r0 + step]
            pair = torch.stack([chunk, u[part].view(chunk.shape)], dim=3).view(-1, b, 2, b, c)
            coeffs = mode_products(pair, ph, pw, pc, transpose=True)
            alpha, beta = coeffs[:, :, 0], coeffs[:, :, 1]  # (n, b, b, C) views, no copies
            core, parts = shrink_core(alpha, beta, prm.c1, prm.c2, adaptive=prm.adaptive, eps=prm.eps, terms=terms)
            for key, value in parts.items():
                acc[key] = acc.get(key, 0.0) + value
            blocks[part] = mode_products(core, ph, pw, pc, transpose=False)
        return blocks

    def estimate(self, z: torch.Tensor, matches: BlockMatches, *, reuse_bases: bool = False,
                 terms: bool = False) -> tuple[torch.Tensor, dict]:
        """Steps 1-2 of section 4 and eq. 29: the aggregated sparse estimate ``X`` ``(C, H, W)``.

        ``reuse_bases``: keep the dictionaries of the previous call (same ``matches``) instead
        of recomputing them from ``z`` (a lazier schedule, :class:`~capssim.reconstruct.priors.nlstr_prior.
        MatchSchedule` ``dictionary_gap``); refused when there are none for these matches.
        Returns ``X`` and statistics: ``zero_fraction`` of the cores and, when ``terms``, ``l1``
        (sum of lambda_k/mu |C|), ``fit`` (``||alpha - C||^2``), ``nonlocal``
        (``sum eta_k/mu ||beta - C||^2``).
        """
        self._check(z)
        c, h, w = self.shape
        b = self.params.block
        if reuse_bases and (self._bases_cache is None or self._bases_cache[0] is not matches):
            raise InputError("reuse_bases", True, "False when the matches changed (no dictionaries to reuse)")
        if not reuse_bases:
            self._bases_cache = (matches, self._all_bases(z, matches))
        bases = self._bases_cache[1]
        z_pixels = z.permute(1, 2, 0).reshape(h * w, c).contiguous()
        segments = row_segments(z_pixels, b)
        u_all = weighted_block_sums(z_pixels, self._group_matrix(matches), b, w).view(self.n_ref, b, b * c)
        row_starts = torch.arange(b, device=z.device) * w
        num = torch.zeros(h * w, c, dtype=z.dtype, device=z.device)
        acc: dict = {}
        for strip in self.strips:
            ry, rx, groups = self._strip_refs(strip)
            k = groups.numel()
            ph, pw, pc = (basis.narrow(0, int(groups[0]), k) for basis in bases)  # a strip's groups are consecutive
            if self.tiled:  # the reference blocks R: a strided view (rows, Nx, b, b*C)
                refs = self._reference_blocks(z_pixels, strip).flatten(-2)
            else:
                refs = gather_blocks(segments, ry * w + rx, row_starts)[:, None]
            u = u_all.narrow(0, int(groups[0]), k)  # U = S x4 w (eq. 19); a strip's groups are consecutive
            blocks = self._shrunk_blocks(refs, u, (ph, pw, pc), acc, terms)
            if self.tiled:
                self._add_tiles(num.view(h, w, c), blocks, strip)
            else:
                idx = ((ry * w + rx)[:, None] + self.block_offsets[None, :]).reshape(-1)
                num.index_add_(0, idx, blocks.reshape(-1, c))
        x = num.reshape(h, w, c).permute(2, 0, 1) * self.inv_count
        stats = {key: float(v) for key, v in acc.items()}
        stats["zero_fraction"] = stats.pop("zeros") / max(self.n_ref * b * b * c, 1)
        return x.contiguous(), stats


__all__ = ["BlockMatches", "NLSTRParameters", "NonlocalSparseTensor", "reference_positions", "shrink_core"]
