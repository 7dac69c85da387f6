"""The pyramid of the registration engine (:mod:`capssim.reconstruct.registration.engine`):
its levels, the criterion of each level, the coarse stage and the coarse-to-fine refinement.

* **Pyramid**: 2x2 averages; a pixel stays valid on a coarser level only when its four
  parents are all valid.
* **Coarse stage**: phase correlation of gradient magnitudes (sign-invariant), whose best
  peaks and the zero shift are tried as candidates and judged by the criterion at the
  coarsest level (translation only).
* **Refinement** from the coarsest level to the finest: translation only on the coarse levels,
  the full motion model on the ``full_model_levels`` finest, optional IRLS passes with windows
  weighted by their local R^2 (paper section 3.1, registration). Each L-BFGS run starts from the
  curvature pairs of the previous one of its kind (:class:`~capssim.reconstruct.registration.lbfgs.Memory`).
"""

from __future__ import annotations

import logging
import math
import time

import torch
import torch.nn.functional as F

from ..filters import gaussian_blur
from .criterion import LevelCriterion, minimize
from .image_ops import (
    gradient_magnitude,
    noise_sigma,
    phase_correlation_peaks,
)
from .lbfgs import Memory
from .motion import spline_sample

log = logging.getLogger(__name__)


def pyramid(img: torch.Tensor, valid: torch.Tensor, levels: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """``levels`` 2x2-average levels of ``img`` ``(B, H, W)`` and of its validity mask (1 = usable), finest first."""
    imgs, vals = [img], [valid]
    for _ in range(1, levels):
        a, v = imgs[-1], vals[-1]
        h2, w2 = a.shape[-2] // 2 * 2, a.shape[-1] // 2 * 2
        imgs.append(F.avg_pool2d(a[:, None, :h2, :w2], 2)[:, 0])
        vals.append((F.avg_pool2d(v[:, None, :h2, :w2], 2)[:, 0] > 0.999).to(a.dtype))
    return imgs, vals


def pyramid_level_count(shape: tuple[int, int], *, min_level_size: int, max_levels: int) -> int:
    """Number of pyramid levels (at most ``max_levels``) whose shorter side stays >= ``min_level_size``."""
    levels = 1
    while min(shape) // (2 ** levels) >= min_level_size and levels < max_levels:
        levels += 1
    return levels


class LevelCriteria:
    """The :class:`~capssim.reconstruct.registration.criterion.LevelCriterion` of each pyramid level of
    one registration problem: ``moving`` ``(B, H, W)`` against ``ref`` ``(H, W)``.

    Reference pixels within ``border`` full-resolution pixels of the edge are left out; the
    windows' regularising ``eps`` is set by the largest noise std of the images. ``finest`` is the finest level
    the warps are fitted on (0: full resolution; 1: half resolution, the ``fast`` registration mode); the
    parameters are in full-resolution pixels whatever the level.
    """

    def __init__(self, ref: torch.Tensor, moving: torch.Tensor, ref_valid: torch.Tensor, moving_valid: torch.Tensor,
                 *, model: str, window_radius: int, border: int, levels: int, finest: int = 0):
        hh, ww = ref.shape
        self.model, self.window_radius, self.border, self.levels = model, window_radius, border, levels
        self.finest = min(max(int(finest), 0), levels - 1)
        self.centre = ((ww - 1) / 2.0, (hh - 1) / 2.0)
        self.radius = max(hh, ww) / 2.0
        self.ref, self.ref_valid = pyramid(ref[None], ref_valid[None], levels)
        self.moving, self.moving_valid = pyramid(moving, moving_valid, levels)
        self.noise_sigma = noise_sigma(torch.cat([ref[None], moving]))

    def __call__(self, level: int, stokes_weight: float, model: str | None = None, *,
                 window_radius: int | None = None, robust_power: float = 0.0,
                 images: list[int] | None = None) -> LevelCriterion:
        """The criterion of pyramid ``level`` (0 = finest) with the Stokes term weighted by ``stokes_weight``;
        ``model`` and ``window_radius`` default to the problem's (the radius is capped at a sixth of the level).
        ``images``: only these moving images (their indices; the Stokes term needs all three)."""
        s = 2 ** level
        rv = self.ref_valid[level][0].clone()
        lb = max(1, int(math.ceil(self.border / s)))
        rv[:lb], rv[-lb:], rv[:, :lb], rv[:, -lb:] = 0, 0, 0, 0
        lh, lw = rv.shape
        rad = self.window_radius if window_radius is None else window_radius
        rad = max(1, min(rad, min(lh, lw) // 6))
        eps = float(((2.0 * self.noise_sigma.max()) / s) ** 2) + 1e-12
        moving, moving_valid = self.moving[level], self.moving_valid[level]
        if images is not None:
            moving, moving_valid = moving[images], moving_valid[images]
        return LevelCriterion(self.ref[level][0], moving, rv, moving_valid, scale=s,
                              window_radius=rad, model=self.model if model is None else model, centre=self.centre,
                              radius=self.radius, eps=eps, stokes_weight=stokes_weight, robust_power=robust_power)


def coarse_translation(criteria: LevelCriteria, ref: torch.Tensor, moving: torch.Tensor, *,
                       peaks: int) -> tuple[torch.Tensor, dict]:
    """Starting translations ``(B, 2)`` (full-resolution pixels) and a record of the coarse stage.

    The zero shift and the ``peaks`` highest phase-correlation peaks of the gradient magnitudes
    are each refined (translation, coarsest level) and the one with the highest local R^2 kept.
    """
    b, dev, dtype = moving.shape[0], ref.device, ref.dtype
    gm_ref = gradient_magnitude(gaussian_blur(ref[None], 1.0, padding="replicate"))[0]
    gm_mov = gradient_magnitude(gaussian_blur(moving, 1.0, padding="replicate"))
    shifts, heights = phase_correlation_peaks(gm_ref, gm_mov, peaks=peaks)
    candidates = torch.cat([torch.zeros(b, 1, 2, dtype=dtype, device=dev), shifts], 1)  # (B, K+1, 2)
    crit = criteria(criteria.levels - 1, 0.0, "translation")
    best_score = torch.full((b,), -math.inf, dtype=dtype, device=dev)
    best = torch.zeros(b, 2, dtype=dtype, device=dev)
    tried = []
    for k in range(candidates.shape[1]):
        cand = candidates[:, k]
        if k > 0 and not bool(torch.isfinite(heights[:, k - 1]).any()):
            continue
        pk, _, _ = minimize(crit, cand, max_iterations=15)
        crit.fix_weights(pk)
        with torch.no_grad():
            score = crit.local_r2(spline_sample(crit.coef, crit.coords(pk)))
        score = torch.where(torch.isfinite(score) & torch.isfinite(pk).all(1), score,
                            torch.full_like(score, -math.inf))
        better = score > best_score + 1e-9
        best = torch.where(better[:, None], pk, best)
        best_score = torch.where(better, score, best_score)
        tried.append({"start": cand.tolist(), "converged": pk.tolist(), "local_r2": score.tolist()})
    record = {"phase_correlation_shifts": shifts.tolist(), "phase_correlation_heights": heights.tolist(),
              "candidates": tried, "chosen_shift": best.tolist(), "chosen_local_r2": best_score.tolist()}
    return best, record


def refine_levels(p: torch.Tensor, criteria: LevelCriteria, *, first_level: int, stokes_weight: float,
                  stokes_levels: int, max_iterations: int, full_model_levels: int, robust_power: float,
                  robust_levels: int, robust_passes: int, robust_window_radius: int | None,
                  info: dict) -> torch.Tensor:
    """Coarse-to-fine L-BFGS refinement of the parameters ``p`` ``(B, P)`` from ``first_level`` down to the
    finest level fitted, ``criteria.finest`` (0 unless the registration stops at half resolution).

    The Stokes term (``stokes_weight``) is used on the ``stokes_levels`` finest levels, the full
    motion model on the ``full_model_levels`` finest (translation only above them), and
    ``robust_passes`` IRLS passes on the ``robust_levels`` finest, each counted from ``criteria.finest``.
    One record per level is appended to ``info["levels"]``.
    """
    model = criteria.model
    # L-BFGS curvature carried from one full-model level to the next, and from one IRLS pass to the next
    # (same parameters, finer data or slightly other weights): 40 % fewer evaluations on the finest level
    memory, robust_memory = Memory(), Memory()
    finest = criteria.finest
    for level in range(max(first_level, finest), finest - 1, -1):
        rank = level - finest  # 0 on the finest level fitted
        stokes = stokes_weight if rank < stokes_levels else 0.0
        t1 = time.perf_counter()
        if rank >= full_model_levels and model != "translation":
            # coarse levels: translation only (a Siemens star is nearly invariant to scale and
            # rotation about its centre; the full model from the start drifts along that valley)
            crit = criteria(level, stokes, "translation")
            p_new, iters, evals = minimize(crit, p[:, :2].contiguous(), max_iterations=max_iterations)
            p_new = torch.cat([p_new, p[:, 2:]], 1)
        else:
            crit = criteria(level, stokes)
            p_new, iters, evals = minimize(crit, p, max_iterations=max_iterations, memory=memory)
        if bool(torch.isfinite(p_new).all()):
            p = p_new
        else:
            log.warning("registration: non-finite parameters at pyramid level %d; kept the previous estimate", level)
        if robust_power > 0 and rank < robust_levels:
            rcrit = criteria(level, stokes, robust_power=robust_power, window_radius=robust_window_radius)
            for _ in range(robust_passes):  # IRLS: window weights R^2^k frozen at the current estimate
                p_new, it2, ev2 = minimize(rcrit, p, max_iterations=max_iterations, memory=robust_memory)
                iters, evals = iters + it2, evals + ev2
                if bool(torch.isfinite(p_new).all()):
                    p = p_new
        info["levels"].append({"level": level, "size": list(crit.shape), "window_radius": crit.r,
                               "stokes_weight": stokes, "iterations": iters, "evaluations": evals,
                               "time_s": time.perf_counter() - t1,
                               "valid_pixels": [int(v) for v in crit.weights.sum(dim=(1, 2))]})
    return p
