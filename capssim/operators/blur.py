"""Optical blur: 2-D convolution with a PSF kernel, border replicated (paper D_spatial).

The PSF kernels are pixel-integrated: each tap is the PSF's energy over one pixel of the
grid the kernel is applied on, so ``sigma -> 0`` gives the identity.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from scipy.special import erf, j1

from capssim.errors import InputError
from capssim.operators.base import LinearOperator


def gaussian_psf_kernel(sigma_px: float, *, truncate: float = 3.5) -> np.ndarray:
    """Pixel-integrated isotropic Gaussian PSF of std ``sigma_px`` (pixels), odd square, sums to 1."""
    if not (sigma_px >= 0 and math.isfinite(sigma_px)):
        raise InputError("sigma_px", sigma_px, "a finite number >= 0 (pixels)")
    if sigma_px < 1e-6:
        return np.ones((1, 1))
    radius = max(1, int(math.ceil(truncate * sigma_px)))
    edges = np.arange(-radius, radius + 2) - 0.5
    cdf = 0.5 * (1 + erf(edges / (math.sqrt(2) * sigma_px)))
    taps = np.diff(cdf)
    taps /= taps.sum()
    return np.outer(taps, taps)


def airy_psf_kernel(f_number: float, wavelength_nm: float, pixel_um: float, *,
                    rings: int = 3, supersample: int = 9) -> np.ndarray:
    """Diffraction-limited Airy PSF ``[2 J1(v)/v]^2``, ``v = pi r / (lambda N)``, pixel-integrated.

    ``pixel_um`` is the pitch of the grid it is applied on. The kernel covers ``rings``
    dark rings (first zero at ``1.22 lambda N``) and is normalised to sum 1.
    """
    for arg, value in (("f_number", f_number), ("wavelength_nm", wavelength_nm), ("pixel_um", pixel_um)):
        if not (value > 0 and math.isfinite(value)):
            raise InputError(arg, value, "a finite positive number")
    lam_n_um = wavelength_nm * 1e-3 * f_number
    radius_um = (rings + 0.22) * lam_n_um
    radius = max(1, int(math.ceil(radius_um / pixel_um)))
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    grid = np.arange(-radius, radius + 1)
    fine = (grid[:, None] + offsets[None, :]).ravel() * pixel_um
    yy, xx = np.meshgrid(fine, fine, indexing="ij")
    v = np.pi * np.hypot(xx, yy) / lam_n_um
    with np.errstate(invalid="ignore", divide="ignore"):
        psf = np.where(v < 1e-9, 1.0, (2 * j1(v) / np.where(v < 1e-9, 1.0, v)) ** 2)
    n = 2 * radius + 1
    psf = psf.reshape(n, supersample, n, supersample).sum(axis=(1, 3))
    return psf / psf.sum()


def _replicate_index(n: int, before: int, after: int) -> torch.Tensor:
    return torch.clamp(torch.arange(-before, n + after), 0, n - 1)


class Convolve(LinearOperator):
    """``(..., H, W) -> (..., H, W)`` correlation with an odd ``kernel``, border replicated.

    Forward = replicate-pad (a gather) then valid ``conv2d``; adjoint = ``conv_transpose2d``
    then the pad's adjoint (an ``index_add`` folding the border back).
    """

    name = "convolve"

    def __init__(self, kernel, shape: tuple[int, ...]):
        k = np.asarray(kernel, dtype=np.float64)
        if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
            raise InputError("kernel", f"shape {k.shape}", "a 2-D kernel with odd height and width")
        super().__init__(shape, shape)
        self.kernel = torch.as_tensor(k)[None, None]
        self.pad = (k.shape[0] // 2, k.shape[1] // 2)
        h, w = shape[-2:]
        self.row_index = _replicate_index(h, self.pad[0], self.pad[0])
        self.col_index = _replicate_index(w, self.pad[1], self.pad[1])
        self.is_identity = k.shape == (1, 1) and k[0, 0] == 1.0

    def _grouped_kernel(self, like, n: int, *, flipped: bool = False):
        # planes as channels of one grouped conv: much faster on CPU than a batch of 1-channel convs
        k = self._const("kf" if flipped else "k", torch.flip(self.kernel, (2, 3)) if flipped else self.kernel, like)
        return k.expand(n, 1, *k.shape[2:])

    def _forward(self, x):
        if self.is_identity:
            return x.clone()
        h, w = self.input_shape[-2:]
        n = x.numel() // (h * w)
        ph, pw = self.pad
        padded = F.pad(x.reshape(1, n, h, w), (pw, pw, ph, ph), mode="replicate")
        return F.conv2d(padded, self._grouped_kernel(x, n), groups=n).reshape(self.output_shape)

    def _adjoint(self, y):
        if self.is_identity:
            return y.clone()
        h, w = self.input_shape[-2:]
        n = y.numel() // (h * w)
        ph, pw = self.pad
        # conv_transpose2d(y, k) written as a full correlation with the flipped kernel
        full = F.pad(y.reshape(1, n, h, w), (2 * pw, 2 * pw, 2 * ph, 2 * ph))
        padded = F.conv2d(full, self._grouped_kernel(y, n, flipped=True), groups=n).reshape(n, 1, h + 2 * ph, w + 2 * pw)
        return self._fold_padding(padded, y)
