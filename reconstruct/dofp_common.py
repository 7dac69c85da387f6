"""Shared helpers of the DoFP colour-polarization demosaicking baselines.

Geometry of the mosaic (README "Conventions", :func:`capssim.conventions.dofp_channel_map`):
the mosaic is ``(H, W)`` at the HR pitch; pixel ``(r, c)`` (row, col) sits behind the polarizer
``layout[r % 2][c % 2]`` and the colour filter ``RGGB[(r // 2) % 2][(c // 2) % 2]`` (quad Bayer,
4x4 period). Hence:

* the pixels with cell offset ``(dr, dc)`` all share one polarizer angle and form a
  half-resolution *sub-mosaic* ``mosaic[dr::2, dc::2]``, shape ``(H/2, W/2)``, which is a plain
  RGGB Bayer image (R at its (0, 0)) whatever the layout;
* sub-mosaic pixel ``(i, j)`` lies at full-resolution position ``(2i + dr, 2j + dc)``: each
  polarization lattice has its own sub-pixel offset, which the interpolation must respect.

Everything here is torch, device-agnostic and vectorized (no loops over pixels); images are
``(..., H, W)`` tensors. Filters are correlations (not convolutions, as MATLAB ``imfilter``),
the kernel centre on the output pixel, mirror-padded (see :func:`correlate`).
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from capssim.conventions import BAYER_RGGB, POLARIZER_ANGLES_DEG, dofp_layout
from capssim.errors import InputError

log = logging.getLogger(__name__)

#: smallest mosaic side the DoFP methods accept (three 4x4 colour-polarization periods; the
#: 9-tap filters of the colour stage mirror-pad its half-resolution sub-mosaics by 4)
MIN_MOSAIC_SIZE = 12

#: bilinear interpolation kernel of a lattice with period 2 in both axes (R/B Bayer sites,
#: one polarizer angle of a 2x2 cell)
KERNEL_BILINEAR_RECT = ((0.25, 0.5, 0.25), (0.5, 1.0, 0.5), (0.25, 0.5, 0.25))
#: bilinear interpolation kernel of a quincunx lattice (Bayer G sites)
KERNEL_BILINEAR_QUINCUNX = ((0.0, 0.25, 0.0), (0.25, 1.0, 0.25), (0.0, 0.25, 0.0))


# -- input checking and conversion ---------------------------------------------------------------
def check_mosaic(mosaic, *, argument: str = "mosaic", device: torch.device | str | None = None,
                 dtype: torch.dtype | None = None) -> torch.Tensor:
    """Validate a DoFP mosaic and return it as a float tensor ``(H, W)``.

    Accepts a numpy array or a torch tensor: 2-D, floating point (raw DN must be converted
    first, e.g. with :meth:`capssim.sensor.Sensor.to_float`), finite, both sides even and at
    least :data:`MIN_MOSAIC_SIZE`. Odd sides are rejected: the 2x2 polarizer cell would be cut
    (``capssim demosaic --trim-odd`` drops the last row/column instead). The tensor is float64
    when the input is float64 (or ``dtype`` says so), else float32.
    """
    if isinstance(mosaic, torch.Tensor):
        t = mosaic
    else:
        arr = np.asarray(mosaic)
        if arr.dtype == object:
            raise InputError(argument, "an object array", "a 2-D float array")
        t = torch.from_numpy(np.ascontiguousarray(arr))
    if t.ndim != 2:
        raise InputError(argument, f"shape {tuple(t.shape)}", "a 2-D mosaic (H, W): one value per pixel",
                         "A colour image is not a raw mosaic; pass the single-channel raw frame.")
    if not (t.is_floating_point()):
        raise InputError(argument, f"dtype {t.dtype}", "a float mosaic on [0, 1] of full scale",
                         "Convert raw DN first (e.g. DN / (2**bits - 1), or Sensor.to_float).")
    h, w = t.shape
    if h % 2 or w % 2:
        raise InputError(argument, f"size {h}x{w}", "an even height and width (whole 2x2 polarizer cells)",
                         "Drop the last row/column (capssim demosaic --trim-odd).")
    if h < MIN_MOSAIC_SIZE or w < MIN_MOSAIC_SIZE:
        raise InputError(argument, f"size {h}x{w}", f"at least {MIN_MOSAIC_SIZE}x{MIN_MOSAIC_SIZE} pixels")
    if dtype is None:
        dtype = torch.float64 if t.dtype == torch.float64 else torch.float32
    t = t.to(device=device if device is not None else t.device, dtype=dtype)
    if not bool(torch.isfinite(t).all()):
        raise InputError(argument, f"{int((~torch.isfinite(t)).sum())} NaN/inf values", "finite values")
    return t


def as_output(image: torch.Tensor, like) -> np.ndarray | torch.Tensor:
    """Return ``image`` as the caller gave its input: a tensor stays a tensor, else float32 numpy."""
    if isinstance(like, torch.Tensor):
        return image
    return image.detach().to("cpu", torch.float32).numpy()


# -- layout ------------------------------------------------------------------------------------
def angle_offsets(layout="sony") -> tuple[tuple[int, int], ...]:
    """Cell offset ``(dr, dc)`` of each polarizer angle, in the order (0, 45, 90, 135) deg."""
    cell = dofp_layout(layout)
    where = {cell[r][c]: (r, c) for r in range(2) for c in range(2)}
    return tuple(where[a] for a in POLARIZER_ANGLES_DEG)


def split_submosaics(mosaic: torch.Tensor, layout="sony") -> torch.Tensor:
    """``(..., H, W)`` -> ``(..., 4, H/2, W/2)``: the RGGB sub-mosaic of each angle (0, 45, 90, 135)."""
    return torch.stack([mosaic[..., dr::2, dc::2] for dr, dc in angle_offsets(layout)], dim=-3)


def merge_submosaics(subs: torch.Tensor, layout="sony") -> torch.Tensor:
    """Inverse of :func:`split_submosaics`: ``(..., 4, h, w)`` -> ``(..., 2h, 2w)``.

    Pixel ``(2i + dr_p, 2j + dc_p)`` takes ``subs[..., p, i, j]``. With a colour axis in
    ``...`` this builds the "RGB polarization mosaic": every pixel carries the colours of its
    own polarizer angle.
    """
    *lead, n, h, w = subs.shape
    if n != 4:
        raise ValueError(f"merge_submosaics: expected 4 sub-mosaics, got {n}")
    out = subs.new_empty((*lead, 2 * h, 2 * w))
    for p, (dr, dc) in enumerate(angle_offsets(layout)):
        out[..., dr::2, dc::2] = subs[..., p, :, :]
    return out


def polarization_masks(height: int, width: int, layout="sony", *, device=None,
                       dtype=torch.float32) -> torch.Tensor:
    """``(4, H, W)``: 1 where polarizer angle p (0, 45, 90, 135) is sampled, else 0."""
    masks = torch.zeros((4, height, width), device=device, dtype=dtype)
    for p, (dr, dc) in enumerate(angle_offsets(layout)):
        masks[p, dr::2, dc::2] = 1
    return masks


def bayer_masks(height: int, width: int, *, device=None, dtype=torch.float32) -> torch.Tensor:
    """``(3, h, w)`` RGGB site masks (R at (0, 0)); channel k is colour k (R, G, B)."""
    rows = torch.arange(height, device=device)[:, None] % 2
    cols = torch.arange(width, device=device)[None, :] % 2
    colour = torch.as_tensor(BAYER_RGGB, device=device)[rows, cols]
    return torch.stack([(colour == k) for k in range(3)]).to(dtype)


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


# -- residual interpolation (shared by dofp-eari and dofp-igri2) ---------------------------------
#: sparse Laplacian over a lattice with period 2 (Kiku et al., MLRI)
KERNEL_LAPLACIAN_STEP2 = ((0, 0, -1, 0, 0), (0, 0, 0, 0, 0), (-1, 0, 4, 0, -1), (0, 0, 0, 0, 0), (0, 0, -1, 0, 0))
#: horizontal sparse Laplacian (directional MLRI of the Bayer green step)
KERNEL_LAPLACIAN_H = ((-1, 0, 2, 0, -1),)


def mlri_tentative(guide: torch.Tensor, samples: torch.Tensor, mask: torch.Tensor, laplacian,
                   *, radius_y: int, radius_x: int, eps: float, weight_floor: float) -> torch.Tensor:
    """Tentative estimate of a sparsely sampled image by MLRI guided filtering (weighted version).

    Kiku, Monno, Tanaka, Okutomi, "Beyond color difference: residual interpolation for color
    image demosaicking", IEEE TIP 25(3), 2016: minimized-Laplacian residual interpolation with
    weighted averaging of the local linear models.

    For each window ``w_k`` (``(2 radius_y + 1) x (2 radius_x + 1)``, truncated at borders), with
    ``L`` the sparse ``laplacian`` and only lattice pixels (``mask`` = 1) counted:

    * slope ``a_k = mean(L(guide m) L(samples m)) / (mean(L(guide m)^2) + eps)``: the slope that
      minimizes the Laplacian energy of the residual (the DC offset cancels in ``L``);
    * offset ``b_k = mean(samples) - a_k mean(guide)`` over the lattice pixels of ``w_k``;
    * fit residual energy ``e_k = mean((a_k guide + b_k - samples)^2)``, weight ``1 / max(e_k, weight_floor)``;
    * ``tentative = abar guide + bbar`` with ``abar, bbar`` the weight-averaged ``a, b`` of all
      windows covering the pixel.

    All tensors ``(..., H, W)``; ``mask`` broadcastable. Returns ``(..., H, W)``.
    """
    mask = mask.to(guide.dtype)  # kept unexpanded: box(mask) is shared by all images it broadcasts to
    g = guide
    s = samples * mask
    lap_g = correlate(g * mask, laplacian)
    lap_s = correlate(s, laplacian)
    def box(x):
        return box_sum(x, radius_y, radius_x)
    count = box(mask).clamp_min(1.0)
    if count.shape != g.shape:
        count = count.expand_as(g)
    sum_g, sum_s = box(g * mask), box(s)
    a = (box(lap_g * lap_s * mask) / count) / (box(lap_g * lap_g * mask) / count + eps)
    b = (sum_s - a * sum_g) / count
    # sum over the window's lattice pixels of (a g + b - s)^2, expanded so a, b stay per window
    energy = (a * a * box(g * g * mask) + b * b * count + box(s * s) + 2 * a * b * sum_g
              - 2 * b * sum_s - 2 * a * box(g * s)) / count
    weight = 1.0 / energy.clamp_min(weight_floor)
    wsum = box(weight).clamp_min(torch.finfo(g.dtype).tiny)
    a_bar = box(a * weight) / wsum
    b_bar = box(b * weight) / wsum
    return a_bar * g + b_bar


def residual_interpolation(guide: torch.Tensor, samples: torch.Tensor, mask: torch.Tensor, *, eps: float,
                           weight_floor: float, clip_max: float, radius: int = 5) -> torch.Tensor:
    """Residual interpolation of a period-2 lattice (both axes) under a full-resolution ``guide``.

    1. tentative estimate by :func:`mlri_tentative` (11x11 windows, step-2 Laplacian), clipped
       to ``[0, clip_max]``;
    2. residual ``samples - tentative`` on the lattice, filled by bilinear interpolation;
    3. output = tentative + interpolated residual (so lattice pixels keep their samples).
    """
    tentative = mlri_tentative(guide, samples, mask, KERNEL_LAPLACIAN_STEP2, radius_y=radius, radius_x=radius,
                               eps=eps, weight_floor=weight_floor).clamp(0.0, clip_max)
    residual = normalized_interpolation(samples - tentative, mask, KERNEL_BILINEAR_RECT)
    return tentative + residual


def polarization_residual_interpolation(guide: torch.Tensor, pol_rgb: torch.Tensor, layout="sony", *,
                                        eps: float, weight_floor: float, clip_max: float) -> torch.Tensor:
    """Fill the four polarizer lattices of every colour plane by :func:`residual_interpolation`.

    ``guide`` ``(3, H, W)``: the full-resolution guide of each colour; ``pol_rgb`` ``(3, H, W)``:
    the colour planes, each sampled on the four polarizer lattices of ``layout``. Returns
    ``(4 [angle], 3 [colour], H, W)``; lattice pixels keep their samples, the rest is clipped
    to ``[0, clip_max]`` (the overshoot of the residual step).
    """
    height, width = pol_rgb.shape[-2:]
    masks = polarization_masks(height, width, layout, device=pol_rgb.device, dtype=pol_rgb.dtype)  # (4, H, W)
    shape = (4, 3, height, width)
    out = residual_interpolation(guide.expand(shape), pol_rgb.expand(shape), masks[:, None], eps=eps,
                                 weight_floor=weight_floor, clip_max=clip_max)
    return torch.where(masks[:, None] > 0, pol_rgb[None], out.clamp(0.0, clip_max))


def gaussian_one_sided(sigma: float, *, taps: int = 5, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalized one-sided Gaussian weights on offsets ``-(taps-1)..0`` and ``0..taps-1``."""
    x = torch.arange(-(taps - 1), taps, dtype=like.dtype, device=like.device)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    left = torch.where(x <= 0, g, torch.zeros_like(g))
    right = torch.where(x >= 0, g, torch.zeros_like(g))
    return left / left.sum(), right / right.sum()


def _directional_green_difference(raw: torch.Tensor, *, eps: float, weight_floor: float,
                                  clip_max: float) -> torch.Tensor:
    """Horizontal colour difference ``G - X`` (X the row's R or B) of RGGB images ``(..., h, w)``.

    Each row of an RGGB image alternates G with one other colour X (R on even rows, B on odd).
    Along the row:

    1. directional guides: ``G`` filled at X sites by the mean of its left/right neighbours,
       and ``X`` filled at G sites likewise;
    2. MLRI tentative estimates (7x7 windows, 1-D Laplacian ``[-1 0 2 0 -1]``) of X from the
       G guide and of G from the X guide, each from its own sites;
    3. residuals at the sites, linearly interpolated to the row neighbours and added back,
       giving G at X sites and X at G sites;
    4. difference ``G - X`` at every pixel.

    Run on the transposed image for the vertical direction (a transposed RGGB is RGGB).
    """
    h, w = raw.shape[-2:]
    masks = bayer_masks(h, w, device=raw.device, dtype=raw.dtype)
    m_r, m_g, m_b = masks[0], masks[1], masks[2]
    even_row = (torch.arange(h, device=raw.device) % 2 == 0).to(raw.dtype)[:, None]
    m_gr, m_gb = m_g * even_row, m_g * (1 - even_row)  # G on R rows, G on B rows
    row_mean = correlate(raw, ((0.5, 0.0, 0.5),))  # mean of left/right neighbours
    guide_g = raw * m_g + row_mean * (m_r + m_b)
    guide_r = raw * m_r + row_mean * m_gr
    guide_b = raw * m_b + row_mean * m_gb
    kw = dict(radius_y=3, radius_x=3, eps=eps, weight_floor=weight_floor)

    def estimate(guide, site_mask, target_mask):
        tentative = mlri_tentative(guide, raw, site_mask, KERNEL_LAPLACIAN_H, **kw).clamp(0.0, clip_max)
        residual = correlate((raw - tentative) * site_mask, ((0.5, 0.0, 0.5),))
        return ((tentative + residual) * target_mask).clamp(0.0, clip_max)

    g_at_r = estimate(guide_r, m_gr, m_r)
    g_at_b = estimate(guide_b, m_gb, m_b)
    r_at_g = estimate(guide_g, m_r, m_gr)
    b_at_g = estimate(guide_g, m_b, m_gb)
    green = raw * m_g + g_at_r + g_at_b
    other = raw * (m_r + m_b) + r_at_g + b_at_g
    return green - other


def ri_green(raw: torch.Tensor, *, eps: float, weight_floor: float, clip_max: float, sigma: float = 1.0,
             direction_floor: float = 1e-2) -> torch.Tensor:
    """Full-resolution green of RGGB images ``(..., h, w)`` by residual interpolation.

    Kiku et al. (TIP 2016) green step, as used by EARI for its colour stage:
    horizontal and vertical colour differences ``G - X`` (:func:`_directional_green_difference`)
    are combined per pixel from four one-sided estimates (north, south, west, east; 5-tap
    one-sided Gaussian averages, ``sigma`` in pixels), each weighted by
    ``1 / (D^2 + direction_floor)`` with ``D`` the 3x3-summed absolute gradient of that colour
    difference at the neighbour on that side (gradient-based threshold-free weighting). Green at
    an X site is ``X + combined difference``; G sites keep their samples.
    """
    dif_h = _directional_green_difference(raw, eps=eps, weight_floor=weight_floor, clip_max=clip_max)
    dif_v = _directional_green_difference(raw.transpose(-1, -2).contiguous(), eps=eps, weight_floor=weight_floor,
                                          clip_max=clip_max).transpose(-1, -2).contiguous()
    grad_h = box_sum(correlate(dif_h, ((1.0, 0.0, -1.0),)).abs(), 1, 1)
    grad_v = box_sum(correlate(dif_v, ((1.0,), (0.0,), (-1.0,))).abs(), 1, 1)
    w_west = 1.0 / (correlate(grad_h, ((1.0, 0.0, 0.0),)) ** 2 + direction_floor)
    w_east = 1.0 / (correlate(grad_h, ((0.0, 0.0, 1.0),)) ** 2 + direction_floor)
    w_north = 1.0 / (correlate(grad_v, ((1.0,), (0.0,), (0.0,))) ** 2 + direction_floor)
    w_south = 1.0 / (correlate(grad_v, ((0.0,), (0.0,), (1.0,))) ** 2 + direction_floor)
    left, right = gaussian_one_sided(sigma, like=raw)
    est_west = correlate(dif_h, left[None, :])
    est_east = correlate(dif_h, right[None, :])
    est_north = correlate(dif_v, left[:, None])
    est_south = correlate(dif_v, right[:, None])
    dif = (w_north * est_north + w_south * est_south + w_west * est_west + w_east * est_east) / (
        w_north + w_south + w_west + w_east)
    m_g = bayer_masks(*raw.shape[-2:], device=raw.device, dtype=raw.dtype)[1]
    return (raw * m_g + (raw + dif) * (1 - m_g)).clamp(0.0, clip_max)


def ri_bayer_demosaic(raw: torch.Tensor, *, eps: float, weight_floor: float, clip_max: float,
                      sigma: float = 1.0) -> torch.Tensor:
    """RGGB ``(..., h, w)`` -> RGB ``(..., 3, h, w)`` by residual interpolation (Kiku et al. TIP 2016).

    Green by :func:`ri_green`; then R and B each by :func:`residual_interpolation` with the
    full green as guide (11x11 MLRI windows, step-2 Laplacian, bilinear residuals), clipped to
    ``[0, clip_max]``.
    """
    h, w = raw.shape[-2:]
    masks = bayer_masks(h, w, device=raw.device, dtype=raw.dtype)
    green = ri_green(raw, eps=eps, weight_floor=weight_floor, clip_max=clip_max, sigma=sigma)
    kw = dict(eps=eps, weight_floor=weight_floor, clip_max=clip_max)
    red = residual_interpolation(green, raw, masks[0], **kw)
    blue = residual_interpolation(green, raw, masks[2], **kw)
    # R/B sites keep their samples exactly (the bilinear residual restores them up to rounding)
    red = torch.where(masks[0] > 0, raw, red.clamp(0.0, clip_max))
    blue = torch.where(masks[2] > 0, raw, blue.clamp(0.0, clip_max))
    return torch.stack([red, green, blue], dim=-3)


def reject_unknown_options(leftover: dict, known: Sequence[str]) -> None:
    """Raise :class:`~capssim.errors.UnknownNameError` when ``leftover`` holds an option not in ``known``."""
    from capssim.errors import UnknownNameError

    for key in leftover:
        raise UnknownNameError("option", str(key), list(known) or ["(this method takes no options)"])


def run_dofp_method(capture, context, demosaic, defaults: dict):
    """The registered-method body shared by the residual-interpolation DoFP methods.

    Reads the options ``precision`` (``float32`` | ``float64``) and the float parameters named
    in ``defaults`` from ``context.options``, demosaicks ``capture.dofp_float()`` with
    ``demosaic(mosaic, *, layout, dtype, timer, **params)`` on ``context.device`` and returns
    the :class:`~reconstruct.registry.MethodOutput` with the parameters used.
    """
    from capssim.reconstruct.registry import MethodOutput

    opts = dict(context.options)
    precision = opts.pop("precision", "float32")
    if precision not in ("float32", "float64"):
        raise InputError("precision", precision, "float32 or float64")
    params = {}
    for key, default in defaults.items():
        raw = opts.pop(key, default)
        try:
            params[key] = float(raw)
        except (TypeError, ValueError):
            raise InputError(key, raw, "a number", f"Pass e.g. -O {key}={default}.") from None
        if not np.isfinite(params[key]):
            raise InputError(key, raw, "a finite number", f"Pass e.g. -O {key}={default}.")
    reject_unknown_options(opts, ["precision", *defaults])
    with context.timer.stage("load"):
        mosaic = torch.from_numpy(capture.dofp_float()).to(context.device)
        n_saturated = int(capture.dofp_saturated().sum())
    image = demosaic(mosaic, layout=capture.dofp_layout, dtype=getattr(torch, precision), timer=context.timer,
                     **params)
    with context.timer.stage("to_host"):
        image = image.to("cpu", torch.float32).numpy()
    return MethodOutput(image=image, params={"layout": [list(r) for r in capture.dofp_layout], "precision": precision,
                                             **params},
                        extra={"n_saturated_pixels": n_saturated,
                               "saturation_handling": "none (interpolation uses saturated samples as they are)"})


def clip_ceiling(mosaic: torch.Tensor) -> float:
    """Upper clip of intermediate estimates: 1 (full scale), or the mosaic maximum if larger."""
    return max(1.0, float(mosaic.max()))


def stack_12(images: Sequence[torch.Tensor] | torch.Tensor) -> torch.Tensor:
    """``(4 [angle], 3 [colour], H, W)`` -> ``(12, H, W)`` in the order ``c = 3*p + k``."""
    x = images if isinstance(images, torch.Tensor) else torch.stack(list(images))
    return x.reshape(12, *x.shape[-2:])


def dofp_array_function(method: str):
    """The plain array function ``fn(mosaic, *, layout, device, timer)`` behind a DoFP method name."""
    from capssim.errors import UnknownNameError

    if method == "dofp-bilinear":
        from capssim.reconstruct.methods.dofp_bilinear import demosaic_dofp_bilinear

        return demosaic_dofp_bilinear
    if method == "dofp-eari":
        from capssim.reconstruct.methods.dofp_eari import demosaic_dofp_eari

        return demosaic_dofp_eari
    if method == "dofp-igri2":
        from capssim.reconstruct.methods.dofp_igri2 import demosaic_dofp_igri2

        return demosaic_dofp_igri2
    raise UnknownNameError("DoFP method", method, ["dofp-bilinear", "dofp-eari", "dofp-igri2"])
