"""Per-aperture Gaussian PSF width from a Siemens-star capture.

Reference: model-based PSF estimation on a known target (the slanted-edge / Siemens-star idea of
ISO 12233:2017, fitted in the image domain). With the star's ground truth ``x`` (``gt.tiff``), the
calibrated geometry, analyzer and flat field, aperture n's raw frame is predicted for a Gaussian
PSF of std ``sigma`` (HR px) by the one camera model (:func:`capssim.operators.caps_raw_operator`);
``sigma`` minimises the residual after a least-squares brightness scale, on a grid then on a finer
grid around its minimum (a parabola through the three best points gives the value). The frame's
outer 6 % are left out (warped-in border replicates).
"""

from __future__ import annotations

import numpy as np
import torch

from capssim.geometry import ArrayGeometry
from capssim.operators import caps_raw_operator
from capssim.psf import gaussian_psf_kernel
from capssim.rig import RigModel

COARSE_SIGMAS = np.arange(0.0, 1.51, 0.1)
BORDER_FRACTION = 0.06


def _residuals(gt: torch.Tensor, raw: np.ndarray, geometry: ArrayGeometry, rig: RigModel, sigma: float) -> np.ndarray:
    """``(4,)`` RMS residual of each aperture for PSF ``sigma`` (after a per-aperture LS scale)."""
    model = RigModel(angle_offsets_deg=rig.angle_offsets_deg, extinction_ratio=rig.extinction_ratio,
                     gain=rig.gain, vignetting=rig.vignetting)
    op = caps_raw_operator(geometry.hr_shape, geometry.aperture_homographies, gaussian_psf_kernel(sigma), rig=model)
    with torch.no_grad():
        pred = op(gt).numpy()
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
                   noise_sigma: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(4,)`` Gaussian PSF std (HR px) per aperture, its std (``(4,)``, from the curvature of the
    mean squared residual: ``Delta chi^2 = 1``) and a record (the residual curves)."""
    x = torch.from_numpy(np.asarray(gt, dtype=np.float64))
    coarse = np.stack([_residuals(x, raw, geometry, rig, s) for s in COARSE_SIGMAS], axis=1)  # (4, S)
    sigmas, stds = np.zeros(4), np.zeros(4)
    n_pix = raw[0].size * (1 - 2 * BORDER_FRACTION) ** 2
    fine_curves = []
    for n in range(4):
        centre = COARSE_SIGMAS[int(np.argmin(coarse[n]))]
        fine = np.clip(centre + np.arange(-0.1, 0.101, 0.02), 0.0, None)
        fine = np.unique(fine)
        curve = np.array([_residuals(x, raw, geometry, rig, s)[n] for s in fine])
        sigmas[n], curvature = _parabola_min(fine, curve ** 2)
        stds[n] = noise_sigma / np.sqrt(n_pix * curvature) if curvature > 0 else float("inf")
        fine_curves.append({"sigma": fine.tolist(), "rms": curve.tolist()})
    return sigmas, stds, {"coarse_sigma": COARSE_SIGMAS.tolist(), "coarse_rms": coarse.tolist(), "fine": fine_curves}


__all__ = ["fit_psf_sigmas"]
