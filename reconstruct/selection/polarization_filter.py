"""The polarization part of a 12-channel image, guided-filtered by its intensity, with the filter chosen by
held-out raw pixels or by the Stokes-consistency test (``caps-plus``'s last step, ``-p polarization_filter=auto``;
not the paper's).

Write the image of colour ``k`` as its analyzer mean ``m_k = (1/4) sum_p I_{p,k}`` (intensity, ``S0 / 2``) and
each analyzer's deviation from it, ``d_{p,k} = I_{p,k} - m_k`` (the polarization part: ``S1``, ``S2`` seen through
analyzer ``p``). The noise a solver leaves in ``d`` is what the DoLP and AoP of dark and unpolarized regions show.
The step replaces ``d_{p,k}`` by its guided filter with ``m_k`` as the guide (He, Sun and Tang, "Guided image
filtering", IEEE TPAMI 35(6) 2013, eq. 1-8, box windows of radius ``r`` HR pixels, regularizer ``eps``):
polarization edges that follow intensity edges are kept, and a small ``eps`` keeps more of them. The analyzer
mean is not changed (the filtered deviations are re-centred to sum to 0 over the analyzers).

A fixed filter smooths real polarization structure where the intensity does not show it (polarization stars,
the cellphone cases; docs: notes/beyond-the-paper.md, section 9), so the filter is chosen per capture: each
candidate of :data:`POLARIZATION_FILTERS` is applied to the held-out validation's best iterate
(:class:`~capssim.reconstruct.selection.holdout.HoldoutValidation`), its held-out raw pixels are predicted through
``M`` (eq. 15), and the candidate with the lowest mean error is taken only if it lowers the error by more than one
standard error of the paired per-sample differences (else no filter). The chosen filter is then applied to the
final image, before the physical projection.

The held-out pixels cannot judge a capture whose analyzers differ only by the apertures' own errors: the raw frames
differ by detail the HR grid cannot hold (aliasing each aperture samples differently), the 12-channel image can only
explain it as polarization, and the held-out pixels reward that false polarization (docs: notes/beyond-the-paper.md,
sections 16-18). So the selection first asks the Stokes-consistency test
(:mod:`capssim.reconstruct.selection.polarization_evidence`) whether the analyzers show polarization structure at all;
where they do not, the final image gets :data:`UNSTRUCTURED_FILTER`, the most smoothing candidate, and the held-out
pixels choose nothing.
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from capssim.conventions import N_CHANNELS
from capssim.errors import InputError

from ..model.cagf import box_mean

__all__ = ["POLARIZATION_FILTERS", "UNSTRUCTURED_FILTER", "apply_chosen_filter", "choose_polarization_filter",
           "filter_polarization"]

#: the candidate ``(radius HR px, eps)`` pairs, from the lightest to the most smoothing (``eps`` in intensity
#: units squared, on the [0, 1] scale; ``eps = 1e-2`` is close to a box mean)
POLARIZATION_FILTERS = ((1, 1e-4), (2, 1e-4), (2, 1e-3), (4, 1e-4), (4, 1e-3), (4, 1e-2))
#: the filter of a capture whose analyzers show no polarization structure: the most smoothing candidate
UNSTRUCTURED_FILTER = POLARIZATION_FILTERS[-1]


def filter_polarization(image: torch.Tensor, radius: int, eps: float) -> torch.Tensor:
    """``(12, H, W)``: ``image`` (channel ``c = 3 p + k``) with each analyzer's deviation from its colour's analyzer
    mean guided-filtered by that mean (module docstring); the analyzer means unchanged. ``radius`` 0 returns a copy."""
    if image.ndim != 3 or image.shape[0] != N_CHANNELS:
        raise InputError("image", f"shape {tuple(image.shape)}", "(12, H, W), channel c = 3 p + k")
    if int(radius) <= 0:
        return image.clone()
    four = image.reshape(4, 3, *image.shape[1:])
    mean = four.mean(dim=0)  # (3, H, W) the guide
    deviation = four - mean
    guide = mean.expand_as(deviation)
    mean_g, mean_d = box_mean(guide, radius), box_mean(deviation, radius)
    var_g = torch.clamp(box_mean(guide * guide, radius) - mean_g * mean_g, min=0)
    slope = (box_mean(guide * deviation, radius) - mean_g * mean_d) / (var_g + eps)
    offset = mean_d - slope * mean_g
    filtered = box_mean(slope, radius) * guide + box_mean(offset, radius)
    filtered = filtered - filtered.mean(dim=0, keepdim=True)  # keep the analyzer mean exactly
    return (mean + filtered).reshape(image.shape)


def choose_polarization_filter(sample_errors: Callable[[torch.Tensor], torch.Tensor], image: torch.Tensor, *,
                               filters=POLARIZATION_FILTERS) -> dict:
    """The filter of ``filters`` whose held-out error is lowest, if it beats no filter by more than one standard
    error; ``{"radius": 0, "eps": 0.0}`` otherwise.

    ``sample_errors(image) -> (n,)``: each held-out sample's weighted squared prediction error (the same samples, in
    the same order, for every image). The result also lists every candidate's relative change of the mean error
    (``candidates``)."""
    base = sample_errors(image).double()
    n, base_mean = base.numel(), float(base.mean())
    rows, best = [], None
    for radius, eps in filters:
        diff = sample_errors(filter_polarization(image, radius, eps)).double() - base
        mean, se = float(diff.mean()), float(diff.std()) / math.sqrt(max(n, 1))
        rows.append({"radius": int(radius), "eps": float(eps), "relative_change": mean / base_mean if base_mean else 0.0})
        if mean + se < 0 and (best is None or mean < best[0]):
            best = (mean, int(radius), float(eps))
    chosen = {"radius": 0, "eps": 0.0} if best is None else {"radius": best[1], "eps": best[2]}
    return {**chosen, "candidates": rows}


def apply_chosen_filter(image: torch.Tensor, choice) -> torch.Tensor:
    """``image`` filtered as ``choice`` (:func:`choose_polarization_filter`'s result) names; unchanged for ``None``,
    radius 0 or an image that is not 12-channel."""
    if not choice or int(choice.get("radius", 0)) <= 0 or image.ndim != 3 or image.shape[0] != N_CHANNELS:
        return image
    return filter_polarization(image, int(choice["radius"]), float(choice["eps"]))
