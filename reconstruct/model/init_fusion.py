"""Initial estimate: fuse all observations onto the HR grid (the paper's SCSR step, Fig. 3).

The paper initializes ADMM with SCSR (Huang et al., spectral-clustering super-resolution
for multispectral camera arrays): all observed bands are resampled onto one HR grid and
high frequencies are shared between bands through per-cluster linear relations between
them. This module is a local-window variant of that idea, built from normalized
convolution (scattered-data interpolation) and a guided-filter style linear model:

1. Every observation pixel is placed at its true position on the HR reference grid
   (the inverse of its homography applied to its pixel centre) and splatted there
   bilinearly, with its data weight (0 for saturated pixels).
2. Per channel, normalized convolution with a Gaussian of ``sigma_channel`` HR pixels
   gives a smooth but alias-free estimate ``T_c`` from that channel's own samples, and a
   wider one (``sigma_lowpass``) gives its low-pass ``B_c``.
3. A full-density "pan" image fuses *all* samples of all channels: each sample keeps its
   own detail ``y - B_c(p)``, rescaled by the local gain ``B_pan / B_c`` to the common
   level ``B_pan`` (the mean of the channels' low-passes). With 16 observations at
   distinct sub-pixel phases the pan has about one sample per HR pixel, so it resolves
   detail that no single channel samples (the aliasing the camera array disentangles).
4. Each channel takes the pan's detail through a local linear model:
   ``x_c = T_c + a_c (pan - P_c)``, where ``P_c`` is the pan resampled exactly like
   ``T_c`` (same positions, same kernel) and ``a_c = cov(T_c, P_c) / (var(P_c) + eps)``
   over a ``(2 r + 1)^2`` window (a guided-filter slope; it is ~0 where the channel does
   not share the pan's texture, the role SCSR's clustering plays).

Differences to SCSR: local windows instead of global spectral clusters; no iterative
reconstruction inside the initialization. Its own accuracy is reported by
``capssim.reconstruct.methods.caps`` (``init_psnr_db`` in the JSON record, when ground
truth is given).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import InputError

from ..filters import gaussian_blur, gaussian_kernel
from .cagf import box_mean
from .rearrange import Observations


def sample_positions(homographies, lr_shape: tuple[int, int]) -> np.ndarray:
    """``(N, h, w, 2)`` HR reference ``(x, y)`` of each observation pixel centre."""
    hm = np.asarray(homographies, dtype=np.float64)
    h, w = lr_shape
    ys, xs = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    src = np.linalg.inv(hm) @ pts  # (N, 3, hw)
    den = np.where(np.abs(src[:, 2]) < 1e-12, 1e-12, src[:, 2])
    out = np.stack([src[:, 0] / den, src[:, 1] / den], axis=-1)
    return out.reshape(hm.shape[0], h, w, 2)


def splat(values: torch.Tensor, positions: torch.Tensor, target: torch.Tensor, n_planes: int,
          hr_shape: tuple[int, int]) -> torch.Tensor:
    """Bilinear splat of ``values`` ``(N, h, w)`` at ``positions`` ``(N, h, w, 2)`` (x, y)
    into plane ``target[n]`` of a ``(n_planes, H, W)`` grid. Samples outside are dropped."""
    hh, ww = hr_shape
    x = positions[..., 0].reshape(-1)
    y = positions[..., 1].reshape(-1)
    plane = target[:, None, None].expand_as(values).reshape(-1)
    v = values.reshape(-1)
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    out = values.new_zeros(n_planes * hh * ww)
    for dy, dx, wt in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        xi, yi = x0 + dx, y0 + dy
        ok = (xi >= 0) & (xi < ww) & (yi >= 0) & (yi < hh)
        idx = (plane * hh + yi.clamp(0, hh - 1)) * ww + xi.clamp(0, ww - 1)
        out.index_add_(0, idx, torch.where(ok, v * wt, torch.zeros_like(v)))
    return out.reshape(n_planes, hh, ww)


def _gaussian_blur_at(x: torch.Tensor, pixels: torch.Tensor, sigma: float) -> torch.Tensor | None:
    """:func:`gaussian_blur` of ``x`` ``(P, H, W)`` at ``pixels`` ``(N, 2)`` (row, col) only: ``(P, N)``.

    The pixels of each quadrant of the image are blurred in their bounding box grown by the kernel's radius
    (clipped to the image, whose zero padding is the blur's own): the same numbers as blurring the whole image,
    at the cost of the boxes. Holes are usually a few clusters (corners the warps leave unseen, saturated spots).
    None when the boxes would cover more than the image (then blur the image)."""
    _, radius = gaussian_kernel(sigma, like=x)
    hh, ww = x.shape[-2:]
    out = x.new_empty(x.shape[0], pixels.shape[0])
    quadrant = (pixels[:, 0] >= hh // 2).long() * 2 + (pixels[:, 1] >= ww // 2).long()
    boxes, area = [], 0
    for q in range(4):
        index = (quadrant == q).nonzero()[:, 0]
        if index.numel() == 0:
            continue
        rows, cols = pixels[index, 0], pixels[index, 1]
        top, left = max(0, int(rows.min()) - radius), max(0, int(cols.min()) - radius)
        bottom, right = min(hh, int(rows.max()) + radius + 1), min(ww, int(cols.max()) + radius + 1)
        boxes.append((index, rows - top, cols - left, (top, bottom, left, right)))
        area += (bottom - top) * (right - left)
    if area > hh * ww:
        return None
    for index, rows, cols, (top, bottom, left, right) in boxes:
        out[:, index] = gaussian_blur(x[:, top:bottom, left:right], sigma)[:, rows, cols]
    return out


def normalized_convolution(num: torch.Tensor, den: torch.Tensor, sigma: float, *, min_density: float = 1e-3,
                           max_doublings: int = 6) -> torch.Tensor:
    """Scattered-data interpolation ``blur(num) / blur(den)``; where the local density of
    samples is below ``min_density`` (holes from saturation or image borders) the kernel
    is doubled until it is not. The doubled kernels are evaluated at the pixels still missing
    only (a few border pixels, usually), unless those are too many."""
    shape = num.shape
    num, den = num.reshape(-1, *shape[-2:]), den.reshape(-1, *shape[-2:])
    bn, bd = gaussian_blur(num, sigma), gaussian_blur(den, sigma)
    ok = bd > min_density
    out = torch.where(ok, bn / bd.clamp(min=1e-12), torch.zeros_like(bn))
    missing = ~ok
    s = sigma
    for _ in range(max_doublings):
        if not bool(missing.any()):
            break
        s *= 2
        pixels = missing.any(0).nonzero()                                             # (N, 2)
        at = (slice(None), pixels[:, 0], pixels[:, 1])                                # their (P, N) values
        bn_at, bd_at = _gaussian_blur_at(num, pixels, s), _gaussian_blur_at(den, pixels, s)
        if bn_at is None:  # too many: the whole image at once
            bn_at, bd_at = gaussian_blur(num, s)[at], gaussian_blur(den, s)[at]
        still, ok_at = missing[at], bd_at > min_density
        out[at] = torch.where(still & ok_at, bn_at / bd_at.clamp(min=1e-12), out[at])
        missing[at] = still & ~ok_at
    if bool(missing.any()):
        # no sample at all in a whole plane (every pixel saturated): fall back to the plane mean
        total_w = den.sum(dim=(-2, -1), keepdim=True)
        mean = torch.where(total_w > 0, num.sum(dim=(-2, -1), keepdim=True) / total_w.clamp(min=1e-12),
                           torch.zeros_like(total_w))
        out = torch.where(missing, mean.expand_as(out), out)
    return out.reshape(shape)


def sample_maps(maps: torch.Tensor, positions: torch.Tensor, plane: torch.Tensor) -> torch.Tensor:
    """Bilinear read of ``maps[plane[n]]`` ``(P, H, W)`` at ``positions`` ``(N, h, w, 2)`` -> ``(N, h, w)``."""
    hh, ww = maps.shape[-2:]
    src = maps.index_select(0, plane)[:, None]  # (N, 1, H, W)
    gx = 2 * positions[..., 0] / max(ww - 1, 1) - 1
    gy = 2 * positions[..., 1] / max(hh - 1, 1) - 1
    grid = torch.stack([gx, gy], dim=-1)
    return F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=True)[:, 0]


def fuse_initial_estimate(obs: Observations, homographies, hr_shape: tuple[int, int], *, sigma_channel: float = 2.0,
                          sigma_lowpass: float = 4.0, sigma_pan: float = 0.7, radius: int = 6, eps: float = 1e-4,
                          gain_max: float = 4.0, slope_max: float = 4.0, dark_floor: float = 0.02) -> torch.Tensor:
    """Initial HR estimate ``(C, H, W)`` from all observations (see the module docstring).

    ``homographies`` ``(N, 3, 3)`` map the HR reference frame to each observation's pixels.
    Sigmas are in HR pixels; ``radius`` is the window of the local linear model;
    ``dark_floor`` keeps the gain ``B_pan / B_c`` finite where a channel is near 0.
    """
    hm = np.asarray(homographies, dtype=np.float64)
    if hm.shape != (obs.count, 3, 3):
        raise InputError("homographies", f"shape {hm.shape}", f"({obs.count}, 3, 3)")
    dev, dt = obs.images.device, obs.images.dtype
    c = obs.n_channels
    hh, ww = hr_shape
    pos = torch.as_tensor(sample_positions(hm, tuple(obs.images.shape[-2:])), dtype=dt, device=dev)
    y, wts, ch = obs.images, obs.weights, obs.channel_of
    zeros = torch.zeros_like(ch)

    den_c = splat(wts, pos, ch, c, hr_shape)
    num_c = splat(y * wts, pos, ch, c, hr_shape)
    t_c = normalized_convolution(num_c, den_c, sigma_channel)          # per-channel estimate
    b_c = normalized_convolution(num_c, den_c, sigma_lowpass)          # per-channel low-pass
    b_pan = b_c.mean(dim=0, keepdim=True)

    # each sample's detail, moved to the common level of the pan
    b_c_at = sample_maps(b_c, pos, ch)
    b_pan_at = sample_maps(b_pan, pos, zeros)
    gain = ((b_pan_at + dark_floor) / (b_c_at + dark_floor)).clamp(1.0 / gain_max, gain_max)
    pan_values = b_pan_at + gain * (y - b_c_at)
    pan = normalized_convolution(splat(pan_values * wts, pos, zeros, 1, hr_shape),
                                 splat(wts, pos, zeros, 1, hr_shape), sigma_pan)

    # the pan seen through each channel's own sampling and kernel
    pan_at = sample_maps(pan, pos, zeros)
    p_c = normalized_convolution(splat(pan_at * wts, pos, ch, c, hr_shape), den_c, sigma_channel)

    mean_t, mean_p = box_mean(t_c, radius), box_mean(p_c, radius)
    cov = box_mean(t_c * p_c, radius) - mean_t * mean_p
    var = torch.clamp(box_mean(p_c * p_c, radius) - mean_p * mean_p, min=0)
    slope = box_mean((cov / (var + eps)).clamp(-slope_max, slope_max), radius)
    return t_c + slope * (pan - p_c)


__all__ = ["fuse_initial_estimate", "normalized_convolution", "sample_maps", "sample_positions",
           "splat"]
