"""Confidence-aware guided filtering (CAGF), paper section 3.2, eq. 12-14.

For a target image ``A`` and a guide ``G``, the guided-filter residual in the window
``w_k`` centred at pixel ``k`` is (eq. 12)::

    r_k = min_{a,b} sum_{i in w_k} ((a G_i + b - A_i)^2 + eps a^2)
        = n_k (var_A - cov_AG^2 / (var_G + eps))        (closed form, a = cov / (var_G + eps))

with window means computed by box filters. The confidence is ``L_k = exp(-r_k / nu)``
(eq. 13), and the confidence between channels k and j is the smaller of the two
directions (eq. 14), i.e. ``exp(-max(r(k|j), r(j|k)) / nu)``.

Choices where the paper is silent:

* the residual is the window *sum* (n_k terms, as eq. 12 writes it), window 9x9 LR
  pixels (``radius=4``, the window of the paper's Fig. 5) and ``eps = 1e-4`` on [0, 1] data;
* the 16 observations are first aligned onto the reference image's grid (image 0,
  0-deg R) with the registration homographies; the two G images of an aperture are
  averaged into their channel's image;
* the confidence of a channel with itself is 1 (the derivative dI^c/dI^c of eq. 16);
* the LR confidence maps are resized to the HR grid by bilinear interpolation at the
  exact position each HR pixel has on the reference grid.

A zero-variance guide gives ``a = 0`` and ``r = n var_A`` (no division by zero).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import InputError

from ..filters import sliding_window_sum

DEFAULT_NU = 0.2
DEFAULT_RADIUS = 4
DEFAULT_EPS = 1e-4


@dataclass(frozen=True)
class CAGFParameters:
    """The CAGF settings: ``nu`` of eq. 13, window radius (LR pixels) and ``eps`` of eq. 12."""

    nu: float = DEFAULT_NU
    radius: int = DEFAULT_RADIUS
    eps: float = DEFAULT_EPS


def box_mean(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over the ``(2r+1)^2`` window of every pixel of ``(..., h, w)``, valid pixels only."""
    if radius <= 0:
        return x.clone()
    # separable exact window sums (about 2 log2(2r+1) passes), not avg_pool2d's (2r+1)^2 taps per pixel
    h, w = x.shape[-2:]
    size = 2 * radius + 1
    padded = F.pad(x.reshape(-1, h, w), (radius, radius, radius, radius))
    sums = sliding_window_sum(sliding_window_sum(padded, size, dim=2), size, dim=1)
    return (sums / window_count(h, w, radius, device=x.device, dtype=x.dtype)).reshape(x.shape)


def window_count(h: int, w: int, radius: int, *, device=None, dtype=torch.float32) -> torch.Tensor:
    """``(h, w)`` number of valid pixels in each window (``(2r+1)^2`` away from the border)."""
    rows = torch.arange(h, device=device)
    cols = torch.arange(w, device=device)
    nr = (torch.clamp(rows + radius, max=h - 1) - torch.clamp(rows - radius, min=0) + 1).to(dtype)
    nc = (torch.clamp(cols + radius, max=w - 1) - torch.clamp(cols - radius, min=0) + 1).to(dtype)
    return nr[:, None] * nc[None, :]


def guided_filter_residual(target: torch.Tensor, guide: torch.Tensor, *, radius: int = DEFAULT_RADIUS,
                           eps: float = DEFAULT_EPS) -> torch.Tensor:
    """Eq. 12: residual ``r`` of the guided filter of ``target`` by ``guide``, both ``(..., h, w)``.

    Returns the window sum of squared residuals plus ``eps a^2`` at the optimal ``a, b``
    (same shape, >= 0).
    """
    if target.shape != guide.shape:
        raise InputError("guide", f"shape {tuple(guide.shape)}", f"the target's shape {tuple(target.shape)}")
    if eps <= 0:
        raise InputError("eps", eps, "a positive regularizer (the guided filter's epsilon)")
    mean_a = box_mean(target, radius)
    mean_g = box_mean(guide, radius)
    var_a = torch.clamp(box_mean(target * target, radius) - mean_a * mean_a, min=0)
    var_g = torch.clamp(box_mean(guide * guide, radius) - mean_g * mean_g, min=0)
    cov = box_mean(target * guide, radius) - mean_a * mean_g
    n = window_count(target.shape[-2], target.shape[-1], radius, device=target.device, dtype=target.dtype)
    return n * torch.clamp(var_a - cov * cov / (var_g + eps), min=0)


def pairwise_confidence(channels: torch.Tensor, *, nu: float = DEFAULT_NU, radius: int = DEFAULT_RADIUS,
                        eps: float = DEFAULT_EPS) -> torch.Tensor:
    """Eq. 13-14 for every pair of the ``C`` aligned channel images ``(C, h, w)``.

    Returns ``L`` ``(C, C, h, w)``, symmetric, in (0, 1], with ``L[k, k] = 1``.
    """
    if channels.ndim != 3:
        raise InputError("channels", f"shape {tuple(channels.shape)}", "(C, h, w) aligned channel images")
    if not nu > 0:
        raise InputError("nu", nu, "a positive number (the Gaussian variance of eq. 13)")
    c, h, w = channels.shape
    if not (eps > 0 and np.isfinite(eps)):
        raise InputError("cagf_eps", eps, "a finite positive number (the guided filter's epsilon, eq. 12)")
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or not 1 <= radius <= max(h, w):
        raise InputError("cagf_radius", radius, f"an integer in [1, {max(h, w)}] (window radius, LR pixels; "
                                                "at most the image's larger side)",
                         "The paper uses 4." if max(h, w) >= 4 else f"Use -p cagf_radius={max(h, w)} (the paper's 4 "
                         f"is past this {h}x{w} image).")
    x = channels
    mean = box_mean(x, radius)                                          # (C, h, w)
    second = box_mean(x[:, None] * x[None, :], radius)                  # (C, C, h, w)
    cov = second - mean[:, None] * mean[None, :]
    var = torch.clamp(torch.diagonal(cov, dim1=0, dim2=1).permute(2, 0, 1), min=0)  # (C, h, w)
    n = window_count(h, w, radius, device=x.device, dtype=x.dtype)
    # residual of target k guided by j: n (var_k - cov_kj^2 / (var_j + eps))
    resid = n * torch.clamp(var[:, None] - cov * cov / (var[None, :] + eps), min=0)
    worst = torch.maximum(resid, resid.transpose(0, 1))                 # min of the two confidences
    conf = torch.exp(-worst / nu)
    eye = torch.eye(c, dtype=torch.bool, device=x.device)[:, :, None, None]
    return torch.where(eye, torch.ones_like(conf), conf)


def _grid_for(homography: np.ndarray, out_hw: tuple[int, int], in_hw: tuple[int, int], device, dtype) -> torch.Tensor:
    """``grid_sample`` grid (align_corners=True) sampling the input at ``homography @ (x, y, 1)``."""
    hout, wout = out_hw
    hin, win = in_hw
    ys, xs = np.meshgrid(np.arange(hout, dtype=np.float64), np.arange(wout, dtype=np.float64), indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    src = np.asarray(homography, dtype=np.float64) @ pts
    den = np.where(np.abs(src[2]) < 1e-12, 1e-12, src[2])
    sx, sy = src[0] / den, src[1] / den
    gx = 2 * sx / max(win - 1, 1) - 1
    gy = 2 * sy / max(hin - 1, 1) - 1
    grid = np.stack([gx, gy], axis=-1).reshape(1, hout, wout, 2)
    return torch.as_tensor(grid, dtype=dtype, device=device)


def align_to_reference(images: torch.Tensor, homographies, *, reference: int = 0,
                       weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp ``(N, h, w)`` images onto image ``reference``'s pixel grid.

    ``homographies`` ``(N, 3, 3)`` map the HR reference frame to each image's pixel
    coordinates (x=col, y=row). Returns the aligned images and their weights (0 where a
    sample falls outside its image or on a zero-weight pixel).
    """
    hm = np.asarray(homographies, dtype=np.float64)
    n, h, w = images.shape
    if hm.shape != (n, 3, 3):
        raise InputError("homographies", f"shape {hm.shape}", f"({n}, 3, 3)")
    ref_inv = np.linalg.inv(hm[reference])
    out, wts = [], []
    ones = torch.ones(1, 1, h, w, dtype=images.dtype, device=images.device)
    for m in range(n):  # 16 small warps, not a per-pixel loop
        grid = _grid_for(hm[m] @ ref_inv, (h, w), (h, w), images.device, images.dtype)
        out.append(F.grid_sample(images[m][None, None], grid, mode="bilinear", padding_mode="border", align_corners=True)[0, 0])
        src_w = ones if weights is None else weights[m][None, None]
        inside = (grid.abs() <= 1 + 1e-6).all(dim=-1)[0].to(images.dtype)
        sampled = F.grid_sample(src_w, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[0, 0]
        wts.append(inside * (sampled > 0.999).to(images.dtype))
    return torch.stack(out), torch.stack(wts)


def channel_images(aligned: torch.Tensor, aligned_weights: torch.Tensor, channel_of: torch.Tensor,
                   n_channels: int) -> torch.Tensor:
    """``(C, h, w)``: per channel, the weighted mean of its aligned observations."""
    h, w = aligned.shape[-2:]
    num = aligned.new_zeros(n_channels, h, w).index_add_(0, channel_of, aligned * aligned_weights)
    den = aligned.new_zeros(n_channels, h, w).index_add_(0, channel_of, aligned_weights)
    plain = aligned.new_zeros(n_channels, h, w).index_add_(0, channel_of, aligned)
    cnt = torch.bincount(channel_of, minlength=n_channels).to(aligned.dtype).clamp(min=1)[:, None, None]
    return torch.where(den > 0, num / den.clamp(min=1e-12), plain / cnt)


def aligned_channel_images(images: torch.Tensor, homographies, channel_of: torch.Tensor, n_channels: int, *,
                           weights: torch.Tensor | None = None, reference: int = 0) -> torch.Tensor:
    """``(C, h, w)``: the observations ``images`` ``(N, h, w)`` aligned onto image ``reference``'s grid
    (:func:`align_to_reference`) and averaged per channel (:func:`channel_images`); the channel images CAGF's
    confidence, the analyzers' agreement and the Stokes-consistency test read."""
    aligned, aligned_weights = align_to_reference(images, homographies, reference=reference, weights=weights)
    return channel_images(aligned, aligned_weights, channel_of, n_channels)


def resize_to_hr(maps: torch.Tensor, reference_homography, hr_shape: tuple[int, int]) -> torch.Tensor:
    """Bilinear resize of ``(..., h, w)`` maps on the reference grid to the HR grid ``(..., H, W)``.

    HR pixel ``(x, y)`` reads the maps at ``reference_homography @ (x, y, 1)``.
    """
    lead = maps.shape[:-2]
    h, w = maps.shape[-2:]
    grid = _grid_for(np.asarray(reference_homography), tuple(hr_shape), (h, w), maps.device, maps.dtype)
    flat = maps.reshape(1, -1, h, w)
    out = F.grid_sample(flat, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(*lead, *hr_shape)


def cagf_confidence(images: torch.Tensor, homographies, channel_of: torch.Tensor, n_channels: int,
                    hr_shape: tuple[int, int], *, weights: torch.Tensor | None = None, nu: float = DEFAULT_NU,
                    radius: int = DEFAULT_RADIUS, eps: float = DEFAULT_EPS, reference: int = 0) -> torch.Tensor:
    """The HR confidence ``L^H`` ``(C, C, H, W)`` between all channel pairs (eq. 12-14, 16).

    ``images`` ``(N, h, w)`` are the observations, ``homographies`` ``(N, 3, 3)`` map the HR
    reference frame to each observation's pixels, ``channel_of`` ``(N,)`` gives each
    observation's channel.
    """
    chans = aligned_channel_images(images, homographies, channel_of, n_channels, weights=weights, reference=reference)
    conf_lr = pairwise_confidence(chans, nu=nu, radius=radius, eps=eps)
    return resize_to_hr(conf_lr, np.asarray(homographies)[reference], hr_shape)


__all__ = ["CAGFParameters", "align_to_reference", "aligned_channel_images", "box_mean", "cagf_confidence",
           "channel_images", "guided_filter_residual", "pairwise_confidence", "resize_to_hr", "window_count"]
