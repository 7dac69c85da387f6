"""Confidence-guided data term (paper eq. 15-16 and 25-26).

Observation ``m`` sees channel ``c(m)`` through its sampling operator ``M_m`` (warp, PSF,
pixel integration, decimation; ``capssim.operators.lr_sampling_operator`` for CAPS):
``y_m = M_m x_{c(m)} + e_m``. With data weights ``w_m`` (0 at saturated pixels):

* value (the data part of eq. 18): ``f(x) = 1/2 sum_m || w_m (y_m - M_m x_{c(m)}) ||^2``
  (``w_m`` is 0/1, so ``w_m^2 = w_m``);
* back-projected residuals ``B_j = sum_{m: c(m) = j} M_m^T w_m (y_m - M_m x_j)``, i.e.
  ``-grad_{x_j} f``;
* the confidence-guided descent direction of eq. 16 / the data part of eq. 26 for
  channel ``c``: ``D_c = sum_m L^H_{c(m), c} . M_m^T w_m (y_m - M_m x_{c(m)})
  = sum_j L^H_{j, c} . B_j`` (all 16 observations, each weighted per HR pixel by the
  confidence between its channel and ``c``).

With a calibrated array (``mixing``, the ``(N, C)`` analyzer matrix of
:meth:`capssim.camera.rig.RigModel.lr_channel_matrix`) observation m sees ``sum_c A[m, c] x_c`` instead
of ``x_{c(m)}``: ``M_m`` is applied to ``(A x)_m`` and the back-projection is ``A^T`` of the
residuals (exact adjoint; :meth:`ConfidenceDataTerm.forward` / :meth:`ConfidenceDataTerm.adjoint`).
Without ``mixing`` the channel selection is an ``index_select`` (the ideal array, unchanged and as
fast as before).

Without confidence (``confidence=None``, the ``caps-no-cagf`` ablation) ``L^H`` is the
identity and ``D = B = -grad f``. With it, ``D = L^H B`` per pixel: the same fixed
points for the data term alone (``L^H`` has unit diagonal), reached faster because
the channels share residuals where CAGF says their textures agree.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import InputError
from capssim.operators.base import LinearOperator

from .rearrange import Observations

#: sampling density, relative to a fully observed channel's mean, under which an HR pixel counts as unobserved
UNOBSERVED_DENSITY = 1e-2
#: half-width (HR pixels) of the window over which the sampling density is averaged: a 4-pixel sampling period
UNOBSERVED_REACH = 2


def field_of_view_mask(homographies, obs_shape: tuple[int, int], hr_shape: tuple[int, int], *,
                       half_extent: float) -> np.ndarray:
    """``(N, h, w)`` bool: observation pixels whose integration footprint lies inside the HR grid.

    ``homographies`` ``(N, 3, 3)`` map HR reference -> observation pixel coordinates. The
    footprint is the square ``(col, row) +- half_extent`` (observation pixels; 0.125 for a
    Bayer sub-image, whose 2x2 integrated aperture-HR pixel centres sit at +-0.5 HR px,
    0.25 for a full raw frame); all four corners must map into ``[0, W-1] x [0, H-1]``.

    Pixels outside see scene content beyond the reconstructed field of view, which the
    warp operator can only replicate from the border; giving them weight 0 keeps their
    back-projections from piling up on the edge pixels (which makes ``dt = 1`` unstable
    there).
    """
    hm = np.asarray(homographies, dtype=np.float64)
    h, w = obs_shape
    hh, ww = hr_shape
    ys, xs = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    inside = np.ones((hm.shape[0], h, w), dtype=bool)
    inv = np.linalg.inv(hm)
    for sy in (-half_extent, half_extent):
        for sx in (-half_extent, half_extent):
            pts = np.stack([(xs + sx).ravel(), (ys + sy).ravel(), np.ones(xs.size)])
            src = inv @ pts
            den = np.where(np.abs(src[:, 2]) < 1e-12, 1e-12, src[:, 2])
            px, py = src[:, 0] / den, src[:, 1] / den
            ok = (px >= -1e-6) & (px <= ww - 1 + 1e-6) & (py >= -1e-6) & (py <= hh - 1 + 1e-6)
            inside &= ok.reshape(-1, h, w)
    return inside


class ConfidenceDataTerm:
    """Data fidelity of the observations ``obs`` under ``operator`` ``(N, H, W) -> (N, h, w)``.

    ``confidence`` is ``L^H`` ``(C, C, H, W)`` (symmetric) or ``None`` for the identity;
    ``mixing`` ``(N, C)`` what each observation sees of the channels, or ``None``: channel ``c(m)``.
    """

    def __init__(self, obs: Observations, operator: LinearOperator, *, confidence: torch.Tensor | None = None,
                 mixing=None):
        n = obs.count
        if operator.output_shape != tuple(obs.images.shape):
            raise InputError("operator", f"output shape {operator.output_shape}",
                             f"the observations' shape {tuple(obs.images.shape)}")
        if operator.input_shape[0] != n or len(operator.input_shape) != 3:
            raise InputError("operator", f"input shape {operator.input_shape}", f"({n}, H, W)")
        self.obs = obs
        self.operator = operator
        self.hr_shape = tuple(operator.input_shape[1:])
        self.n_channels = obs.n_channels
        if confidence is not None:
            expected = (self.n_channels, self.n_channels, *self.hr_shape)
            if tuple(confidence.shape) != expected:
                raise InputError("confidence", f"shape {tuple(confidence.shape)}", f"shape {expected}")
        self.confidence = confidence
        self.mixing = None
        if mixing is not None:
            self.mixing = torch.as_tensor(np.asarray(mixing), dtype=obs.images.dtype, device=obs.images.device)
            if tuple(self.mixing.shape) != (n, self.n_channels):
                raise InputError("mixing", f"shape {tuple(self.mixing.shape)}", f"shape ({n}, {self.n_channels})")
        self._weighted_y = obs.images * obs.weights
        self._last: tuple | None = None  # (x, x's version, residual): value(x) then descent_direction(x)

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return (self.n_channels, *self.hr_shape)

    def coverage(self, weights: torch.Tensor | None = None) -> torch.Tensor:
        """``(C, H, W)`` sampling density ``sum_{m: c(m)=j} M_m^T w_m`` (the data weights by default)."""
        w = self.obs.weights if weights is None else weights
        bp = self.operator.adjoint(w)
        if self.mixing is not None:
            return torch.einsum("mc,mhw->chw", self.mixing.abs().to(bp.dtype), bp)
        return torch.zeros(self.image_shape, dtype=bp.dtype, device=bp.device).index_add_(0, self.obs.channel_of, bp)

    def unobserved_mask(self, *, min_relative_density: float = UNOBSERVED_DENSITY,
                        reach: int = UNOBSERVED_REACH) -> np.ndarray:
        """``(C, H, W)`` bool: HR pixels with no usable observation.

        The weighted sampling density :meth:`coverage`, averaged over the ``(2 reach + 1)^2``
        window around each pixel (one sampling period of a Bayer sub-image: without a PSF a
        sample touches only its own footprint), is compared with its channel's mean density
        with every weight 1 (all observations in view and unsaturated); below
        ``min_relative_density`` times that, saturated or out-of-view samples (weight 0) leave
        only the data term's zero there, and the output is the prior's or the initialization's.
        """
        window = dict(kernel_size=2 * reach + 1, stride=1, padding=reach, count_include_pad=False)
        usable = F.avg_pool2d(self.coverage()[None], **window)[0]
        full = self.coverage(torch.ones_like(self.obs.weights)).mean(dim=(-2, -1), keepdim=True)
        return (usable < min_relative_density * full.clamp(min=1e-12)).cpu().numpy()

    def residual(self, x: torch.Tensor) -> torch.Tensor:
        """``w_m (y_m - M_m x_{c(m)})`` ``(N, h, w)`` (:meth:`forward` gives ``M_m x_{c(m)}`` or ``M_m (A x)_m``).

        The residual of the last ``x`` is kept (while ``x`` is not modified in place): a solver's
        ``value(x_new)`` followed by ``descent_direction(x_new)`` applies ``M`` once, not twice.
        """
        last = self._last
        if last is not None and last[0] is x and last[1] == x._version:
            return last[2]
        r = self._weighted_y - self.obs.weights * self.forward(x)
        self._last = (x, x._version, r)
        return r

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The observation model ``(C, H, W) -> (N, h, w)``: ``M_m x_{c(m)}``, or ``M_m (A x)_m`` with ``mixing``."""
        if self.mixing is None:
            return self.operator.forward(x.index_select(0, self.obs.channel_of))
        return self.operator.forward(torch.einsum("mc,chw->mhw", self.mixing.to(x.dtype), x))

    def adjoint(self, r: torch.Tensor) -> torch.Tensor:
        """The exact adjoint of :meth:`forward` ``(N, h, w) -> (C, H, W)``: ``sum_{m: c(m)=j} M_m^T r_m``,
        or ``A^T (M^T r)`` with ``mixing``."""
        bp = self.operator.adjoint(r)
        if self.mixing is not None:
            return torch.einsum("mc,mhw->chw", self.mixing.to(bp.dtype), bp)
        return torch.zeros(self.image_shape, dtype=bp.dtype, device=bp.device).index_add_(0, self.obs.channel_of, bp)

    def value(self, x: torch.Tensor) -> float:
        """``f(x) = 1/2 sum_m ||w_m (y_m - M_m x_c(m))||^2`` (``(A x)_m`` for ``x_c(m)`` with ``mixing``)."""
        return 0.5 * float(self.residual(x).square().sum())

    def backprojection(self, x: torch.Tensor, residual: torch.Tensor | None = None) -> torch.Tensor:
        """``B`` ``(C, H, W)``: ``B_j = sum_{m: c(m)=j} M_m^T w_m r_m`` (``sum_m A[m, j] M_m^T w_m r_m`` with
        ``mixing``); equals ``-grad f``."""
        r = self.residual(x) if residual is None else residual
        return self.adjoint(r * self.obs.weights)

    def mix(self, b: torch.Tensor) -> torch.Tensor:
        """The direction ``D`` ``(C, H, W)`` from the back-projection ``B`` ``(C, H, W)``: eq. 26's
        :func:`confidence_mix` with CAGF's confidence, ``B`` itself without it. The one step the structure-aware
        data terms (``cagf-split``, ``cagf-agree``, ``cagf-stokes``) change."""
        if self.confidence is None:
            return b
        return confidence_mix(self.confidence, b)

    def descent_direction(self, x: torch.Tensor) -> tuple[torch.Tensor, float]:
        """Eq. 16 / 26 data part ``D = mix(B)`` ``(C, H, W)`` and the value ``f(x)`` (from the same residual)."""
        r = self.residual(x)
        value = 0.5 * float(r.square().sum())
        return self.mix(self.backprojection(x, r)), value


def confidence_mix(confidence: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``D_c = sum_j L^H_{j, c} . B_j`` per pixel (eq. 26): ``(C, C, H, W)`` and ``(C, H, W)`` -> ``(C, H, W)``.

    One fused multiply-add per source channel: ``einsum`` lowers this to one tiny matrix product per
    pixel, about 10x slower on CPU.
    """
    out = confidence[0] * b[0]
    for j in range(1, b.shape[0]):
        out.addcmul_(confidence[j], b[j])
    return out


__all__ = ["UNOBSERVED_DENSITY", "UNOBSERVED_REACH", "ConfidenceDataTerm", "confidence_mix", "field_of_view_mask"]
