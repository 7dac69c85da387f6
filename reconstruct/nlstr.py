"""Nonlocal sparse tensor regularization (NLSTR), paper section 3.3 and section 4 steps 1-2.

The HR image ``Z = I - L`` (``(C, H, W)``, C = 12 for CAPS) is cut into overlapping
``b x b x C`` blocks ``R_k`` whose top-left corners lie on a grid of step ``stride``
(the last row/column of blocks always touches the border, so any size >= b works).
For each reference block:

1. **Block matching** (section 3.3): the ``P`` most similar blocks ``S^(k)`` in a
   ``(2 R + 1)^2`` window around it, by the channel-summed squared difference. All
   candidate offsets are scored at once per row of offsets: the squared differences of
   the image with its shifted copies, box-summed over the block (``avg_pool``), then
   ``topk``. No Python loop over blocks.
2. **Dictionaries** (eq. 21, PCAT): the height-, width- and channel-mode PCA bases of
   the group are the eigenvectors of the mode Gram matrices ``S_(n) S_(n)^T``, summed
   over the ``P`` blocks. Each block's own 8x8 / 8x8 / CxC Gram matrix is read from
   per-position Gram maps computed for the whole image with box filters of products of
   shifted images (DESIGN.md performance notes); a group then only sums ``P`` small
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
   x3 Phi_c)``, by ``index_add`` into the image.

Memory is bounded by processing reference rows in strips sized by ``strip_mb``; the
working set is estimated and checked (:mod:`capssim.resources`) before anything is
allocated. On CUDA the same code runs unchanged. The block-matching schedule across ADMM
iterations belongs to :class:`capssim.reconstruct.nlstr_prior.NLSTRPrior`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from capssim.errors import InputError
from capssim.reconstruct.filters import sliding_window_sum
from capssim.resources import check_memory, check_range

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NLSTRParameters:
    """Parameters of the nonlocal sparse tensor step (paper 5.1 defaults)."""

    block: int = 8
    stride: int = 4
    search_radius: int = 7
    c1: float = 0.002
    c2: float = 0.02
    adaptive: str = "element"
    weight_bandwidth: float = 1.0
    eps: float = 1e-8
    strip_mb: float = 48.0  # working-set bound of one strip of reference rows (MiB)

    @property
    def strip_bytes(self) -> int:
        """``strip_mb`` in bytes."""
        return int(self.strip_mb * 2**20)

    def validate(self) -> None:
        for name in ("block", "stride", "search_radius"):
            if isinstance(getattr(self, name), bool) or not isinstance(getattr(self, name), int):
                raise InputError(name, repr(getattr(self, name)), "an integer")
        if self.block < 2:
            raise InputError("block", self.block, "an integer >= 2 (block side in HR pixels)")
        if not 1 <= self.stride <= self.block:
            raise InputError("stride", self.stride, f"an integer in [1, block={self.block}]")
        if self.search_radius < 0:
            raise InputError("search_radius", self.search_radius, "an integer >= 0")
        for name in ("c1", "c2", "weight_bandwidth", "strip_mb"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise InputError(name, v, "a finite positive number")
        if self.adaptive not in ("element", "block"):
            raise InputError("adaptive", self.adaptive, "'element' or 'block'")


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


@dataclass
class _Strip:
    ref_rows: torch.Tensor     # indices into the reference-row list
    y_lo: int                  # first candidate block row
    y_hi: int                  # last candidate block row (inclusive)


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
                    fix=f"Use -O search_radius={min(params.search_radius, max(h, w))} or less (default 7).")
        self.params = params
        self.shape = (c, h, w)
        self.device = torch.device(device)
        self.dtype = dtype
        self.ref_y = reference_positions(h, b, params.stride).to(self.device)
        self.ref_x = reference_positions(w, b, params.stride).to(self.device)
        self.n_ref = int(self.ref_y.numel() * self.ref_x.numel())
        self.strips = self._plan_strips()
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
        self._tri_b = _triu(b, self.device)
        self._tri_c = _triu(c, self.device)

    # -- planning ------------------------------------------------------------------------
    def _map_planes(self) -> int:
        b, c = self.params.block, self.shape[0]
        return b * (b + 1) + c * (c + 1) // 2

    def _plan_strips(self) -> list[_Strip]:
        """Group reference rows so each strip's Gram maps fit in ``strip_mb``."""
        c, h, w = self.shape
        b, s, r = self.params.block, self.params.stride, self.params.search_radius
        per_row = (w - b + 1) * self._map_planes() * 4 + 15 * c * w * 4
        rows_budget = max(1, self.params.strip_bytes // max(per_row, 1))
        # a strip of n reference rows spans about n*s + 2r block rows
        n_rows = max(1, int((rows_budget - 2 * r) // s))
        strips = []
        ny = self.ref_y.numel()
        for start in range(0, ny, n_rows):
            rows = torch.arange(start, min(ny, start + n_rows), device=self.device)
            ya, yb = int(self.ref_y[rows[0]]), int(self.ref_y[rows[-1]])
            strips.append(_Strip(rows, max(0, ya - r), min(h - b, yb + r)))
        return strips

    def working_set_bytes(self, n_similar: int) -> int:
        """Peak bytes of one NLSTR step with ``n_similar`` blocks per group, about: the padded image,
        the matches ``(K, P)``, and per strip of ``n`` reference rows (``m`` image rows) the larger of
        the offset maps ``(m, (2R+1)^2, W)`` (x4) with the candidate tables ``(n Nx, (2R+1)^2)``, and
        the Gram maps ``(m-b+1, W-b+1, planes)`` (x3) with the groups' blocks ``(n Nx, b, b, C)`` (x10)."""
        c, h, w = self.shape
        b, s, r = self.params.block, self.params.stride, self.params.search_radius
        item, n_off = torch.tensor([], dtype=self.dtype).element_size(), (2 * r + 1) ** 2
        p, nx = max(1, min(int(n_similar), n_off)), int(self.ref_x.numel())
        rows = max(int(st.ref_rows.numel()) for st in self.strips)
        match_rows = (rows - 1) * s + b
        match = match_rows * n_off * w * item * 4 + rows * nx * n_off * (2 * item + 17)
        gram_rows = min(h, match_rows + 2 * r) - b + 1
        gram = gram_rows * (w - b + 1) * self._map_planes() * item * 3 + rows * nx * b * b * c * item * 10
        persistent = c * (h + 2 * r) * (w + 2 * r) * item + self.n_ref * (p * (16 + 2 * item) + b * b * 16)
        return int(persistent + 4 * h * w * c * item + max(match, gram))

    def check_resources(self, *, n_similar: int) -> None:
        """Refuse (:class:`~capssim.errors.ResourceError`) a step whose working set is past the memory limit."""
        prm, (_, h, w) = self.params, self.shape
        check_memory("search_radius", self.working_set_bytes(n_similar), what=(
            f"NLSTR on a {h}x{w} image (block {prm.block}, stride {prm.stride}, search_radius {prm.search_radius}, "
            f"n_similar {n_similar})"), fix="Use a smaller -O search_radius (default 7), n_similar or block, or a "
                                            "larger stride.")

    def _strip_refs(self, strip: _Strip) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
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
        """The ``n_similar`` most similar blocks of every reference block (reference first)."""
        self._check(z)
        self.check_resources(n_similar=n_similar)
        c, h, w = self.shape
        b, r = self.params.block, self.params.search_radius
        n_off = (2 * r + 1) ** 2
        p = max(1, min(int(n_similar), n_off))
        zpad = F.pad(z, (r, r, r, r))
        dy_all = torch.arange(-r, r + 1, device=z.device)
        dys = dy_all[:, None].expand(-1, 2 * r + 1).reshape(-1)
        dxs = dy_all[None, :].expand(2 * r + 1, -1).reshape(-1)
        out_y = torch.empty(self.n_ref, p, dtype=torch.int64, device=z.device)
        out_x = torch.empty_like(out_y)
        out_d = torch.empty(self.n_ref, p, dtype=z.dtype, device=z.device)
        for strip in self.strips:
            ry, rx, groups = self._strip_refs(strip)
            ya = int(self.ref_y[strip.ref_rows[0]])
            yb = int(self.ref_y[strip.ref_rows[-1]])
            rows = yb + b - ya
            a = z[:, ya:ya + rows, :]
            ref_rows_rel = self.ref_y[strip.ref_rows] - ya
            sq = torch.empty(rows, n_off, w, dtype=z.dtype, device=z.device)
            for t in range(n_off):  # whole-image ops per offset, no loop over blocks
                dy, dx = divmod(t, 2 * r + 1)
                diff = a - zpad[:, ya + dy:ya + dy + rows, dx:dx + w]
                sq[:, t] = diff.square_().sum(0)
            box = sliding_window_sum(sq, b, dim=2).index_select(2, self.ref_x)         # (rows, n_off, nx)
            box = sliding_window_sum(box, b, dim=0).index_select(0, ref_rows_rel)      # (nrows, n_off, nx)
            dist = box.permute(0, 2, 1)                                                # (nrows, nx, n_off)
            dist = dist.reshape(-1, n_off) / float(b * b * c)
            cy = ry[:, None] + dys[None, :]
            cx = rx[:, None] + dxs[None, :]
            valid = (cy >= 0) & (cy <= h - b) & (cx >= 0) & (cx <= w - b)
            dist = torch.where(valid, dist.clamp(min=0), torch.full_like(dist, float("inf")))
            dist[:, n_off // 2] = -1.0  # the reference itself always comes first
            best_d, best = torch.topk(dist, p, dim=1, largest=False, sorted=True)
            best_d[:, 0] = 0.0
            ok = torch.isfinite(best_d)
            out_y[groups] = torch.where(ok, ry[:, None] + dys[best], ry[:, None].expand(-1, p))
            out_x[groups] = torch.where(ok, rx[:, None] + dxs[best], rx[:, None].expand(-1, p))
            out_d[groups] = best_d
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

    # -- step: per-position Gram maps --------------------------------------------------
    def _gram_maps(self, zr: torch.Tensor) -> torch.Tensor:
        """Per-block-position Gram entries of a region ``(C, Hr, W)`` -> ``(Ny*Nx, planes)``.

        Planes: height mode ``(i, i+d)`` for ``i + d < b`` (b(b+1)/2), width mode
        likewise, channel mode ``(c, c')`` for ``c <= c'``. Box sums use
        (exact pairwise sums, see :func:`capssim.reconstruct.filters.sliding_window_sum`).
        """
        c, hr, w = zr.shape
        b = self.params.block
        ny, nx = hr - b + 1, w - b + 1
        zh = zr.permute(1, 2, 0)                                                   # (hr, W, C) view
        planes = []
        # height mode: G_h[i, i+d] = sum_{j<b, c} z[c, y+i, x+j] z[c, y+i+d, x+j]
        for d in range(b):
            prod = (zr[:, :hr - d, :] * zr[:, d:, :]).sum(0)                      # (hr-d, W)
            rowbox = sliding_window_sum(prod, b, dim=1)                           # (hr-d, nx)
            for i in range(b - d):
                planes.append(rowbox[i:i + ny])
        # width mode: G_w[j, j+d] = sum_{i<b, c} z[c, y+i, x+j] z[c, y+i, x+j+d]
        for d in range(b):
            prod = (zr[:, :, :w - d] * zr[:, :, d:]).sum(0)                       # (hr, W-d)
            colbox = sliding_window_sum(prod, b, dim=0)                           # (ny, W-d)
            for j in range(b - d):
                planes.append(colbox[:, j:j + nx])
        maps_hw = torch.stack(planes, dim=-1)                                      # (ny, nx, b(b+1))
        # channel mode: 2-D box of every channel product c <= c'
        iu, ju = self._tri_c
        prods = zh.index_select(2, iu) * zh.index_select(2, ju)                    # (hr, W, T)
        box = sliding_window_sum(sliding_window_sum(prods, b, dim=0), b, dim=1)    # (ny, nx, T)
        return torch.cat([maps_hw, box], dim=-1).reshape(ny * nx, -1)

    def _unpack(self, sums: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Summed Gram entries ``(k, planes)`` -> height+width ``(2k, b, b)`` and channel ``(k, C, C)``."""
        b, c = self.params.block, self.shape[0]
        k = sums.shape[0]
        nb = b * (b + 1) // 2
        # plane order above: for d, for i -> pair (i, i + d)
        pairs = [(i, i + d) for d in range(b) for i in range(b - d)]
        rows = torch.tensor([p[0] for p in pairs], device=sums.device)
        cols = torch.tensor([p[1] for p in pairs], device=sums.device)
        hw = sums.new_zeros(2, k, b, b)
        for mode in range(2):
            vals = sums[:, mode * nb:(mode + 1) * nb]
            hw[mode][:, rows, cols] = vals
            hw[mode][:, cols, rows] = vals
        cc = sums.new_zeros(k, c, c)
        iu, ju = self._tri_c
        vals = sums[:, 2 * nb:]
        cc[:, iu, ju] = vals
        cc[:, ju, iu] = vals
        return hw.reshape(2 * k, b, b), cc

    @staticmethod
    def _bases(gram: torch.Tensor) -> torch.Tensor:
        """Eigenvectors (columns) of a batch of symmetric PSD matrices, scale-normalized."""
        scale = torch.diagonal(gram, dim1=-2, dim2=-1).sum(-1).clamp(min=1e-30)[:, None, None]
        n = gram.shape[-1]
        eye = torch.eye(n, dtype=gram.dtype, device=gram.device)
        _, vecs = torch.linalg.eigh(gram / scale + 1e-7 * eye)
        return vecs

    # -- transforms --------------------------------------------------------------------
    @staticmethod
    def _mode_products(t: torch.Tensor, ph: torch.Tensor, pw: torch.Tensor, pc: torch.Tensor,
                       transpose: bool) -> torch.Tensor:
        """``t x1 Ph x2 Pw x3 Pc`` (or with the transposes) for blocks ``t`` ``(k, b, b, C)``."""
        k, b, _, c = t.shape
        if transpose:
            ph, pw = ph.transpose(1, 2), pw.transpose(1, 2)
        else:
            pc = pc.transpose(1, 2)
        # mode 1 (height): out[a, j, c] = sum_i Ph[a, i] t[i, j, c]
        x = torch.bmm(ph, t.reshape(k, b, b * c)).reshape(k, b, b, c)
        # mode 2 (width)
        x = torch.bmm(pw, x.transpose(1, 2).reshape(k, b, b * c)).reshape(k, b, b, c).transpose(1, 2)
        # mode 3 (channel): out[..., d] = sum_c x[..., c] Pc[c, d]
        return torch.bmm(x.reshape(k, b * b, c), pc).reshape(k, b, b, c)

    def _gather_blocks(self, z_flat: torch.Tensor, py: torch.Tensor, px: torch.Tensor) -> torch.Tensor:
        """Blocks ``(k, b, b, C)`` at top-left corners ``py, px`` ``(k,)`` of ``z_flat`` ``(H*W, C)``."""
        b = self.params.block
        w = self.shape[2]
        idx = ((py * w + px)[:, None] + self.block_offsets[None, :]).reshape(-1)
        return z_flat.index_select(0, idx).reshape(-1, b, b, z_flat.shape[1])

    # -- step: dictionaries, cores, aggregation ---------------------------------------
    def estimate(self, z: torch.Tensor, matches: BlockMatches) -> tuple[torch.Tensor, dict]:
        """Steps 1-2 of section 4 and eq. 29: the aggregated sparse estimate ``X`` ``(C, H, W)``.

        Returns ``X`` and statistics: ``l1`` (sum of lambda_k/mu |C|), ``fit``
        (``||alpha - C||^2``), ``nonlocal`` (``sum eta_k/mu ||beta - C||^2``), ``zero_fraction``.
        """
        self._check(z)
        c, h, w = self.shape
        b = self.params.block
        prm = self.params
        z_flat = z.permute(1, 2, 0).reshape(h * w, c).contiguous()
        num = torch.zeros(h * w, c, dtype=z.dtype, device=z.device)
        stats = {"l1": 0.0, "fit": 0.0, "nonlocal": 0.0, "zeros": 0.0, "coefficients": 0}
        acc = {k: z.new_zeros(()) for k in ("l1", "fit", "nonlocal", "zeros")}
        for strip in self.strips:
            ry, rx, groups = self._strip_refs(strip)
            k = groups.numel()
            zr = z[:, strip.y_lo:strip.y_hi + b, :]
            maps = self._gram_maps(zr)                                              # (ny*nx, planes)
            nx = w - b + 1
            py = matches.pos_y[groups]
            px = matches.pos_x[groups]
            local = (py - strip.y_lo) * nx + px                                    # (k, P)
            sums = maps.index_select(0, local[:, 0])
            for j in range(1, matches.n_similar):
                sums.add_(maps.index_select(0, local[:, j]))
            del maps
            gram_hw, gram_c = self._unpack(sums)
            bases_hw = self._bases(gram_hw)
            ph, pw = bases_hw[:k], bases_hw[k:]
            pc = self._bases(gram_c)
            ref_blocks = self._gather_blocks(z_flat, ry, rx)
            wts = matches.weights[groups]
            u = self._gather_blocks(z_flat, py[:, 0], px[:, 0]).mul_(wts[:, :1, None, None])
            for j in range(1, matches.n_similar):
                u.add_(self._gather_blocks(z_flat, py[:, j], px[:, j]).mul_(wts[:, j:j + 1, None, None]))
            alpha = self._mode_products(ref_blocks, ph, pw, pc, transpose=True).reshape(k, -1)
            beta = self._mode_products(u, ph, pw, pc, transpose=True).reshape(k, -1)
            core, parts = shrink_core(alpha, beta, prm.c1, prm.c2, adaptive=prm.adaptive, eps=prm.eps)
            for key in acc:
                acc[key] += parts[key]
            blocks = self._mode_products(core.reshape(k, b, b, c), ph, pw, pc, transpose=False)
            idx = ((ry * w + rx)[:, None] + self.block_offsets[None, :]).reshape(-1)
            num.index_add_(0, idx, blocks.reshape(-1, c))
        x = num.reshape(h, w, c).permute(2, 0, 1) * self.inv_count
        n_coef = self.n_ref * b * b * c
        stats = {key: float(v) for key, v in acc.items()}
        stats["zero_fraction"] = stats.pop("zeros") / max(n_coef, 1)
        return x.contiguous(), stats


def shrink_core(alpha: torch.Tensor, beta: torch.Tensor, c1: float, c2: float, *, adaptive: str = "element",
                eps: float = 1e-8) -> tuple[torch.Tensor, dict]:
    """Eq. 23 with the adaptive ``lambda_k/mu`` and ``eta_k/mu`` of section 4, for cores ``(k, n)``.

    ``C = soft((2 t beta + alpha) / (1 + 2 t), (lambda/mu) / (1 + 2 t))``, ``t = eta/mu``.
    Returns the core and the summed terms ``l1`` (``lambda/mu |C|``), ``fit``
    (``|alpha - C|^2``), ``nonlocal`` (``eta/mu |beta - C|^2``) and ``zeros`` (count of zeros).
    """
    if adaptive == "element":
        lam = c1 / (alpha.abs() + eps)
        t = c2 / ((alpha - beta).square() + eps)
    elif adaptive == "block":
        lam = (c1 / (alpha.abs().sum(1, keepdim=True) + eps)).expand_as(alpha)
        t = (c2 / ((alpha - beta).square().sum(1, keepdim=True) + eps)).expand_as(alpha)
    else:
        raise InputError("adaptive", adaptive, "'element' or 'block'")
    denom = 1.0 + 2.0 * t
    v = (2.0 * t * beta + alpha) / denom
    thr = lam / denom
    core = torch.sign(v) * torch.clamp(v.abs() - thr, min=0)
    parts = {
        "l1": (lam * core.abs()).sum(),
        "fit": (alpha - core).square().sum(),
        "nonlocal": (t * (beta - core).square()).sum(),
        "zeros": (core == 0).sum().to(alpha.dtype),
    }
    return core, parts


__all__ = ["BlockMatches", "NLSTRParameters", "NonlocalSparseTensor", "reference_positions", "shrink_core"]
