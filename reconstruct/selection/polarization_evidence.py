"""Does a capture show polarization structure at all? The Stokes-consistency test of the analyzers' aligned
images (not the paper's; ``caps-plus``'s ``-p polarization_filter=auto``).

Ideal linear analyzers at 0, 45, 90 and 135 deg see ``I_p = (S0 + S1 cos 2 theta_p + S2 sin 2 theta_p) / 2``
(Goldstein, *Polarized Light*, 3rd ed., 2011, ch. 8), so every polarization state gives

    c = I_0 - I_45 + I_90 - I_135 = 0,        d = (I_0 - I_90, I_45 - I_135) = (S1, S2).

The four apertures' aligned LR images add errors of their own ``e_p``: noise, the aliasing that their sub-pixel
offsets sample differently, misregistration, gain. If these are independent with one variance ``v``, the local
variances (over CAGF's window) satisfy

    E var(c) = 4 v,        E [var(d_1) + var(d_2)] = 4 v + var(S1) + var(S2),

so the ratio of their sums over the frame and the colours,

    T = sum var(c) / sum [var(d_1) + var(d_2)],

is below 1 by the share of the polarization differences that the scene's structure explains, and about 1 (or
above, where the apertures' errors are correlated as aliasing is) when the analyzers differ only as the errors
alone would make them: the data then show no polarization structure, and any that a reconstruction puts in the
polarization part is the apertures' errors read as polarization (false polarization, e.g. of an unpolarized
Siemens star, whose aliased centre each aperture samples differently). ``T >= 1`` is the null value of the test,
not a tuned threshold.

With a calibrated analyzer (``unmix``) the channel images are unmixed per pixel first, so that ``c`` and ``d`` are
those of the ideal analyzers. Channel order: ``c = 3 p + k`` (angle-major, :mod:`capssim.conventions`).
"""

from __future__ import annotations

import numpy as np
import torch

from capssim.conventions import N_CHANNELS
from capssim.errors import InputError

from ..model.cagf import DEFAULT_RADIUS, aligned_channel_images, box_mean
from ..model.observation_model import unmix_analyzer

__all__ = ["STRUCTURE_THRESHOLD", "polarization_evidence", "problem_polarization_evidence", "stokes_inconsistency_ratio"]

#: ``T`` below this: the analyzers' differences show polarization structure (the test's null value, module docstring)
STRUCTURE_THRESHOLD = 1.0
#: a local variance per sample (intensity units squared) below which the analyzers do not differ at all
VARIANCE_FLOOR = 1e-20


def stokes_inconsistency_ratio(channels: torch.Tensor, *, radius: int = DEFAULT_RADIUS) -> float:
    """``T`` (module docstring) of aligned channel images ``channels`` ``(12, h, w)`` (channel ``c = 3 p + k``, the
    ideal analyzers' images), local variances over ``(2 radius + 1)^2`` windows; 1.0 for images whose analyzers
    do not differ at all (nothing to tell), and always finite."""
    if channels.ndim != 3 or channels.shape[0] != N_CHANNELS:
        raise InputError("channels", f"shape {tuple(channels.shape)}", "(12, h, w) aligned channel images, c = 3 p + k")
    x = channels.double().reshape(4, 3, *channels.shape[1:])  # analyzers 0, 45, 90, 135 deg; colours

    def local_variance(z: torch.Tensor) -> torch.Tensor:
        mean = box_mean(z, radius)
        return (box_mean(z * z, radius) - mean * mean).clamp(min=0)

    inconsistency = float(local_variance(x[0] - x[1] + x[2] - x[3]).sum())
    difference = float((local_variance(x[0] - x[2]) + local_variance(x[1] - x[3])).sum())
    floor = VARIANCE_FLOOR * x[0].numel()  # below it a sum of local variances is rounding, not structure
    if inconsistency <= floor and difference <= floor:
        return 1.0
    return inconsistency / max(difference, floor)


def polarization_evidence(images: torch.Tensor, homographies, channel_of: torch.Tensor, *,
                          weights: torch.Tensor | None = None, unmix: np.ndarray | None = None,
                          radius: int = DEFAULT_RADIUS, reference: int = 0) -> dict:
    """The test of the module docstring on the observations ``images`` ``(N, h, w)`` of a 12-channel problem,
    aligned onto the reference image as CAGF aligns them (:func:`~capssim.reconstruct.model.cagf.aligned_channel_images`;
    ``homographies``, ``channel_of``, ``weights`` as there), unmixed by ``unmix`` ``(12, 12)`` when given.

    Returns ``{"stokes_inconsistency": T, "structure": T < 1}``."""
    channels = aligned_channel_images(images, homographies, channel_of, N_CHANNELS, weights=weights, reference=reference)
    if unmix is not None:
        channels = unmix_analyzer(channels, unmix)
    ratio = stokes_inconsistency_ratio(channels, radius=radius)
    return {"stokes_inconsistency": ratio, "structure": bool(ratio < STRUCTURE_THRESHOLD)}


def problem_polarization_evidence(problem, *, radius: int = DEFAULT_RADIUS) -> dict:
    """:func:`polarization_evidence` of a pipeline problem (:class:`capssim.reconstruct.pipeline.problem.Problem`:
    its ``seen`` observations, ``homographies`` and ``unmix``); ``{"structure": True}`` (nothing tested) for a problem
    that is not of all 12 channels."""
    seen = problem.seen
    if seen.n_channels != N_CHANNELS:
        return {"structure": True}
    return polarization_evidence(seen.images, problem.homographies, seen.channel_of, weights=seen.weights,
                                 unmix=problem.unmix, radius=radius)
