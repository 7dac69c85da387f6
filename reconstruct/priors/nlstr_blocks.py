"""Block-level kernels of NLSTR (section 3.3, eq. 21-23): block-matching differences, Gram maps, PCA bases, mode
products, cores.

Split out of :mod:`capssim.reconstruct.priors.nlstr`, which plans the strips and the groups. Blocks
are ``(k, b, b, C)`` (height, width, channel); images ``(C, H, W)`` or, for the gathers, the
pixel-major ``(H*W, C)`` layout in which a block's row of ``b`` pixels is ``b*C`` consecutive
numbers. Everything is batched torch and runs unchanged on CUDA.
"""

from __future__ import annotations

import warnings

import torch

from capssim.errors import InputError

from ..filters import sliding_window_sum


def principal_channels(z: torch.Tensor, count: int) -> torch.Tensor:
    """``z`` ``(C, H, W)`` projected on its ``count`` leading principal components of the channels
    (eigenvectors of the mean-removed ``C x C`` channel covariance): ``(count, H, W)``; ``z`` itself when
    ``count`` is 0 or at least ``C``. Distances between blocks of the projection are those of ``z``
    within the components' subspace (a lower bound)."""
    c = z.shape[0]
    if count <= 0 or count >= c:
        return z
    flat = z.reshape(c, -1)
    centred = flat - flat.mean(1, keepdim=True)
    _, vectors = torch.linalg.eigh(centred @ centred.T)                     # ascending eigenvalues
    return (vectors[:, -count:].T @ flat).reshape(count, *z.shape[1:])


def offset_differences(zpad: torch.Tensor, top: int, rows: int, width: int, radius: int) -> torch.Tensor:
    """``sq[t, y, x] = sum_c (z[c, top + y, x] - z[c, top + y + oy, x + ox])^2`` for every offset ``t = (oy, ox)``
    of the ``(2 r + 1)^2`` window (row-major), from ``zpad`` = ``z`` zero-padded by ``2 r``: ``(n_off, rows, W)``.

    Offsets come in pairs ``+-o`` with ``sq[-o](p) = sq[o](p - o)``: each pair is one pass over the channels,
    on the region widened by ``r`` (bit-identical to computing both; about 0.6x the work). Values at pixels
    whose partner lies outside the image are those of zero padding and belong to invalid candidates only.
    """
    r = radius
    side = 2 * r + 1
    n_off = side * side
    sq = zpad.new_empty(n_off, rows, width)
    sq[n_off // 2] = 0.0
    ext = zpad[:, top + r:top + rows + 3 * r, r:width + 3 * r]                  # image rows top-r.., cols -r..
    diff = torch.empty_like(ext)
    pair_sum = zpad.new_empty(ext.shape[1:])
    for t in range(n_off // 2 + 1, n_off):  # the offsets after the centre; their mirrors are n_off - 1 - t
        oy, ox = t // side - r, t % side - r
        torch.sub(ext, zpad[:, top + r + oy:top + rows + 3 * r + oy, r + ox:width + 3 * r + ox], out=diff)
        torch.sum(diff.square_(), 0, out=pair_sum)
        sq[t] = pair_sum[r:r + rows, r:r + width]
        sq[n_off - 1 - t] = pair_sum[r - oy:r - oy + rows, r - ox:r - ox + width]
    return sq


def chunked_windows(size: int, starts: torch.Tensor, length: int) -> bool:
    """Whether :func:`window_sums_at` sums windows ``[start, start + size)`` of a length-``length`` axis as
    consecutive chunks: the starts are ``0, s, 2s, ...`` with ``s`` dividing ``size`` (chunks of ``s``; one start:
    one chunk of ``size``). Else it takes every window sum and selects the starts. The two round differently in
    float32, so a caller that splits an axis keeps the choice of the whole (:mod:`.nlstr_matching`)."""
    n = starts.numel()
    step = int(starts[1] - starts[0]) if n > 1 else size
    return (step > 0 and size % step == 0 and step * (n - 1) + size <= length and int(starts[0]) == 0
            and bool((starts == torch.arange(n, device=starts.device) * step).all()))


def window_sums_at(x: torch.Tensor, size: int, starts: torch.Tensor, *, dim: int, chunked: bool | None = None
                   ) -> torch.Tensor:
    """Sums of ``x`` over ``[start, start + size)`` along ``dim`` for each of ``starts`` (ascending).

    When the starts are ``0, s, 2s, ...`` with ``s`` dividing ``size`` (the reference grid of an
    image whose sides are multiples of the stride), the windows are sums of ``size / s``
    consecutive ``s``-chunks: one pass over ``x`` instead of window sums at every position.
    ``chunked`` (default: :func:`chunked_windows`) forces the choice; ``True`` needs such starts.
    """
    n = starts.numel()
    step = int(starts[1] - starts[0]) if n > 1 else size
    span = step * (n - 1) + size
    aligned = chunked_windows(size, starts, x.shape[dim]) if chunked is None else chunked
    if not aligned:
        return sliding_window_sum(x, size, dim=dim).index_select(dim, starts)
    chunks = x.narrow(dim, 0, span).unflatten(dim, (span // step, step)).sum(dim + 1)
    out = chunks.narrow(dim, 0, n).clone()
    for q in range(1, size // step):
        out.add_(chunks.narrow(dim, q, n))
    return out


def _channel_dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``sum_c a[c] * b[c]`` of two ``(C, H, W)`` tensors, one multiply and one add per channel in channel order:
    every pixel's number is the same wherever the region starts (a ``sum(0)`` reduction rounds differently with
    the width), so Gram maps of a window equal the whole image's there."""
    out = torch.mul(a[0], b[0])
    tmp = torch.empty_like(out)
    for i in range(1, a.shape[0]):
        out.add_(torch.mul(a[i], b[i], out=tmp))
    return out


def gram_maps(zr: torch.Tensor, block: int, tri_c: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Per-block-position Gram entries of a region ``(C, Hr, W)`` -> ``(Ny*Nx, planes)``.

    Planes: height mode ``(i, i+d)`` for ``i + d < b`` (b(b+1)/2, ordered by ``d`` then ``i``),
    width mode likewise, channel mode ``(c, c')`` for ``c <= c'`` (``tri_c``: ``torch.triu_indices(C, C)``,
    row-major). The box sums are exact pairwise sums (:func:`capssim.reconstruct.filters.sliding_window_sum`) and
    the channel sums run in channel order, so a position's entries do not depend on where the region starts;
    every plane is written once into the position-major result (no stacking and concatenation).
    """
    c, hr, w = zr.shape
    b = block
    ny, nx = hr - b + 1, w - b + 1
    nb = b * (b + 1) // 2
    out = zr.new_empty(ny, nx, 2 * nb + tri_c[0].numel())
    slot = 0
    for d in range(b):  # height mode: G_h[i, i+d] = sum_{j<b, c} z[c, y+i, x+j] z[c, y+i+d, x+j]
        rowbox = sliding_window_sum(_channel_dot(zr[:, :hr - d, :], zr[:, d:, :]), b, dim=1)   # (hr-d, nx)
        out[:, :, slot:slot + b - d] = rowbox.unfold(0, b - d, 1)[:ny]
        slot += b - d
    for d in range(b):  # width mode: G_w[j, j+d] = sum_{i<b, c} z[c, y+i, x+j] z[c, y+i, x+j+d]
        colbox = sliding_window_sum(_channel_dot(zr[:, :, :w - d], zr[:, :, d:]), b, dim=0)    # (ny, W-d)
        out[:, :, slot:slot + b - d] = colbox.unfold(1, b - d, 1)[:, :nx]
        slot += b - d
    zh = zr.permute(1, 2, 0).contiguous()                                                  # (hr, W, C)
    prods = zr.new_empty(hr, w, tri_c[0].numel())                                          # (hr, W, T)
    start = 0
    for i in range(c):  # row i of the upper triangle (tri_c is row-major): channel i times channels i..C-1
        torch.mul(zh[:, :, i:i + 1], zh[:, :, i:], out=prods[:, :, start:start + c - i])
        start += c - i
    out[:, :, slot:] = sliding_window_sum(sliding_window_sum(prods, b, dim=0), b, dim=1)
    return out.view(ny * nx, -1)


def unpack_grams(sums: torch.Tensor, block: int, tri_c: tuple[torch.Tensor, torch.Tensor],
                 channels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Summed Gram entries ``(k, planes)`` -> height+width ``(2k, b, b)`` and channel ``(k, C, C)``."""
    b, k = block, sums.shape[0]
    nb = b * (b + 1) // 2
    pairs = [(i, i + d) for d in range(b) for i in range(b - d)]  # the plane order of gram_maps
    rows = torch.tensor([p[0] for p in pairs], device=sums.device)
    cols = torch.tensor([p[1] for p in pairs], device=sums.device)
    hw = sums.new_zeros(2, k, b, b)
    for mode in range(2):
        vals = sums[:, mode * nb:(mode + 1) * nb]
        hw[mode][:, rows, cols] = vals
        hw[mode][:, cols, rows] = vals
    cc = sums.new_zeros(k, channels, channels)
    iu, ju = tri_c
    cc[:, iu, ju] = sums[:, 2 * nb:]
    cc[:, ju, iu] = sums[:, 2 * nb:]
    return hw.reshape(2 * k, b, b), cc


def orthonormal_bases(gram: torch.Tensor) -> torch.Tensor:
    """Eigenvectors (columns) of a batch of symmetric PSD matrices, scale-normalized (eq. 21)."""
    scale = torch.diagonal(gram, dim1=-2, dim2=-1).sum(-1).clamp(min=1e-30)[:, None, None]
    eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    return torch.linalg.eigh(gram / scale + 1e-7 * eye)[1]


def mode_products(t: torch.Tensor, ph: torch.Tensor, pw: torch.Tensor, pc: torch.Tensor,
                  transpose: bool) -> torch.Tensor:
    """``t x1 Ph x2 Pw x3 Pc`` (or with the transposes) for blocks ``t`` ``(k, b, b, C)``.

    ``t`` may also be ``(k, b, S, b, C)``: ``S`` stacked blocks of each group sharing its bases
    (one batched product for the reference block and ``U`` of eq. 22-23).
    """
    k, b, c = t.shape[0], t.shape[1], t.shape[-1]
    stacked = t.dim() == 5
    s = t.shape[2] if stacked else 1
    if transpose:
        ph, pw = ph.transpose(1, 2), pw.transpose(1, 2)
    else:
        pc = pc.transpose(1, 2)
    # mode 1 (height): out[a, ...] = sum_i Ph[a, i] t[i, ...]
    x = torch.bmm(ph, t.reshape(k, b, -1))                                      # (k, b_a, S*b*C)
    # mode 2 (width): Pw applied to every (a, S) slice in place, broadcast over them (no transposed copies)
    x = torch.matmul(pw[:, None], x.view(k, b * s, b, c))                        # (k, (a, S), b_j', C)
    # mode 3 (channel): out[..., d] = sum_c x[..., c] Pc[c, d]
    x = torch.bmm(x.view(k, b * s * b, c), pc)
    return x.view(k, b, s, b, c) if stacked else x.view(k, b, b, c)


def row_segments(z_pixels: torch.Tensor, block: int) -> torch.Tensor:
    """Overlapping view ``(H*W - b + 1, b*C)`` of ``z_pixels`` ``(H*W, C)``: row ``p`` holds pixels
    ``p .. p+b-1``, so a block is ``b`` gathered rows instead of ``b*b`` gathered pixels."""
    n, c = z_pixels.shape
    return z_pixels.as_strided((n - block + 1, block * c), (c, 1))


def gather_blocks(segments: torch.Tensor, corners: torch.Tensor, row_starts: torch.Tensor) -> torch.Tensor:
    """Blocks ``(k, b, b*C)`` whose top-left pixels have flat indices ``corners`` ``(k,)``.

    ``row_starts`` ``(b,)`` are the flat offsets ``i * W`` of the block's rows; ``segments`` is
    :func:`row_segments`.
    """
    idx = (corners[:, None] + row_starts[None, :]).reshape(-1)
    return segments.index_select(0, idx).view(corners.shape[0], row_starts.shape[0], -1)


def group_matrix(corners: torch.Tensor, weights: torch.Tensor, n_columns: int) -> torch.Tensor:
    """Sparse CSR ``(K, n_columns)`` with row ``k`` holding ``weights[k]`` at the flat block corners
    ``corners[k]`` (both ``(K, P)``; columns sorted within each row, repeats kept and summed by products).
    Indices are ``int32`` where they fit (the sparse products run about 15 % faster than with ``int64``)."""
    k, p = corners.shape
    index_dtype = torch.int32 if max(k * p, n_columns) < 2**31 else torch.int64
    cols, order = torch.sort(corners, dim=1)
    crow = torch.arange(0, k * p + 1, p, dtype=index_dtype, device=corners.device)
    with warnings.catch_warnings():  # torch flags CSR as beta once per process
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, cols.reshape(-1).to(index_dtype), weights.gather(1, order).reshape(-1),
                                       size=(k, n_columns), check_invariants=False)


def weighted_block_sums(z_pixels: torch.Tensor, group_weights: torch.Tensor, block: int, width: int) -> torch.Tensor:
    """``U_k = sum_p w_kp B(pos_kp)`` (eq. 19) of every group, ``(K, b, b, C)``.

    ``group_weights`` is :func:`group_matrix` of the groups' flat corners and weights. Pixel
    ``(i, j)`` of every block is one sparse-dense product with ``z_pixels`` shifted by
    ``i * W + j``: no ``(K, P, b, b, C)`` gather is ever built.
    """
    k, n_cols = group_weights.shape
    u = z_pixels.new_empty(k, block, block, z_pixels.shape[1])
    for i in range(block):
        for j in range(block):
            start = i * width + j
            u[:, i, j] = torch.sparse.mm(group_weights, z_pixels[start:start + n_cols])
    return u


def shrink_core(alpha: torch.Tensor, beta: torch.Tensor, c1: float, c2: float, *, adaptive: str = "element",
                eps: float = 1e-8, terms: bool = True) -> tuple[torch.Tensor, dict]:
    """Eq. 23 with the adaptive ``lambda_k/mu`` and ``eta_k/mu`` of section 4, for cores ``(k, ...)``
    (one group per index of the first axis; ``alpha`` and ``beta`` may be strided views).

    ``C = soft((2 t beta + alpha) / (1 + 2 t), (lambda/mu) / (1 + 2 t))``, ``t = eta/mu``.
    Returns the core and the summed terms ``zeros`` (count of zero coefficients) and, when
    ``terms``, ``l1`` (``lambda/mu |C|``), ``fit`` (``|alpha - C|^2``) and ``nonlocal``
    (``eta/mu |beta - C|^2``).
    """
    if adaptive == "element":
        lam = alpha.abs().add_(eps).reciprocal_().mul_(c1)
        t = (alpha - beta).square_().add_(eps).reciprocal_().mul_(c2)
    elif adaptive == "block":
        dims = tuple(range(1, alpha.dim()))
        lam = (c1 / (alpha.abs().sum(dims, keepdim=True) + eps)).expand_as(alpha)
        t = (c2 / ((alpha - beta).square().sum(dims, keepdim=True) + eps)).expand_as(alpha)
    else:
        raise InputError("adaptive", adaptive, "'element' or 'block'")
    denom = t.mul(2.0).add_(1.0)
    v = torch.addcmul(alpha, t, beta, value=2.0).div_(denom)
    core = torch.sign(v)
    core.mul_(v.abs_().sub_(lam / denom).clamp_(min=0))
    parts = {"zeros": (core == 0).sum().to(alpha.dtype)}
    if terms:
        parts.update({"l1": (lam * core.abs()).sum(), "fit": (alpha - core).square().sum(),
                      "nonlocal": (t * (beta - core).square()).sum()})
    return core, parts


__all__ = ["chunked_windows", "gather_blocks", "gram_maps", "group_matrix", "mode_products", "offset_differences", "orthonormal_bases",
           "principal_channels", "row_segments", "shrink_core", "unpack_grams", "weighted_block_sums", "window_sums_at"]
