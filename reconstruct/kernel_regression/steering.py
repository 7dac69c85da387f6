"""Kernels steered by the local structure tensor, and the noise level they adapt to.

Reference: Wronski et al., "Handheld multi-frame super-resolution", ACM TOG 38(4) 2019, section 5.1.2 (kernel
covariance from the eigen-analysis of the structure tensor); the noise estimate is Immerkaer, "Fast noise
variance estimation", CVIU 64(2) 1996.

The structure tensor of the merged intensity ``G`` (HR grid) is ``T = g_sigma * [Gx^2, Gx Gy; Gx Gy, Gy^2]``
(central differences, Gaussian window :data:`TENSOR_SIGMA` HR px). Its eigenvalues ``l1 >= l2`` and the
gradient direction ``e1`` give

- the coherence ``c = (l1 - l2) / (l1 + l2 + eps)`` in [0, 1] (1 at a straight edge);
- the flatness ``F = exp(-sqrt(l1) / (FLAT_K * sigma_n))`` in [0, 1] (1 where the gradient is at the noise level);
- the kernel std across the edge (along ``e1``) ``s_across = s0 / (1 + (SHRINK - 1) c)`` and along it
  ``s_along = s0 (1 + (STRETCH - 1) c)``, with ``s0 = DETAIL + (DENOISE - DETAIL) F`` HR px.

The inverse covariance ``Q = e1 e1^T / s_across^2 + e2 e2^T / s_along^2`` is returned as its three entries
``(Qxx, Qxy, Qyy)`` ``(3, Ho, Wo)``. The constants were chosen on the development suite (``eval/suites/dev.yaml``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["DETAIL", "isotropic", "noise_sigma", "steered"]

#: the kernel std (HR px) at detail (s0 without noise) and in flat regions
DETAIL, DENOISE = 1.5, 2.0
#: how much a coherent edge stretches the kernel along it and shrinks it across it
STRETCH, SHRINK = 2.0, 1.5
#: the Gaussian window of the structure tensor (HR px) and the flatness threshold in noise stds
TENSOR_SIGMA, FLAT_K = 1.0, 3.0


def isotropic(shape: tuple[int, int], sigma: float, device) -> torch.Tensor:
    """``(3, Ho, Wo)``: ``Q = I / sigma^2`` everywhere (``sigma`` in HR px)."""
    q = torch.zeros(3, *shape, dtype=torch.float32, device=device)
    q[0] = q[2] = 1.0 / sigma ** 2
    return q


def _gaussian(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """``(C, H, W)`` blurred by a separable Gaussian of std ``sigma`` px (replicate border)."""
    radius = max(1, int(math.ceil(3 * sigma)))
    t = torch.arange(-radius, radius + 1, dtype=torch.float32, device=image.device)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    x = image[:, None]
    x = F.conv2d(F.pad(x, (radius, radius, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    x = F.conv2d(F.pad(x, (0, 0, radius, radius), mode="replicate"), k.view(1, 1, -1, 1))
    return x[:, 0]


def steered(intensity: torch.Tensor, sigma_n: float, *, scale: float = 1.0, steer: bool = True) -> torch.Tensor:
    """``(3, Ho, Wo)`` inverse kernel covariance steered by ``intensity`` ``(Ho, Wo)`` (module docstring);
    ``sigma_n`` the noise std of ``intensity``; ``scale`` multiplies every std; ``steer=False``: isotropic
    ``s0`` (no stretch, no shrink)."""
    g = F.pad(intensity[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    gx = 0.5 * (g[1:-1, 2:] - g[1:-1, :-2])
    gy = 0.5 * (g[2:, 1:-1] - g[:-2, 1:-1])
    t = _gaussian(torch.stack([gx * gx, gx * gy, gy * gy]), TENSOR_SIGMA)
    txx, txy, tyy = t[0], t[1], t[2]
    half_tr = 0.5 * (txx + tyy)
    root = torch.sqrt((0.5 * (txx - tyy)) ** 2 + txy ** 2)
    l1, l2 = half_tr + root, (half_tr - root).clamp_min(0.0)
    flat = torch.exp(-torch.sqrt(l1) / (FLAT_K * max(float(sigma_n), 1e-4)))
    s0 = scale * (DETAIL + (DENOISE - DETAIL) * flat)
    if not steer:
        return torch.stack([1 / s0 ** 2, torch.zeros_like(s0), 1 / s0 ** 2])
    coherence = (l1 - l2) / (l1 + l2 + 1e-12)
    across = s0 / (1 + (SHRINK - 1) * coherence)
    along = s0 * (1 + (STRETCH - 1) * coherence)
    angle = 0.5 * torch.atan2(2 * txy, txx - tyy)  # direction of e1 (the gradient)
    cx, sy = torch.cos(angle), torch.sin(angle)
    a, b = 1 / across ** 2, 1 / along ** 2
    return torch.stack([a * cx * cx + b * sy * sy, (a - b) * cx * sy, a * sy * sy + b * cx * cx])


def noise_sigma(sub_images: torch.Tensor) -> float:
    """Immerkaer's noise std of ``(N, h, w)`` images (median over the images; 0 when smaller than 3x3):
    ``sqrt(pi / 2) / (6 (w - 2)(h - 2)) sum |I * L|`` with ``L = [[1,-2,1],[-2,4,-2],[1,-2,1]]``."""
    if sub_images.shape[-1] < 3 or sub_images.shape[-2] < 3:
        return 0.0
    lap = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], device=sub_images.device)
    response = F.conv2d(sub_images[:, None].to(torch.float32), lap.view(1, 1, 3, 3))
    per_image = math.sqrt(math.pi / 2) / 6 * response.abs().mean(dim=(1, 2, 3))
    return float(per_image.median())
