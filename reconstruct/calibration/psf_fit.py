"""Per-aperture Gaussian PSF width from a Siemens-star capture.

Reference: model-based PSF estimation on a known target (the Siemens-star idea of ISO 12233:2017,
fitted in the image domain). With the star's ground truth ``x`` (``gt.tiff``), the calibrated
geometry, analyzer and flat field, aperture n's raw frame is predicted for a Gaussian PSF of std
``sigma`` (HR px) and ``sigma`` minimises the residual after a least-squares brightness scale, on a
grid then on a finer grid around its minimum (a parabola through the three best points).

The warp in the prediction is the one that made the data. A simulated capture was warped by the
HR bilinear :class:`capssim.operators.Warp` (its interpolation blur is part of its PSF); a rendered
or real one by the optics themselves, whose warp of the scene blurs nothing: it is predicted with
a Lanczos-3 resampling of the ground truth (:func:`lanczos_warp`), whose own blur is negligible at
the star's frequencies. The frame's outer 6 % are left out (warped-in borders replicate).
"""

from __future__ import annotations

import numpy as np
import torch

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.psf import gaussian_psf_kernel
from capssim.camera.rig import RigModel
from capssim.operators import BayerMosaic, ChannelMix, Convolve, IntegrateDecimate, Multiply, Warp

COARSE_SIGMAS = np.arange(0.0, 1.51, 0.1)
BORDER_FRACTION = 0.06
LANCZOS_A = 3


def _lanczos(d: torch.Tensor) -> torch.Tensor:
    return torch.sinc(d) * torch.sinc(d / LANCZOS_A) * (d.abs() < LANCZOS_A)


def lanczos_warp(image: torch.Tensor, homography: np.ndarray) -> torch.Tensor:
    """``(C, H, W)`` sampled at ``homography^-1 (x, y, 1)`` of every output pixel (Lanczos-3, border replicated).

    ``homography`` ``(3, 3)`` maps input (HR reference) -> output pixel coordinates (x=col, y=row), the
    direction of :class:`capssim.operators.Warp`.
    """
    c, h, w = image.shape
    inv = torch.as_tensor(np.linalg.inv(homography), dtype=image.dtype)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=image.dtype), torch.arange(w, dtype=image.dtype), indexing="ij")
    src = torch.einsum("ij,jhw->ihw", inv, torch.stack([xs, ys, torch.ones_like(xs)]))
    sx, sy = src[0] / src[2], src[1] / src[2]
    x0, y0 = torch.floor(sx), torch.floor(sy)
    taps = torch.arange(-LANCZOS_A + 1, LANCZOS_A + 1, dtype=image.dtype)
    wx = _lanczos(sx[..., None] - (x0[..., None] + taps))  # (H, W, 2a)
    wy = _lanczos(sy[..., None] - (y0[..., None] + taps))
    wx, wy = wx / wx.sum(-1, keepdim=True), wy / wy.sum(-1, keepdim=True)
    ix = (x0[..., None] + taps).clamp(0, w - 1).long()
    iy = (y0[..., None] + taps).clamp(0, h - 1).long()
    flat = image.reshape(c, -1)
    out = torch.zeros(c, h, w, dtype=image.dtype)
    for j in range(2 * LANCZOS_A):
        rows = flat[:, (iy[..., j:j + 1] * w + ix).reshape(-1)].reshape(c, h, w, 2 * LANCZOS_A)
        out += wy[..., j] * (rows * wx).sum(-1)
    return out


def warped_apertures(gt: np.ndarray, geometry: ArrayGeometry, rig: RigModel, *, physical_warp: bool) -> torch.Tensor:
    """``(4, 3, H, W)``: each aperture's analyzed view of ``gt`` on its HR grid, before the PSF."""
    hh, ww = geometry.hr_shape
    x = torch.from_numpy(np.asarray(gt, dtype=np.float64))
    analyzed = ChannelMix(rig.analyzer_matrix(), hh, ww, out_lead=(4, 3))(x)
    if not physical_warp:
        return Warp(geometry.aperture_homographies, 3, (hh, ww))(analyzed)
    return torch.stack([lanczos_warp(analyzed[n], geometry.aperture_homographies[n]) for n in range(4)])


def _residuals(views: torch.Tensor, raw: np.ndarray, flat: np.ndarray, sigma: float) -> np.ndarray:
    """``(4,)`` RMS residual of each aperture for PSF ``sigma`` (after a per-aperture LS scale)."""
    shape = tuple(views.shape)
    blurred = Convolve(gaussian_psf_kernel(sigma), shape)(views)
    pred = BayerMosaic((4, 3, shape[2] // 2, shape[3] // 2))(IntegrateDecimate(2, shape)(blurred))
    pred = Multiply(flat)(pred).numpy()
    h, w = raw.shape[1:]
    b = (int(BORDER_FRACTION * h), int(BORDER_FRACTION * w))
    p, y = pred[:, b[0]:h - b[0], b[1]:w - b[1]].reshape(4, -1), raw[:, b[0]:h - b[0], b[1]:w - b[1]].reshape(4, -1)
    scale = np.sum(p * y, axis=1) / np.maximum(np.sum(p * p, axis=1), 1e-20)
    return np.sqrt(np.mean((y - scale[:, None] * p) ** 2, axis=1))


def _parabola_min(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """The minimum of the parabola through the three points around ``argmin y``, and its curvature ``a``."""
    i = int(np.clip(np.argmin(y), 1, len(x) - 2))
    xs, ys = x[i - 1:i + 2], y[i - 1:i + 2]
    a, b, _ = np.polyfit(xs, ys, 2)
    return (float(np.clip(-b / (2 * a), xs[0], xs[-1])), float(a)) if a > 0 else (float(x[np.argmin(y)]), 0.0)


def fit_psf_sigmas(gt: np.ndarray, raw: np.ndarray, geometry: ArrayGeometry, rig: RigModel, *,
                   noise_sigma: float, physical_warp: bool = True) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(4,)`` Gaussian PSF std (HR px) per aperture, its std (``(4,)``, from the curvature of the
    mean squared residual: ``Delta chi^2 = 1``) and a record (the residual curves).

    ``physical_warp``: predict the apertures' views with :func:`lanczos_warp` (rendered and real
    captures); ``False``: with the bilinear warp operator (simulated captures).
    """
    views = warped_apertures(gt, geometry, rig, physical_warp=physical_warp)
    flat = rig.flat_field(raw.shape[1:])
    coarse = np.stack([_residuals(views, raw, flat, s) for s in COARSE_SIGMAS], axis=1)  # (4, S)
    sigmas, stds = np.zeros(4), np.zeros(4)
    n_pix = raw[0].size * (1 - 2 * BORDER_FRACTION) ** 2
    fine_curves = []
    for n in range(4):
        centre = COARSE_SIGMAS[int(np.argmin(coarse[n]))]
        fine = np.unique(np.clip(centre + np.arange(-0.1, 0.101, 0.02), 0.0, None))
        curve = np.array([_residuals(views, raw, flat, s)[n] for s in fine])
        sigmas[n], curvature = _parabola_min(fine, curve ** 2)
        stds[n] = noise_sigma / np.sqrt(n_pix * curvature) if curvature > 0 else float("inf")
        fine_curves.append({"sigma": fine.tolist(), "rms": curve.tolist()})
    return sigmas, stds, {"coarse_sigma": COARSE_SIGMAS.tolist(), "coarse_rms": coarse.tolist(), "fine": fine_curves,
                          "warp": "lanczos-3 (physical)" if physical_warp else "bilinear (as simulated)"}


__all__ = ["fit_psf_sigmas", "lanczos_warp", "warped_apertures"]
