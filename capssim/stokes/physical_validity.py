"""Projection of a 12-channel estimate onto the physically valid set (ideal linear analyzers).

For one colour at one pixel the four analyzer intensities ``I = (I0, I45, I90, I135)`` of any
partially polarized light are ``I = M s`` with ``M`` the rows ``(1, cos 2a, sin 2a) / 2`` (paper
eq. 1-2) and ``s = (S0, S1, S2)`` in the cone ``sqrt(S1^2 + S2^2) <= S0``. Physically valid
intensities therefore satisfy

* ``I0 + I90 = I45 + I135`` (both are ``S0``), and
* ``DoLP <= 1``, which makes every ``I(a) = S0 (1 + DoLP cos(2a - 2 AoP)) / 2 >= 0``.

:func:`project_to_physical` returns the nearest such intensities in the Euclidean norm of the 12
channels. ``M^T M = diag(1, 1/2, 1/2)``, so the least-squares Stokes fit (the usual
``S0 = sum / 2``, ``S1 = I0 - I90``, ``S2 = I45 - I135``) is the orthogonal projection onto the
consistent subspace, and the remaining step is the projection onto the cone in the metric
``dS0^2 + (dS1^2 + dS2^2) / 2``. Where ``P = sqrt(S1^2 + S2^2) > S0`` that is (with the AoP kept)

    ``S0' = P' = max(0, (2 S0 + P) / 3)``,

i.e. the light becomes fully polarized (DoLP 1) or, for ``2 S0 + P <= 0``, dark.

Pixels that a mask marks unobserved are left as they are (with their colour's other angles), so a
report of unobserved pixels still describes the output.

Reference: the second-order-cone projection, e.g. Bauschke & Combettes, *Convex Analysis and
Monotone Operator Theory in Hilbert Spaces* (2nd ed., 2017), example 29.33, with the cone scaled
by the metric above.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from capssim.conventions import N_CHANNELS
from capssim.errors import InputError
from capssim.stokes.polarization import split_12, stokes_from_intensities, twelve_from_stokes


@dataclass(frozen=True)
class ProjectionReport:
    """What :func:`project_to_physical` changed, as fractions of the checked pixels (all colours).

    ``negative_fraction``: intensities below 0 before; ``inconsistent_rms``: RMS of
    ``(I0 + I90 - I45 - I135) / 2`` before; ``over_polarized_fraction``: pixels with DoLP > 1
    after the consistency step; ``change_rms``: RMS change of the 12 channels.
    """

    negative_fraction: float
    inconsistent_rms: float
    over_polarized_fraction: float
    change_rms: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def _cone_projection(stokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project ``(3, ...)`` Stokes onto ``P <= S0`` in the metric ``dS0^2 + dP^2 / 2``; also the mask of changed pixels."""
    s0, s1, s2 = stokes
    p = np.hypot(s1, s2)
    outside = p > s0
    new_s0 = np.maximum((2.0 * s0 + p) / 3.0, 0.0)
    ratio = np.divide(new_s0, p, out=np.zeros_like(p), where=p > 0)
    out = np.where(outside[None], np.stack([new_s0, s1 * ratio, s2 * ratio]), stokes)
    return out, outside


def project_to_physical(image12: np.ndarray, *, unobserved: np.ndarray | None = None
                        ) -> tuple[np.ndarray, ProjectionReport]:
    """Nearest physically valid intensities to a 12-channel image.

    Parameters
    ----------
    image12 : numpy.ndarray
        ``(12, H, W)`` intensities, channel ``c = 3 p + k``.
    unobserved : numpy.ndarray, optional
        ``(12, H, W)`` bool; a colour's four angles at a pixel are left unchanged where any is unobserved.

    Returns
    -------
    image : numpy.ndarray
        ``(12, H, W)`` float32: every checked intensity ``>= 0``, ``I0 + I90 = I45 + I135`` to float32
        rounding and DoLP <= 1.
    report : ProjectionReport
        What changed, as fractions of the checked pixels.
    """
    if image12.ndim != 3 or image12.shape[0] != N_CHANNELS:
        raise InputError("image12", f"shape {tuple(image12.shape)}", "(12, H, W), channel c = 3*p + k")
    x = np.asarray(image12, dtype=np.float32)
    four = split_12(x)  # (4 angles, 3 colours, H, W)
    inconsistent = (four[0] + four[2] - four[1] - four[3]) / 2
    valid, over = _cone_projection(stokes_from_intensities(four, axis=0))
    projected = np.maximum(twelve_from_stokes(valid), 0.0)  # only rounding below 0 is left
    kept_groups = np.zeros(four.shape[1:], dtype=bool)  # (3 colours, H, W): left unchanged
    if unobserved is not None:
        if unobserved.shape != x.shape:
            raise InputError("unobserved", f"shape {tuple(unobserved.shape)}", f"the image's shape {tuple(x.shape)}")
        kept_groups = split_12(np.asarray(unobserved, dtype=bool)).any(axis=0)
    keep = np.broadcast_to(kept_groups[None], four.shape).reshape(x.shape)
    out = np.where(keep, x, projected)
    checked = ~keep
    n = max(int(checked.sum()), 1)
    n_pix = max(int((~kept_groups).sum()), 1)
    report = ProjectionReport(
        negative_fraction=float(((x < 0) & checked).sum() / n),
        inconsistent_rms=float(np.sqrt(np.sum(np.where(kept_groups, 0.0, inconsistent) ** 2) / n_pix)),
        over_polarized_fraction=float((over & ~kept_groups).sum() / n_pix),
        change_rms=float(np.sqrt(np.sum((out - x) ** 2) / n)),
    )
    return out.astype(np.float32), report
