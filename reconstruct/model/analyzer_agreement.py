"""Structure-aware coupling: the polarization-split data term, coupled across analyzers where their
images agree (not the paper's; ``-p data_term=cagf-agree``).

The paper's data direction (eq. 26) shares every channel's back-projected residual ``B`` with every other
channel, with CAGF's confidence ``L^H`` as the weight: ``D = L^H B``. All weights are >= 0, so where the
analyzer images have opposite local contrast (polarization-only structure) a residual seen at one analyzer
pushes the others the wrong way. The polarization-split direction
(:mod:`capssim.reconstruct.model.polarization_split`) never shares the polarization part of ``B`` across
analyzers, and so also gives up that sharing where it is right: where the analyzer images are positively
related copies of one another (a uniform degree and angle of polarization under intensity structure),
sharing it averages the noise of the four analyzers (the Siemens star's DoLP, and the 3-D scenes whose views
a homography does not fully align).

This data term mixes the two per HR pixel with an **agreement** ``alpha`` in [0, 1]::

    D = alpha L^H B + (1 - alpha) (P L^H P B + (I - P) L^H_angle (I - P) B)

``alpha`` is the smallest, over the colours and the analyzer pairs ``(p, q)``, of the local correlation of
the two analyzers' aligned LR images with the noise taken out, clipped to [0, 1]::

    rho_pq = (cov(I_p, I_q) + eps) / sqrt((var I_p - s_p^2)_+ + eps) ((var I_q - s_q^2)_+ + eps))

over the CAGF window (radius and ``eps`` of eq. 12: ``cagf_radius``, ``cagf_eps``), ``s_p`` the white-noise
std of each aligned channel image (Immerkaer's estimate,
:func:`~capssim.reconstruct.registration.image_ops.noise_sigma`), resized to the HR grid as CAGF's
confidence is. Opposite contrast gives ``rho < 0``, hence ``alpha = 0`` (the split direction); images that
are positive multiples of one another give ``rho`` near 1 (eq. 26); so does a window with no structure
above the noise (``rho -> eps / eps``): where nothing says the analyzers differ, their residuals are shared.
Without the noise correction, noise alone would read as disagreement, more the noisier the capture.

For each pixel the matrix ``alpha L + (1 - alpha) S`` is a convex combination of two symmetric positive
semi-definite matrices (``S`` is the split's; :mod:`.polarization_split`), so ``D`` stays a descent
direction of the same data term ``f`` (eq. 15). It is not ``f``'s gradient, so ADMM's fixed points move with it:
``mu (Z - X) = -D grad f`` weighs data against prior pixel by pixel (docs: notes/caps-plus-model.md). Channel order: angle-major,
``c = p K + k``.
"""

from __future__ import annotations

import numpy as np
import torch

from capssim.errors import InputError

from ..registration.image_ops import noise_sigma
from .cagf import DEFAULT_EPS, DEFAULT_RADIUS, aligned_channel_images, box_mean, resize_to_hr
from .data_term import confidence_mix
from .polarization_split import N_ANGLES, PolarizationSplitDataTerm, split_confidence_mix

__all__ = ["AgreementDataTerm", "agreement_confidence_mix", "analyzer_agreement", "analyzer_agreement_map"]


def analyzer_agreement(channels: torch.Tensor, *, radius: int = DEFAULT_RADIUS, eps: float = DEFAULT_EPS,
                       noise_std: torch.Tensor | None = None, n_angles: int = N_ANGLES) -> torch.Tensor:
    """``alpha`` ``(h, w)`` in [0, 1] of aligned channel images ``channels`` ``(C, h, w)`` (angle-major,
    ``C = n_angles K``): per pixel the smallest noise-corrected local correlation between two analyzers of one
    colour, clipped to [0, 1] (module docstring). ``noise_std`` ``(C,)``: each channel image's white-noise std
    on its own scale (``None``: estimated from ``channels``)."""
    if channels.ndim != 3 or channels.shape[0] % n_angles:
        raise InputError("channels", f"shape {tuple(channels.shape)}",
                         f"(C, h, w) aligned channel images with C a multiple of the {n_angles} analyzers")
    if not (eps > 0 and np.isfinite(eps)):
        raise InputError("cagf_eps", eps, "a finite positive number (the guided filter's epsilon, eq. 12)")
    k = channels.shape[0] // n_angles
    if noise_std is None:
        noise_std = noise_sigma(channels)
    noise_var = torch.as_tensor(noise_std, dtype=channels.dtype, device=channels.device).reshape(n_angles, k, 1, 1) ** 2
    x = channels.reshape(n_angles, k, *channels.shape[1:])
    mean = box_mean(x, radius)
    var = (box_mean(x * x, radius) - mean * mean - noise_var).clamp(min=0) + eps
    worst = None
    for p in range(n_angles):
        for q in range(p + 1, n_angles):
            cov = box_mean(x[p] * x[q], radius) - mean[p] * mean[q]
            rho = (cov + eps) / torch.sqrt(var[p] * var[q])
            worst = rho if worst is None else torch.minimum(worst, rho)
    return worst.amin(dim=0).clamp(0.0, 1.0)


def analyzer_agreement_map(images: torch.Tensor, homographies, channel_of: torch.Tensor, n_channels: int,
                           hr_shape: tuple[int, int], *, weights: torch.Tensor | None = None,
                           radius: int = DEFAULT_RADIUS, eps: float = DEFAULT_EPS, reference: int = 0) -> torch.Tensor:
    """``alpha`` ``(H, W)`` on the HR grid from the observations ``images`` ``(N, h, w)``, aligned onto the
    reference image as CAGF aligns them (:func:`~capssim.reconstruct.model.cagf.cagf_confidence`, same
    arguments)."""
    chans = aligned_channel_images(images, homographies, channel_of, n_channels, weights=weights, reference=reference)
    alpha = analyzer_agreement(chans, radius=radius, eps=eps)
    return resize_to_hr(alpha, np.asarray(homographies)[reference], hr_shape).clamp(0.0, 1.0)


def agreement_confidence_mix(confidence: torch.Tensor, b: torch.Tensor, alpha: torch.Tensor,
                             n_angles: int = N_ANGLES) -> torch.Tensor:
    """``D = alpha L b + (1 - alpha) (P L P b + (I - P) L_angle (I - P) b)`` per pixel.

    ``confidence`` ``(C, C, H, W)``, ``b`` ``(C, H, W)``, ``alpha`` ``(H, W)`` -> ``(C, H, W)``.
    """
    split = split_confidence_mix(confidence, b, n_angles)
    return split + alpha * (confidence_mix(confidence, b) - split)


class AgreementDataTerm(PolarizationSplitDataTerm):
    """The data term of eq. 15 with the direction :func:`agreement_confidence_mix`.

    Same observations, operator, value and back-projection as
    :class:`~capssim.reconstruct.model.data_term.ConfidenceDataTerm`; ``confidence`` ``(C, C, H, W)`` and
    ``agreement`` ``(H, W)`` (``alpha``, in [0, 1]) are required.
    """

    def __init__(self, obs, operator, *, confidence: torch.Tensor, agreement: torch.Tensor, mixing=None,
                 n_angles: int = N_ANGLES):
        super().__init__(obs, operator, confidence=confidence, mixing=mixing, n_angles=n_angles)
        if tuple(agreement.shape) != tuple(confidence.shape[-2:]):
            raise InputError("agreement", f"shape {tuple(agreement.shape)}",
                             f"the confidence's HR shape {tuple(confidence.shape[-2:])}")
        self.agreement = agreement.to(confidence.dtype)

    def mix(self, b: torch.Tensor) -> torch.Tensor:
        """``D`` ``(C, H, W)`` (module docstring) from the back-projection ``b``."""
        return agreement_confidence_mix(self.confidence, b, self.agreement, self.n_angles)
