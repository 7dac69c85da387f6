"""Bayer demosaicking by directional filtering and a posteriori decision (DDFAPD), batched in torch.

Reference: D. Menon, S. Andriani, G. Calvagno, "Demosaicing with directional filtering and a posteriori
decision", IEEE Transactions on Image Processing 16(1):132-141, 2007. The steps and their constants follow the
paper as colour-demosaicing implements it (``demosaicing_CFA_Bayer_Menon2007``, with its refining step), whose
output this module reproduces to float64 rounding (``tests/reconstruction/test_menon2007.py``) on any
``(N, H, W)`` stack of RGGB frames, on the device of its input, without importing colour-science (about 0.6-1 s of
every process that used to demosaic through it):

1. **Green** (paper section II): at red and blue sites, a horizontal and a vertical estimate
   ``G_H = h_0 * x + h_1 * x`` with ``h_0 = (0, 1/2, 0, 1/2, 0)`` and ``h_1 = (-1/4, 0, 1/2, 0, -1/4)``
   (bilinear green plus the Laplacian of the site's own colour).
2. **Decision** (section III): the colour differences ``C = x - G`` at red and blue sites, their gradients two
   pixels apart ``D_H = |C_H(i, j) - C_H(i, j + 2)|`` (``D_V`` likewise down the column), summed over a 5x5
   neighbourhood weighted by ``k`` (the paper's classifier, 3 on the pixel's own row); the direction with the
   smaller sum wins (``M = 1``: horizontal, where ``d_V >= d_H``).
3. **Red and blue** (section IV): bilinear interpolation of the colour differences with green (at green sites
   along the row or column that holds the colour; at blue (red) sites along the chosen direction).
4. **Refining** (section V): the colour differences smoothed by a 3-tap mean along the chosen direction, and
   green, then red and blue, corrected from them.

Borders: 1-D filters mirror about the edge sample (``x[-k] = x[k]``, repeated as often as needed); the
classifier pads with zeros. Shapes: ``(N, H, W)`` in, ``(N, 3, H, W)`` out, the input's dtype (float64 for the
reproduction; float32 runs the same steps).
"""

from __future__ import annotations

import torch

from capssim.errors import InputError

from ..filters import mirror_index

__all__ = ["CLASSIFIER", "menon2007_demosaic"]

#: the decision's 5x5 classifier weights for the horizontal gradients (its transpose for the vertical ones);
#: applied by convolution (``scipy.ndimage.convolve`` orientation), zero outside the frame
CLASSIFIER = ((0.0, 0.0, 1.0, 0.0, 1.0),
              (0.0, 0.0, 0.0, 1.0, 0.0),
              (0.0, 0.0, 3.0, 0.0, 3.0),
              (0.0, 0.0, 0.0, 1.0, 0.0),
              (0.0, 0.0, 1.0, 0.0, 1.0))
#: symmetric 1-D filters as (centre, offset 1, offset 2, ...): the green estimate's ``h_0`` (bilinear) and ``h_1``
#: (the Laplacian of the site's own colour), the red/blue step's mean of the two neighbours, the refining mean of three
H0 = (0.0, 0.5, 0.0)
H1 = (0.5, 0.0, -0.25)
HALVES = (0.0, 0.5)
THIRDS = (1.0 / 3.0, 1.0 / 3.0)


def _symmetric_filter(x: torch.Tensor, taps: tuple[float, ...], dim: int) -> torch.Tensor:
    """``x`` filtered along ``dim`` (-1: rows, -2: columns) by the symmetric ``taps`` (centre first, then the
    offsets 1, 2, ...), mirrored at the borders; summed as ``c x_i + sum_k (x_{i-k} + x_{i+k}) t_k`` from the
    farthest pair in, the order that reproduces the reference to the last bit."""
    radius = len(taps) - 1
    n = x.shape[dim]
    padded = x.index_select(dim, mirror_index(n, radius, device=x.device))
    out = x * taps[0]
    for k in range(radius, 0, -1):
        left = padded.narrow(dim, radius - k, n)
        right = padded.narrow(dim, radius + k, n)
        out = out + (left + right) * taps[k]
    return out


def _classify(gradient: torch.Tensor, weights: tuple[tuple[float, ...], ...]) -> torch.Tensor:
    """The 2-D convolution of ``gradient`` ``(N, H, W)`` with ``weights`` (5x5), zero padding; the taps summed in
    the raster order of the flipped kernel, each product rounded before it is added (not
    :func:`capssim.reconstruct.filters.correlate`, whose fused ``add_(alpha=)`` rounds once: it flips the
    direction decision at rare near-ties, about 2e-5 of the pixels of 8-bit frames, and the reproduction is lost)."""
    size = len(weights)
    radius = size // 2
    h, w = gradient.shape[-2:]
    padded = torch.nn.functional.pad(gradient, (radius, radius, radius, radius))
    out = torch.zeros_like(gradient)
    for a in range(size):
        for b in range(size):
            weight = weights[size - 1 - a][size - 1 - b]
            if weight:
                out = out + padded[:, a:a + h, b:b + w] * weight
    return out


def _rows(x, taps):
    return _symmetric_filter(x, taps, -1)


def _cols(x, taps):
    return _symmetric_filter(x, taps, -2)


def _directional_green(x, green_site):
    """Step 1: the horizontal and vertical green estimates (the samples themselves at green sites)."""
    g_h = torch.where(green_site, x, _rows(x, H0) + _rows(x, H1))
    g_v = torch.where(green_site, x, _cols(x, H0) + _cols(x, H1))
    return g_h, g_v


def _horizontal_wins(x, g_h, g_v, red_site, blue_site):
    """Step 2: ``M``, true where the horizontal green estimate is kept (``d_V >= d_H``)."""
    chroma = red_site | blue_site
    c_h = torch.where(chroma, x - g_h, torch.zeros_like(x))
    c_v = torch.where(chroma, x - g_v, torch.zeros_like(x))
    h, w = x.shape[-2:]
    shifted_h = c_h.index_select(-1, mirror_index(w, 2, device=x.device)[4:])
    shifted_v = c_v.index_select(-2, mirror_index(h, 2, device=x.device)[4:])
    d_h = _classify((c_h - shifted_h).abs(), CLASSIFIER)
    transposed = tuple(zip(*CLASSIFIER))
    d_v = _classify((c_v - shifted_v).abs(), transposed)
    return d_v >= d_h


def _red_blue(x, green, horizontal, masks):
    """Step 3: red and blue at every site from their differences with the chosen green."""
    red_site, green_site, blue_site, red_row, blue_row = masks
    red = torch.where(red_site, x, torch.zeros_like(x))
    blue = torch.where(blue_site, x, torch.zeros_like(x))
    red = torch.where(green_site & red_row, green + _rows(red, HALVES) - _rows(green, HALVES), red)
    red = torch.where(green_site & blue_row, green + _cols(red, HALVES) - _cols(green, HALVES), red)
    blue = torch.where(green_site & blue_row, green + _rows(blue, HALVES) - _rows(green, HALVES), blue)
    blue = torch.where(green_site & red_row, green + _cols(blue, HALVES) - _cols(green, HALVES), blue)
    red = torch.where(blue_row & blue_site,
                      torch.where(horizontal, blue + _rows(red, HALVES) - _rows(blue, HALVES),
                                  blue + _cols(red, HALVES) - _cols(blue, HALVES)), red)
    blue = torch.where(red_row & red_site,
                       torch.where(horizontal, red + _rows(blue, HALVES) - _rows(red, HALVES),
                                   red + _cols(blue, HALVES) - _cols(red, HALVES)), blue)
    return red, blue


def _along(x, horizontal, taps):
    return torch.where(horizontal, _rows(x, taps), _cols(x, taps))


def _refine(red, green, blue, horizontal, masks, columns):
    """Step 4: the refining step (green, then red and blue at green sites, then red (blue) at blue (red) sites)."""
    red_site, green_site, blue_site, red_row, blue_row = masks
    red_col, blue_col = columns
    red_green = _along(red - green, horizontal, THIRDS)
    blue_green = _along(blue - green, horizontal, THIRDS)
    green = torch.where(red_site, red - red_green, torch.where(blue_site, blue - blue_green, green))
    red_diff, blue_diff = red - green, blue - green
    red = torch.where(green_site & blue_row, green + _cols(red_diff, HALVES), red)
    red = torch.where(green_site & blue_col, green + _rows(red_diff, HALVES), red)
    blue = torch.where(green_site & red_row, green + _cols(blue_diff, HALVES), blue)
    blue = torch.where(green_site & red_col, green + _rows(blue_diff, HALVES), blue)
    red_blue = _along(red - blue, horizontal, THIRDS)
    red = torch.where(blue_site, blue + red_blue, red)
    blue = torch.where(red_site, red - red_blue, blue)
    return red, green, blue


def menon2007_demosaic(raw: torch.Tensor, *, refine: bool = True) -> torch.Tensor:
    """``raw`` ``(N, H, W)`` RGGB frames (red at row 0, column 0) -> ``(N, 3, H, W)`` RGB by DDFAPD (Menon et al.
    2007, module docstring), unclipped, in ``raw``'s dtype and on its device; ``refine=False`` skips step 4."""
    x = torch.as_tensor(raw)
    if x.ndim != 3 or x.shape[-1] < 1 or x.shape[-2] < 1:
        raise InputError("raw", f"shape {tuple(x.shape)}", "(N, H, W) RGGB frames with H, W >= 1",
                         "Stack the frames along a first axis, e.g. raw[None] for one frame.")
    if not x.is_floating_point():
        x = x.to(torch.float64)
    h, w = x.shape[-2:]
    rows = torch.arange(h, device=x.device)[:, None] % 2
    cols = torch.arange(w, device=x.device)[None, :] % 2
    red_site = (rows == 0) & (cols == 0)
    blue_site = (rows == 1) & (cols == 1)
    green_site = ~(red_site | blue_site)
    red_row, blue_row = red_site.any(1, keepdim=True), blue_site.any(1, keepdim=True)
    red_col, blue_col = red_site.any(0, keepdim=True), blue_site.any(0, keepdim=True)
    g_h, g_v = _directional_green(x, green_site)
    horizontal = _horizontal_wins(x, g_h, g_v, red_site, blue_site)
    green = torch.where(horizontal, g_h, g_v)
    del g_h, g_v
    masks = (red_site, green_site, blue_site, red_row, blue_row)
    red, blue = _red_blue(x, green, horizontal, masks)
    if refine:
        red, green, blue = _refine(red, green, blue, horizontal, masks, (red_col, blue_col))
    return torch.stack([red, green, blue], dim=1)
