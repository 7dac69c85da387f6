"""Image filters shared by the demosaicking baselines, the registration and NLSTR.

Correlations (not convolutions, as MATLAB ``imfilter``) with the kernel centre on the output
pixel and mirror padding; exact sliding-window sums by pairwise doubling. Everything is torch,
device-agnostic and vectorized; images are ``(..., H, W)`` tensors.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from capssim.errors import InputError


# -- filtering primitives ----------------------------------------------------------------------
def _as_kernel(kernel, like: torch.Tensor) -> torch.Tensor:
    k = torch.as_tensor(kernel, dtype=like.dtype, device=like.device)
    if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
        raise ValueError(f"kernel must be 2-D with odd sides, got shape {tuple(k.shape)}")
    return k


def mirror_index(n: int, pad: int, device=None) -> torch.Tensor:
    """Indices of a length-``n`` axis mirrored by ``pad`` on each side (``x[-k] = x[k]``, repeated as
    often as needed, so any ``pad`` works on any ``n >= 1``; an even ``pad`` keeps a Bayer phase)."""
    i = torch.arange(-pad, n + pad, device=device)
    if n == 1:
        return torch.zeros_like(i)
    period = 2 * (n - 1)
    i = i.remainder(period)
    return torch.where(i >= n, period - i, i)


def correlate(image: torch.Tensor, kernel, *, padding: str = "reflect") -> torch.Tensor:
    """2-D correlation of every ``(H, W)`` slice of ``image`` with ``kernel``.

    ``padding``: ``'reflect'`` (mirror about the edge pixel, ``x[-k] = x[k]``), ``'replicate'`` or
    ``'zeros'``. Mirroring keeps every period-2 lattice on itself (``-k`` and ``k`` have the same
    parity), so a padded mosaic is still a valid mosaic of the same layout; the reference MATLAB
    code pads by replication, which mixes lattices in the outermost pixels. Computed
    as a weighted sum of shifted views over the kernel's non-zero taps: the kernels here are small
    and sparse, and on CPU this is several times faster than ``conv2d`` with one channel.
    """
    k = _as_kernel(kernel, image)
    kh, kw = k.shape
    h, w = image.shape[-2:]
    lead = image.shape[:-2]
    x = image.reshape(-1, 1, h, w)
    pad = (kw // 2, kw // 2, kh // 2, kh // 2)
    if padding in ("reflect", "replicate"):
        x = F.pad(x, pad, mode=padding)
    elif padding == "zeros":
        x = F.pad(x, pad)
    else:
        raise ValueError(f"padding must be 'reflect', 'replicate' or 'zeros', got {padding!r}")
    x = x[:, 0]
    out = None
    for (i, j), v in zip(torch.nonzero(k).tolist(), k[k != 0].tolist()):
        view = x[:, i:i + h, j:j + w]
        out = view * v if out is None else out.add_(view, alpha=v)
    if out is None:
        out = image.new_zeros((x.shape[0], h, w))
    return out.reshape(*lead, h, w)


def gaussian_kernel(sigma: float, *, like: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The normalised 1-D Gaussian of standard deviation ``sigma`` (pixels) on ``-r..r``, and ``r = ceil(3 sigma)``."""
    radius = max(1, int(math.ceil(3 * sigma)))
    t = torch.arange(-radius, radius + 1, dtype=like.dtype, device=like.device)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    return k / k.sum(), radius


def gaussian_blur(image: torch.Tensor, sigma: float, *, padding: str = "zeros") -> torch.Tensor:
    """Separable Gaussian blur of every ``(H, W)`` slice of ``image`` (``sigma`` in pixels; 0: a copy).

    ``padding`` as :func:`correlate` (``'zeros'`` for normalized convolution, ``'replicate'``
    for images). Two 1-D passes of :func:`correlate`: on CPU several times faster than a
    grouped ``conv2d`` and the same float32 values.
    """
    if sigma <= 0:
        return image.clone()
    k, _ = gaussian_kernel(sigma, like=image)
    return correlate(correlate(image, k[None, :], padding=padding), k[:, None], padding=padding)


def sliding_window_sum(x: torch.Tensor, size: int, *, dim: int) -> torch.Tensor:
    """Sums of ``size`` consecutive entries along ``dim`` ("valid": length ``n - size + 1``).

    Exact pairwise doubling (window sums of length 1, 2, 4, ... combined by the binary
    digits of ``size``): about log2(size) full-array additions, no long running sums.
    Always a new tensor.
    """
    out_len = x.shape[dim] - size + 1
    if size < 1 or out_len < 1:
        raise InputError("size", size, f"an integer in [1, {x.shape[dim]}] (the length along dim {dim})")
    if size == 1:
        return x.clone()
    cur, length, pos, remaining, result = x, 1, 0, int(size), None
    while remaining:
        if remaining & 1:
            part = cur.narrow(dim, pos, out_len)
            result = part if result is None else result + part
            pos += length
        remaining >>= 1
        if remaining:
            m = cur.shape[dim] - length
            cur = cur.narrow(dim, 0, m) + cur.narrow(dim, length, m)
            length *= 2
    return result


def _window_sum(x: torch.Tensor, radius: int, dim: int) -> torch.Tensor:
    """Sum over ``2 radius + 1`` consecutive samples along ``dim`` (-1 or -2), zero outside."""
    part = F.pad(x, (radius, radius) if dim == -1 else (0, 0, radius, radius))
    return sliding_window_sum(part, 2 * radius + 1, dim=dim)


def box_sum(image: torch.Tensor, radius_y: int, radius_x: int) -> torch.Tensor:
    """Sum over the ``(2 radius_y + 1) x (2 radius_x + 1)`` window, truncated at the borders."""
    x = image
    if radius_x > 0:
        x = _window_sum(x, radius_x, -1)
    if radius_y > 0:
        x = _window_sum(x, radius_y, -2)
    return x if x is not image else image.clone()


def normalized_interpolation(samples: torch.Tensor, mask: torch.Tensor, kernel) -> torch.Tensor:
    """Fill a sampled lattice by normalized convolution: ``K*(m x) / K*m`` (zero padding).

    ``samples`` ``(..., H, W)`` (values off the lattice are ignored), ``mask`` broadcastable to it
    (1 on the lattice). With the bilinear kernels above this is bilinear interpolation: in the
    interior the kernel weights that fall on the lattice sum to 1, so it equals plain
    ``K*(m x)``; at the borders it averages the samples that exist instead of mixing in padding.
    Values on the lattice are kept exactly (the kernels put weight 1 on the centre and no weight
    on other lattice points within reach).
    """
    mask = mask.to(samples.dtype)
    num = correlate(samples * mask, kernel, padding="zeros")
    den = correlate(mask, kernel, padding="zeros")  # broadcasts: computed once per distinct mask
    return num / den.clamp_min(torch.finfo(samples.dtype).tiny)


def gaussian_one_sided(sigma: float, *, taps: int = 5, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalized one-sided Gaussian weights on offsets ``-(taps-1)..0`` and ``0..taps-1``."""
    x = torch.arange(-(taps - 1), taps, dtype=like.dtype, device=like.device)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    left = torch.where(x <= 0, g, torch.zeros_like(g))
    right = torch.where(x >= 0, g, torch.zeros_like(g))
    return left / left.sum(), right / right.sum()
