"""Gain and vignetting of each aperture from flat-field captures.

Reference: the flat-field model of EMVA 1288 (release 4.0, section 8: photo-response
non-uniformity): with uniform unpolarized light of known level ``L``, aperture n's raw pixel reads
``F_n(u, v) L`` (:meth:`capssim.camera.rig.RigModel.flat_field`). ``F_n`` is fitted by linear least
squares in the degree-4 polynomial basis of :data:`capssim.camera.rig.VIGNETTING_MONOMIALS` over all of
the aperture's pixels (the average of several frames when given); its value at the frame centre
(the constant term) is the gain, and the map divided by it the vignetting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from capssim.camera.rig import normalised_raw_coordinates, vignetting_design

#: a flat field with more saturated pixels than this fraction is refused
MAX_SATURATED_FRACTION = 1e-4


@dataclass
class FlatFieldFit:
    """``coefficients`` ``(4, 15)`` of ``F_n`` (not normalised), ``gain`` ``(4,)`` and its std, the
    vignetting ``(4, 15)`` (``F_n / gain_n``), the RMS relative residual ``(4,)`` and the raw noise std."""

    coefficients: np.ndarray
    gain: np.ndarray
    gain_std: np.ndarray
    vignetting: np.ndarray
    residual_rms: np.ndarray
    noise_sigma: float
    level: float

    def maps(self, raw_shape) -> np.ndarray:
        """``(4, H, W)`` fitted ``F_n`` on the raw grid."""
        u, v = normalised_raw_coordinates(raw_shape)
        return np.moveaxis(vignetting_design(u, v) @ self.coefficients.T, -1, 0)


def fit_flat_field(frames: np.ndarray, level: float) -> FlatFieldFit:
    """Fit ``F_n`` to flat frames ``(F, 4, H, W)`` (float, full scale 1) of light level ``level``."""
    mean = np.mean(np.asarray(frames, dtype=np.float64), axis=0) / level
    design = vignetting_design(*normalised_raw_coordinates(mean.shape[1:])).reshape(-1, 15)
    coef, *_ = np.linalg.lstsq(design, mean.reshape(4, -1).T, rcond=None)  # (15, 4)
    fitted = (design @ coef).T.reshape(mean.shape)
    resid = mean - fitted
    # per-pixel noise of one frame (raw units), from the residual of the mean of the frames
    noise_sigma = float(np.std(resid) * level * np.sqrt(len(frames)))
    gain = coef[0].copy()
    cov_scale = np.linalg.inv(design.T @ design)[0, 0]
    gain_std = np.std(resid.reshape(4, -1), axis=1) * np.sqrt(cov_scale)
    return FlatFieldFit(coefficients=coef.T, gain=gain, gain_std=gain_std, vignetting=(coef / coef[0]).T,
                        residual_rms=np.sqrt(np.mean((resid / fitted) ** 2, axis=(1, 2))), noise_sigma=noise_sigma,
                        level=float(level))


__all__ = ["MAX_SATURATED_FRACTION", "FlatFieldFit", "fit_flat_field"]
