"""The image-registration engine behind :mod:`capssim.reconstruct.registration` (device-agnostic torch).

:func:`register_stack` registers a batch of *moving* images to one *reference* image whose
intensities may differ from theirs in a spatially varying way (other polarizer angles, other
colours), in the order of paper section 3.1's registration step:

1. **coarse stage**: phase-correlation candidates judged at the coarsest pyramid level
   (:func:`~capssim.reconstruct.registration.levels.coarse_translation`);
2. **refinement** on a 2x2-average pyramid, minimised with L-BFGS through autograd
   (:func:`~capssim.reconstruct.registration.levels.refine_levels`) of the local-correlation and
   Stokes-consistency criterion (:mod:`~capssim.reconstruct.registration.criterion`), with
   cubic-spline interpolation and the motion models of :mod:`~capssim.reconstruct.registration.motion`;
3. **rescues** of images that still match poorly: more phase-correlation peaks, then a joint
   re-run dominated by the Stokes consistency (:mod:`~capssim.reconstruct.registration.rescue`);
4. optionally the **Stokes-subspace refinement** (same module).

All coordinates are ``(x=col, y=row)`` with pixel centres on integers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from capssim.errors import InputError, UnknownNameError

from .criterion import final_fit, stokes_residual_rms
from .levels import (
    LevelCriteria,
    coarse_translation,
    pyramid_level_count,
    refine_levels,
)
from .motion import (
    MOTION_MODELS,
    params_to_matrices,
    spline_coefficients,
    spline_sample,
)
from .rescue import (
    rescue_from_more_peaks,
    stokes_joint_rescue,
    stokes_subspace_refine,
)

#: the engine's public names (the interpolation is also used by :mod:`capssim.eval.gt_check`)
__all__ = ["MOTION_MODELS", "StackRegistration", "params_to_matrices", "register_stack", "spline_coefficients",
           "spline_sample", "stokes_residual_rms"]


@dataclass
class StackRegistration:
    """Result of :func:`register_stack`: ``params`` ``(B, P)`` (full-resolution pixels of displacement at the
    image radius), ``matrices`` ``(B, 3, 3)`` (reference pixel -> moving pixel), ``correlation`` ``(B,)`` (final
    local R^2) and ``info`` (per-stage records)."""

    params: np.ndarray
    matrices: np.ndarray
    correlation: np.ndarray
    info: dict = field(default_factory=dict)


def register_stack(ref: torch.Tensor, moving: torch.Tensor, *, ref_valid: torch.Tensor | None = None,
                   moving_valid: torch.Tensor | None = None, model: str = "similarity", window_radius: int = 3,
                   stokes_weight: float = 0.0, stokes_levels: int = 2, max_iterations: int = 60,
                   min_level_size: int = 24, max_levels: int = 5, coarse_peaks: int = 3,
                   border: int = 3, initial: torch.Tensor | None = None, robust_power: float = 0.0,
                   robust_levels: int = 2, robust_passes: int = 2, full_model_levels: int = 2,
                   rescue_below: float = 0.7, rescue_peaks: int = 8, stokes_subspace_std: float = 0.0,
                   stokes_subspace_iterations: int = 4, robust_window_radius: int | None = None,
                   start_level: int | None = None, half_resolution_min_size: int = 0) -> StackRegistration:
    """Register ``moving`` ``(B, H, W)`` to ``ref`` ``(H, W)`` (float64 tensors on one device).

    ``ref_valid``/``moving_valid`` (1 = usable pixel) mask saturated or otherwise bad pixels.
    ``stokes_weight > 0`` adds the Stokes-consistency term on the finest ``stokes_levels``
    levels; it needs ``B == 3`` moving images at 45, 90, 135 deg and a 0 deg reference.
    ``border``: reference pixels this close to the edge are ignored (full-resolution pixels).
    ``initial``: ``(B, P)`` starting parameters (skips the coarse stage and the phase-correlation
    rescue; the Stokes-consistency rescue still runs unless ``rescue_below = 0``);
    ``start_level`` (only with ``initial``): the pyramid level the refinement starts on, 0 = finest
    (default: the coarsest). Images whose final local R^2 is below ``rescue_below`` are rescued
    (``rescue_peaks`` phase-correlation peaks, then the Stokes-consistency re-run).
    ``stokes_subspace_std > 0`` (needs ``B == 3``) ends with
    :func:`~capssim.reconstruct.registration.rescue.stokes_subspace_refine`.
    ``half_resolution_min_size > 0``: the warps are fitted down to the half-resolution pyramid level only wherever
    that level's shorter side has at least this many pixels (the ``fast`` mode; 4x fewer pixels per evaluation);
    the restarts and the final local R^2 stay at full resolution (:func:`~.rescue.rescue_from_more_peaks`).
    """
    t0 = time.perf_counter()
    dev, dtype = ref.device, ref.dtype
    b = moving.shape[0]
    if model not in MOTION_MODELS:
        raise UnknownNameError("motion model", model, list(MOTION_MODELS))
    if stokes_weight > 0 and b != 3:
        raise InputError("stokes_weight", stokes_weight, "0 unless there are exactly 3 moving images (45, 90, 135 deg)")
    if start_level is not None and (initial is None or not 0 <= start_level):
        raise InputError("start_level", start_level, "an integer >= 0, and only together with initial parameters")
    ref_valid = torch.ones_like(ref) if ref_valid is None else ref_valid.to(dtype)
    moving_valid = torch.ones_like(moving) if moving_valid is None else moving_valid.to(dtype)
    levels = pyramid_level_count(ref.shape, min_level_size=min_level_size, max_levels=max_levels)
    finest = int(half_resolution_min_size > 0 and levels > 1 and min(ref.shape) // 2 >= half_resolution_min_size)
    criteria = LevelCriteria(ref, moving, ref_valid, moving_valid, model=model, window_radius=window_radius,
                             border=border, levels=levels, finest=finest)
    info: dict = {"levels": [], "pyramid_levels": levels, "finest_level": finest,
                  "noise_sigma": [float(v) for v in criteria.noise_sigma]}

    t_coarse = time.perf_counter()
    if initial is None:
        p = torch.zeros(b, MOTION_MODELS[model], dtype=dtype, device=dev)
        p[:, :2], info["coarse"] = coarse_translation(criteria, ref, moving, peaks=coarse_peaks)
    else:
        p = initial.to(dev, dtype).clone()
    info["time_coarse_s"] = time.perf_counter() - t_coarse

    p = refine_levels(p, criteria, first_level=levels - 1 if start_level is None else min(start_level, levels - 1),
                      stokes_weight=stokes_weight, stokes_levels=stokes_levels, max_iterations=max_iterations,
                      full_model_levels=full_model_levels, robust_power=robust_power, robust_levels=robust_levels,
                      robust_passes=robust_passes, robust_window_radius=robust_window_radius, info=info)
    if rescue_below > 0 and initial is None:
        p = rescue_from_more_peaks(p, ref, moving, criteria, threshold=rescue_below, peaks=rescue_peaks,
                                   max_iterations=max_iterations, info=info)
    if rescue_below > 0 and b == 3:
        def refine(q, weight):
            return register_stack(ref, moving, ref_valid=ref_valid, moving_valid=moving_valid, model=model,
                                  window_radius=window_radius, stokes_weight=weight, stokes_levels=levels,
                                  max_iterations=max_iterations, min_level_size=min_level_size,
                                  max_levels=max_levels, border=border, initial=q, robust_power=0.0,
                                  full_model_levels=full_model_levels, rescue_below=0.0,
                                  half_resolution_min_size=half_resolution_min_size)

        p = stokes_joint_rescue(p, criteria, threshold=rescue_below, refine=refine, info=info)
    if stokes_subspace_std > 0 and b == 3:
        p = stokes_subspace_refine(p, criteria, max_std=stokes_subspace_std, iterations=stokes_subspace_iterations,
                                   info=info)
    r2, stokes_rms = final_fit(criteria, p, stokes=b == 3)
    if stokes_rms is not None:
        info["stokes_residual_rms"] = stokes_rms
    g = params_to_matrices(p, model, criteria.centre, criteria.radius)
    info["time_s"] = time.perf_counter() - t0
    return StackRegistration(params=p.cpu().numpy(), matrices=g.cpu().numpy(), correlation=r2.cpu().numpy(),
                             info=info)
