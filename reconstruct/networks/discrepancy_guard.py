"""The discrepancy guard of a learned DoFP demosaicker: where its output departs from the raw samples by more than
their noise explains, move it towards an estimate that reproduces them.

Reference: V. A. Morozov, "On the solution of functional equations by the method of regularization", Soviet
Mathematics Doklady 7 (1966) 414-417 (the discrepancy principle: an estimate should reproduce the data to within
their noise).

A DoFP pixel measures one channel of the 12-channel image (the one its polarizer and colour filter select):
``m = M x + n``, with noise of std ``s`` at each pixel. For the true image the normalized residual
``z = (M x - m) / s`` has unit mean square, so its local mean square ``e`` (a Gaussian window of std
:data:`WINDOW_SIGMA` px: about ``4 pi WINDOW_SIGMA^2 = 200`` samples, so the truth's ``e`` stays within about
1 +- 0.1) is 1. A learned estimate whose ``e`` exceeds :data:`THRESHOLD` (five of those standard deviations above
the truth's) contradicts the data there: it is moved towards the fallback by ``b = 1 - THRESHOLD / e``,
``x' = x + b (x_fallback - x)`` (``b = 0`` wherever ``e <= THRESHOLD``). The fallback here is IGRI2, which
reproduces the samples exactly. ``s`` is at least ``noise_floor``: on a noise-free mosaic the guard then allows the
estimate that much error per sample, and no more.

Measured (docs/results/dofp-nafnet.md, "Scenes it never saw"): ``dofp-nafnet`` trained without the Qiu scenes lost
3-7 dB to IGRI2 on the photoelastic phone cases, whose strong colourful polarization it had not seen; on the 12
development captures of the two held-out scenes the guard gained +1.58 dB (paired SE 0.62, 12 wins of 12). Where the
scene has detail finer than the samples (a dense Siemens star) or no noise, a good estimate also departs from the
samples, and the guard costs up to 1 dB.
"""

from __future__ import annotations

import torch

from ..filters import gaussian_blur
from .cpdnet import sparse_channels

__all__ = ["THRESHOLD", "WINDOW_SIGMA", "discrepancy_guard", "discrepancy_share", "sampled_channel"]

#: the local mean square of the normalized residual above which an estimate contradicts the data (the truth's is
#: 1, within about +-0.1 over the window)
THRESHOLD = 1.5
#: the std (px) of the Gaussian window of the local mean square
WINDOW_SIGMA = 4.0


def sampled_channel(shape: tuple[int, int], layout, device=None) -> torch.Tensor:
    """``(H, W)`` int64: the channel ``c = 3 p + k`` that each pixel of a DoFP mosaic of ``layout`` samples."""
    return sparse_channels(torch.ones((1, *shape), device=device), layout)[0].argmax(0)


def discrepancy_share(estimate: torch.Tensor, mosaic: torch.Tensor, noise_std, layout, *, noise_floor: float,
                      threshold: float = THRESHOLD, window_sigma: float = WINDOW_SIGMA) -> torch.Tensor:
    """``(H, W)`` share ``b`` in [0, 1] that the guard takes from the fallback at each pixel (module docstring), for
    ``estimate`` ``(12, H, W)`` of the ``(H, W)`` ``mosaic`` with noise std ``noise_std`` (``(H, W)`` or a number,
    [0, 1] scale, at least ``noise_floor``)."""
    channel = sampled_channel(tuple(mosaic.shape), layout, estimate.device)
    residual = estimate.gather(0, channel[None])[0] - mosaic.to(estimate.dtype)
    scale = torch.as_tensor(noise_std, dtype=estimate.dtype, device=estimate.device).clamp_min(noise_floor)
    # normalized convolution: a window at the border averages the samples it holds (no padded copies)
    weight = gaussian_blur(torch.ones_like(residual), window_sigma, padding="zeros")
    energy = gaussian_blur((residual / scale).square(), window_sigma, padding="zeros") / weight
    return (1.0 - threshold / energy.clamp_min(1e-12)).clamp(0.0, 1.0)


def discrepancy_guard(estimate: torch.Tensor, fallback: torch.Tensor, mosaic: torch.Tensor, noise_std, layout, *,
                      noise_floor: float, threshold: float = THRESHOLD,
                      window_sigma: float = WINDOW_SIGMA) -> tuple[torch.Tensor, torch.Tensor]:
    """``estimate`` and ``fallback`` ``(12, H, W)``, the ``(H, W)`` ``mosaic`` they were made from, its noise std
    and DoFP ``layout`` -> the guarded estimate ``x + b (x_fallback - x)`` ``(12, H, W)`` and ``b`` ``(H, W)``
    (:func:`discrepancy_share`)."""
    share = discrepancy_share(estimate, mosaic, noise_std, layout, noise_floor=noise_floor, threshold=threshold,
                              window_sigma=window_sigma)
    return estimate + share * (fallback.to(estimate.dtype) - estimate), share
