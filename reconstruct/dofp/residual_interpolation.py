"""Residual interpolation (RI) for Bayer and polarization demosaicking.

The colour stage of EARI (Morimatsu et al., ICIP 2020), after Kiku, Monno, Tanaka, Okutomi,
'Beyond color difference: residual interpolation for color image demosaicking', IEEE TIP 25(3)
2016 (minimized-Laplacian RI, MLRI): a tentative estimate by a guided linear model fitted on
Laplacians, then interpolation of the residual. Used by ``dofp-eari`` / ``dofp-igri2``, by the
paper's ICCP cascade (``caps-iccp``, Bayer demosaicking of [15]) and by the registration's
demosaicked luminance.
"""

from __future__ import annotations

import torch

from ..filters import box_sum, correlate, gaussian_one_sided, mirror_index, normalized_interpolation
from .mosaic import KERNEL_BILINEAR_RECT, bayer_masks, polarization_masks

#: the colour-stage settings of EARI (``dofp-eari``'s defaults), used wherever capssim demosaicks
#: a Bayer frame by RI: ``eps`` and ``weight_floor`` regularize the MLRI fits, ``bayer_sigma`` (px)
#: is the Gaussian weighting of the directional green estimates
RI_BAYER_DEFAULTS = {"eps": 1e-10, "weight_floor": 0.01 / 255 ** 2, "bayer_sigma": 1.0}


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


#: mirror padding (pixels, even: keeps the Bayer phase) of :func:`ri_bayer_demosaic_frames`
RI_FRAME_PAD = 6


def ri_bayer_demosaic_frames(raw: torch.Tensor) -> torch.Tensor:
    """RGGB frames ``(..., H, W)`` of any size >= 1 -> RGB ``(..., 3, H, W)``: the colour stage of EARI
    (:func:`ri_bayer_demosaic` with :data:`RI_BAYER_DEFAULTS`), on frames mirror-padded by
    :data:`RI_FRAME_PAD` pixels (the 11x11 MLRI windows need >= 12 px), clipped to ``[0, max(1, max(raw))]``.

    Used by ``caps-iccp`` / ``caps-naive`` (``bayer_method=ri``) and the registration's ``ri-binomial`` image.
    """
    h, w = raw.shape[-2:]
    iy, ix = mirror_index(h, RI_FRAME_PAD, raw.device), mirror_index(w, RI_FRAME_PAD, raw.device)
    padded = raw[..., iy, :][..., ix]
    rgb = ri_bayer_demosaic(padded, eps=RI_BAYER_DEFAULTS["eps"], weight_floor=RI_BAYER_DEFAULTS["weight_floor"],
                            clip_max=max(1.0, float(raw.max())), sigma=RI_BAYER_DEFAULTS["bayer_sigma"])
    return rgb[..., RI_FRAME_PAD:RI_FRAME_PAD + h, RI_FRAME_PAD:RI_FRAME_PAD + w]


# -- residual interpolation (shared by dofp-eari and dofp-igri2) ---------------------------------
#: sparse Laplacian over a lattice with period 2 (Kiku et al., MLRI)
KERNEL_LAPLACIAN_STEP2 = ((0, 0, -1, 0, 0), (0, 0, 0, 0, 0), (-1, 0, 4, 0, -1), (0, 0, 0, 0, 0), (0, 0, -1, 0, 0))
