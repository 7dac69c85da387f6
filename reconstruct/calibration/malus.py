"""Polarizer angle and extinction ratio of each aperture and colour from a polarizer sweep.

Reference: Malus's law for a partial polarizer (Born & Wolf, Principles of Optics, 7th ed.,
section 1.4.2; the polarization-state-generator calibration of D. H. Goldstein, Polarized Light,
3rd ed., chapter 24). A uniform field fully polarized at ``phi`` and of level ``L`` (each stored
channel ``L (1 + cos 2(a - phi))``) seen through a polarizer at ``theta`` with extinction ratio
``ER`` reads, after the flat-field correction,

    m(phi) = L [1 + rho cos 2(phi - theta)],   rho = (ER - 1) / (ER + 1).

Per aperture n and colour k the mean ``m`` of each sweep capture is fitted by linear least
squares in ``[1, cos 2phi, sin 2phi]``: ``theta = atan2(a2, a1) / 2``, ``rho = |a| / a0``.
Samples whose raw mean lies within ``MIN_SIGMAS`` noise stds of 0 are left out (the sensor clips
noise at 0, which biases a mean there). Uncertainties come from the fit's covariance (the larger of
the residual's and the noise's estimate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from capssim.conventions import BAYER_OFFSETS, BAYER_SITE_COLOUR, POLARIZER_ANGLES_DEG

#: samples closer to 0 than this many raw noise stds are not used
MIN_SIGMAS = 4.0
#: fraction of each frame's border left out of the means
BORDER_FRACTION = 0.05


@dataclass
class MalusFit:
    """``theta_deg`` / ``theta_std`` ``(4, 3)`` per aperture and colour; ``angle_offsets_deg`` /
    ``angle_std`` ``(4,)`` (colours combined); ``extinction_ratio`` / ``er_std`` ``(4, 3)``;
    ``samples``: ``(phi (K,), means (4, 3, K), used (4, 3, K))`` for the report; ``rms`` ``(4, 3)``."""

    theta_deg: np.ndarray
    theta_std: np.ndarray
    angle_offsets_deg: np.ndarray
    angle_std: np.ndarray
    extinction_ratio: np.ndarray
    er_std: np.ndarray
    rms: np.ndarray
    samples: tuple


def colour_means(raw: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``(4, 3)``: per aperture and colour, the mean of ``raw / flat`` over the frame's inner part."""
    h, w = raw.shape[1:]
    b = (int(BORDER_FRACTION * h) // 2 * 2, int(BORDER_FRACTION * w) // 2 * 2)
    corrected = (raw / flat)[:, b[0]:h - b[0], b[1]:w - b[1]]
    out = np.zeros((4, 3))
    counts = np.zeros(3)
    for q, (oy, ox) in enumerate(BAYER_OFFSETS):
        k = BAYER_SITE_COLOUR[q]
        out[:, k] += corrected[:, oy::2, ox::2].mean(axis=(1, 2))
        counts[k] += 1
    return out / counts


def _fit_one(phi: np.ndarray, m: np.ndarray, noise_var: float) -> tuple[float, float, float, float, float]:
    """``(theta_deg, theta_std, rho, rho_std, rms)`` of one Malus curve ``m(phi)`` (levels divided out)."""
    x = np.stack([np.ones_like(phi), np.cos(2 * np.radians(phi)), np.sin(2 * np.radians(phi))], axis=1)
    a, *_ = np.linalg.lstsq(x, m, rcond=None)
    resid = m - x @ a
    dof = len(m) - 3
    var = max(float(resid @ resid) / dof if dof > 0 else 0.0, noise_var)
    cov = var * np.linalg.inv(x.T @ x)
    amp2 = a[1] ** 2 + a[2] ** 2
    theta = 0.5 * np.degrees(np.arctan2(a[2], a[1]))
    g_theta = 0.5 * np.degrees(np.array([0.0, -a[2] / amp2, a[1] / amp2]))
    rho = np.sqrt(amp2) / a[0]
    g_rho = np.array([-rho / a[0], a[1] / (np.sqrt(amp2) * a[0]), a[2] / (np.sqrt(amp2) * a[0])])
    return (float(theta), float(np.sqrt(g_theta @ cov @ g_theta)), float(rho), float(np.sqrt(g_rho @ cov @ g_rho)),
            float(np.sqrt(np.mean(resid ** 2))))


def fit_malus(frames: np.ndarray, phi_deg, levels, flat: np.ndarray, noise_sigma: float) -> MalusFit:
    """Fit every aperture and colour of a sweep: ``frames`` ``(K, 4, H, W)`` raw (full scale 1),
    ``phi_deg`` / ``levels`` ``(K,)``, ``flat`` ``(4, H, W)`` the fitted flat field (gain included)."""
    phi, levels = np.asarray(phi_deg, dtype=np.float64), np.asarray(levels, dtype=np.float64)
    means = np.stack([colour_means(f, flat) / lv for f, lv in zip(frames, levels)], axis=-1)  # (4, 3, K)
    raw_means = means * levels * np.mean(flat, axis=(1, 2))[:, None, None]
    used = raw_means > MIN_SIGMAS * noise_sigma
    n_pix = frames.shape[2] * frames.shape[3] / 4
    noise_var = (noise_sigma / levels.mean()) ** 2 / n_pix
    theta, theta_std, er, er_std, rms = (np.zeros((4, 3)) for _ in range(5))
    for n in range(4):
        for k in range(3):
            t, ts, rho, rs, r = _fit_one(phi[used[n, k]], means[n, k, used[n, k]], noise_var)
            nominal = POLARIZER_ANGLES_DEG[n]
            theta[n, k] = (t - nominal + 90.0) % 180.0 - 90.0 + nominal
            theta_std[n, k] = ts
            rho = min(rho, 1.0 - 1e-9)
            er[n, k] = (1 + rho) / (1 - rho)
            er_std[n, k] = 2 * rs / (1 - rho) ** 2
            rms[n, k] = r
    weights = 1.0 / np.maximum(theta_std, 1e-9) ** 2
    offsets = np.sum(weights * (theta - np.asarray(POLARIZER_ANGLES_DEG)[:, None]), axis=1) / weights.sum(axis=1)
    return MalusFit(theta, theta_std, offsets, 1.0 / np.sqrt(weights.sum(axis=1)), er, er_std, rms,
                    (phi, means, used))


__all__ = ["MIN_SIGMAS", "MalusFit", "colour_means", "fit_malus"]
