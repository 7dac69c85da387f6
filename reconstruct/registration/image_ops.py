"""Image helpers of the registration engine (:mod:`capssim.reconstruct.registration.engine`):
window sums, noise level, gradients, blur and the phase-correlation candidates of its coarse stage.

All images are ``(B, H, W)`` torch tensors (device-agnostic); coordinates ``(x=col, y=row)``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..filters import box_sum as separable_box_sum


def box_sum(x: torch.Tensor, radius: int) -> torch.Tensor:
    """``(..., H, W)`` sums over ``(2r+1)^2`` windows, zero padded (exact pairwise sums,
    :func:`capssim.reconstruct.filters.box_sum`: about 2 log2(2r+1) additions per pixel).

    Differentiable: the zero-padded symmetric window sum is its own adjoint, so the backward pass
    is one more window sum (autograd through the pairwise sums' slices would allocate and fill a
    full-size zero gradient for each of them: most of a registration's backward time).
    """
    if radius <= 0:
        return x
    if x.requires_grad and torch.is_grad_enabled():
        return _SelfAdjointBoxSum.apply(x, radius)
    return separable_box_sum(x, radius, radius)


class _SelfAdjointBoxSum(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, radius: int) -> torch.Tensor:
        ctx.radius = radius
        return separable_box_sum(x, radius, radius)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return separable_box_sum(grad, ctx.radius, ctx.radius), None


def noise_sigma(img: torch.Tensor) -> torch.Tensor:
    """Per-image white-noise std ``(B,)`` of ``(B, H, W)``: Immerkaer's Laplacian-difference
    operator (CVIU 1996) with a median (edge-robust) instead of the mean absolute value."""
    if min(img.shape[-2:]) < 3:
        return img.new_zeros(img.shape[0])
    k = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], dtype=img.dtype, device=img.device)
    r = F.conv2d(img[:, None], k[None, None])[:, 0]
    return r.abs().flatten(1).median(dim=1).values / (0.6745 * 6.0)


def gradient_magnitude(img: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` central-difference gradient magnitude (replicate border)."""
    p = F.pad(img[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = p[:, 1:-1, 2:] - p[:, 1:-1, :-2]
    gy = p[:, 2:, 1:-1] - p[:, :-2, 1:-1]
    return torch.sqrt(gx * gx + gy * gy)


def phase_correlation_peaks(ref: torch.Tensor, mov: torch.Tensor, *, peaks: int = 3
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate translations ``(B, K, 2)`` (x, y) with ``mov(p + t) ~ ref(p)``, and peak heights ``(B, K)``.

    ``ref`` ``(H, W)``, ``mov`` ``(B, H, W)``. Hann-windowed whitened cross-power spectrum;
    the ``K`` highest local maxima, each refined by a parabola through its neighbours.
    Shifts are searched within +-H/4, +-W/4.
    """
    hh, ww = ref.shape
    win = torch.outer(torch.hann_window(hh, periodic=False, dtype=ref.dtype, device=ref.device),
                      torch.hann_window(ww, periodic=False, dtype=ref.dtype, device=ref.device))
    fr = torch.fft.rfft2((ref - ref.mean()) * win)
    fm = torch.fft.rfft2((mov - mov.mean(dim=(-2, -1), keepdim=True)) * win)
    cross = fm * fr.conj()
    mag = cross.abs()
    cross = cross / (mag + 1e-6 * mag.amax(dim=(-2, -1), keepdim=True) + 1e-300)
    corr = torch.fft.irfft2(cross, s=(hh, ww))  # (B, H, W), peak at the shift (wrapped)
    corr = torch.fft.fftshift(corr, dim=(-2, -1))
    cy, cx = hh // 2, ww // 2
    ys = torch.arange(hh, device=ref.device)[:, None] - cy
    xs = torch.arange(ww, device=ref.device)[None, :] - cx
    window = (ys.abs() <= max(1, hh // 4)) & (xs.abs() <= max(1, ww // 4))
    local_max = corr == F.max_pool2d(F.pad(corr[:, None], (1, 1, 1, 1), mode="circular"), 3, stride=1)[:, 0]
    score = torch.where(local_max & window, corr, torch.full_like(corr, -math.inf))
    k = min(peaks, hh * ww)
    top, idx = score.flatten(1).topk(k, dim=1)
    py, px = idx // ww, idx % ww
    bi = torch.arange(corr.shape[0], device=ref.device)[:, None].expand_as(py)

    def at(dy, dx):
        return corr[bi, (py + dy) % hh, (px + dx) % ww]

    c0 = at(0, 0)
    offs = []
    for pos, neg in ((at(0, 1), at(0, -1)), (at(1, 0), at(-1, 0))):
        den = pos - 2 * c0 + neg
        off = torch.where(den.abs() > 1e-12, 0.5 * (neg - pos) / den.where(den.abs() > 1e-12, torch.ones_like(den)),
                          torch.zeros_like(den))
        offs.append(off.clamp(-0.5, 0.5))
    shift = torch.stack([(px - cx).to(ref.dtype) + offs[0], (py - cy).to(ref.dtype) + offs[1]], -1)
    shift = torch.where(torch.isfinite(top)[..., None], shift, torch.zeros_like(shift))
    return shift, top

