"""Polarization-split CAGF data term: the residual's angle mean is shared by every channel, its
polarization part only within one analyzer (not the paper's; used by ``caps-plus``).

The paper's data direction (eq. 26) mixes the back-projected residuals ``B`` of all channels with the
CAGF confidence ``L^H`` (:func:`capssim.reconstruct.model.data_term.confidence_mix`): ``D = L^H B`` per
HR pixel. Every weight is >= 0, so a residual seen at one analyzer pushes the other analyzers' images
the same way. That is right for the part of the residual all analyzers share (an error of the
intensity ``S0``), and wrong for its polarization part: where ``I_0`` must rise, ``I_90`` must fall.
On polarization-only structure (the polarization-star scene), or wherever the analyzer images differ
(the cellphone cases), eq. 26 smears the difference away; see the error-budget notes.

This data term splits ``B`` per HR pixel and colour ``k`` into its mean over the ``A`` analyzer angles
and the rest, with the orthogonal projection ``P`` (``(P B)_{p,k} = 1/A sum_q B_{q,k}``), and mixes
the two parts with different couplings::

    D = P L^H P B  +  (I - P) L^H_angle (I - P) B

* ``L^H`` is CAGF's confidence between all channel pairs (eq. 12-14), as in ``caps``;
* ``L^H_angle`` keeps only the pairs of one analyzer angle (the colours of one aperture), zero
  elsewhere: the polarization part is shared between the colours of an analyzer, never across
  analyzers.

``D`` is ``T B`` with ``T`` symmetric and positive semi-definite when ``L^H`` is (``P`` and ``I - P``
are orthogonal projections, and ``L^H_angle`` is ``L^H``'s block diagonal), so it is a descent
direction of the same data term ``f`` (eq. 15); as a direction other than the gradient it also moves ADMM's
fixed points (``mu (Z - X) = -D grad f``, docs: notes/caps-plus-model.md).
Where the analyzer images agree (``(I - P) B = 0``) it is eq. 26 projected on the angle mean.

Channel order: angle-major, ``c = p K + k`` (``p`` the analyzer, ``k`` one of the ``K = C / A``
colours): ``caps``'s 12 channels (``K = 3``) and ``caps-iccp``'s per-colour problems (``K = 1``,
where ``L^H_angle`` is the identity).
"""

from __future__ import annotations

import torch

from capssim.errors import InputError

from .data_term import ConfidenceDataTerm, confidence_mix

__all__ = ["N_ANGLES", "PolarizationSplitDataTerm", "angle_mean", "split_confidence_mix"]

#: analyzer angles of the array (0, 45, 90, 135 deg)
N_ANGLES = 4


def angle_mean(b: torch.Tensor, n_angles: int = N_ANGLES) -> torch.Tensor:
    """``P b``: each channel replaced by the mean over the ``n_angles`` analyzers of its colour.

    ``b`` ``(C, H, W)`` in angle-major order (``c = p K + k``, ``C = n_angles K``) -> ``(C, H, W)``.
    """
    c = b.shape[0]
    per_angle = b.reshape(n_angles, c // n_angles, *b.shape[1:])
    return per_angle.mean(dim=0, keepdim=True).expand_as(per_angle).reshape(b.shape)


def split_confidence_mix(confidence: torch.Tensor, b: torch.Tensor, n_angles: int = N_ANGLES) -> torch.Tensor:
    """``D = P L P b + (I - P) L_angle (I - P) b`` per pixel (module docstring).

    ``confidence`` ``(C, C, H, W)`` (``L^H``, symmetric), ``b`` ``(C, H, W)`` -> ``(C, H, W)``.
    """
    c = b.shape[0]
    if c % n_angles:
        raise InputError("channels", c, f"a multiple of the {n_angles} analyzer angles (angle-major order)")
    k = c // n_angles
    mean = angle_mean(b, n_angles)
    polarization = b - mean
    shared = angle_mean(confidence_mix(confidence, mean), n_angles)
    within = torch.empty_like(b)
    for p in range(n_angles):  # L_angle is block diagonal: the colours of one analyzer
        block = slice(p * k, (p + 1) * k)
        within[block] = confidence_mix(confidence[block, block], polarization[block])
    return shared + within - angle_mean(within, n_angles)


class PolarizationSplitDataTerm(ConfidenceDataTerm):
    """The data term of eq. 15 with the polarization-split direction :func:`split_confidence_mix`.

    Same observations, operator, value ``f(x)`` and back-projection as
    :class:`~capssim.reconstruct.model.data_term.ConfidenceDataTerm`; only
    :meth:`mix` differs. ``confidence`` ``(C, C, H, W)`` is required.
    """

    def __init__(self, obs, operator, *, confidence: torch.Tensor, mixing=None, n_angles: int = N_ANGLES):
        if confidence is None:
            raise InputError("confidence", None, "a CAGF confidence (C, C, H, W)",
                             "Use data_term=plain for a data term without confidence.")
        super().__init__(obs, operator, confidence=confidence, mixing=mixing)
        if self.n_channels % n_angles:
            raise InputError("channels", self.n_channels, f"a multiple of the {n_angles} analyzer angles")
        self.n_angles = n_angles

    def mix(self, b: torch.Tensor) -> torch.Tensor:
        """``D`` ``(C, H, W)`` (module docstring) from the back-projection ``b``."""
        return split_confidence_mix(self.confidence, b, self.n_angles)
