"""The Stokes-subspace data term: the structure-aware direction of ``cagf-agree`` kept to images that linear
polarization can produce (not the paper's; ``-p data_term=cagf-stokes``, the default of ``caps-plus``).

Ideal linear analyzers at 0, 45, 90 and 135 deg see ``I_t = (S0 + S1 cos 2t + S2 sin 2t) / 2`` of each colour, so
the 12 channels of the output hold only 9 unknowns (``S0, S1, S2`` per colour) and obey, per HR pixel and colour::

    I_0 - I_45 + I_90 - I_135 = 0                                   (1)

(Tyo et al., "Review of passive imaging polarimetry for remote sensing applications", Appl. Opt. 45(22), 5453,
2006, section 3: four analyzer angles over-determine the linear Stokes vector). The paper's 12-channel
variable ignores (1), and so does ``cagf-agree``'s direction: the polarization part of the residual seen by the
0 deg aperture moves ``I_0`` only. Under (1) the same residual is evidence on ``S1``, which the 90 deg aperture
sees with the opposite sign at its own sub-pixel offset, so the two apertures together sample ``S1`` (and the
45 and 135 deg apertures ``S2``) on a grid twice as dense as either. That is what polarization-only structure
(the polarization star) needs, where the intensity ``S0`` carries no detail for CAGF to share.

This data term projects the back-projected residual onto the subspace (1) before and after ``cagf-agree``'s
mixing (:func:`~capssim.reconstruct.model.analyzer_agreement.agreement_confidence_mix`, ``T``)::

    D = Q T Q B,        Q b = b - n (n . b) / 4,   n = (1, -1, 1, -1) over the analyzers of one colour

``Q`` is the orthogonal projection onto (1), applied per HR pixel and colour (:func:`stokes_projection`). ``Q T
Q`` is symmetric positive semi-definite where ``T`` is, so ``D`` is a descent direction of the same data term
``f`` (eq. 15), now restricted to the subspace (not its gradient: ADMM's fixed points satisfy
``mu (Z - X) = -D grad f``, docs: notes/caps-plus-model.md). Only the direction changes; the value ``f``, the operator ``M`` and the back-projection are
``cagf-agree``'s. The part of the image outside (1) (from the start or the prior) is left to the physical
projection that ends every run (:mod:`capssim.stokes.physical_validity`). With a calibrated analyzer the variable is
still the ideal analyzers' 12 channels (the calibration's mixing sits in the operator), so (1) holds as well.

Channel order: angle-major, ``c = p K + k`` for the ``A = 4`` analyzers at 0, 45, 90 and 135 deg
(:mod:`capssim.conventions`), ``K`` colours (``caps``: 3; ``caps-iccp``'s per-colour problems: 1).
"""

from __future__ import annotations

import torch

from capssim.errors import InputError

from .analyzer_agreement import AgreementDataTerm

__all__ = ["STOKES_NULL_VECTOR", "StokesAgreementDataTerm", "stokes_projection"]

#: ``n`` of eq. (1), over the analyzers at 0, 45, 90 and 135 deg: ``n . (I_0, I_45, I_90, I_135) = 0`` for every
#: linear polarization state
STOKES_NULL_VECTOR = (1.0, -1.0, 1.0, -1.0)


def stokes_projection(b: torch.Tensor) -> torch.Tensor:
    """``Q b``: ``b`` ``(4 K, H, W)`` (angle-major, analyzers at 0/45/90/135 deg) without its component along
    :data:`STOKES_NULL_VECTOR` for each colour and pixel -> ``(4 K, H, W)``, which obeys eq. (1) of the module
    docstring exactly (to rounding). Idempotent and self-adjoint."""
    n_angles = len(STOKES_NULL_VECTOR)
    if b.ndim != 3 or b.shape[0] % n_angles:
        raise InputError("b", f"shape {tuple(b.shape)}", f"(C, H, W) with C a multiple of the {n_angles} analyzers")
    per_angle = b.reshape(n_angles, b.shape[0] // n_angles, *b.shape[1:])
    n = torch.tensor(STOKES_NULL_VECTOR, dtype=b.dtype, device=b.device).reshape(n_angles, 1, 1, 1)
    along = (per_angle * n).sum(dim=0, keepdim=True) / n_angles  # (n . b) / |n|^2, |n|^2 = 4
    return (per_angle - n * along).reshape(b.shape)


class StokesAgreementDataTerm(AgreementDataTerm):
    """The data term of eq. 15 with the direction ``Q T Q B`` (module docstring), ``T`` ``cagf-agree``'s mixing.

    Same observations, operator, value, back-projection, ``confidence`` ``(C, C, H, W)`` and ``agreement``
    ``(H, W)`` as :class:`~capssim.reconstruct.model.analyzer_agreement.AgreementDataTerm`; the image has
    ``C = 4 K`` channels for the analyzers at 0, 45, 90 and 135 deg.
    """

    def __init__(self, obs, operator, *, confidence: torch.Tensor, agreement: torch.Tensor, mixing=None):
        super().__init__(obs, operator, confidence=confidence, agreement=agreement, mixing=mixing,
                         n_angles=len(STOKES_NULL_VECTOR))

    def mix(self, b: torch.Tensor) -> torch.Tensor:
        """``D = Q T Q b`` ``(C, H, W)`` (module docstring) from the back-projection ``b``."""
        return stokes_projection(super().mix(stokes_projection(b)))
