"""Rescues and the last refinement of the registration engine (:mod:`capssim.reconstruct.registration.engine`).

* **Restart from more peaks** (:func:`rescue_from_more_peaks`): images that still match poorly
  after the pyramid (a wrong basin: periodic or self-similar targets) restart from more
  phase-correlation peaks.
* **Stokes-consistency rescue** (:func:`stokes_joint_rescue`): analyzer images that still
  match the 0 deg image poorly (strong polarization texture, e.g. photoelastic fringes) take
  their warps from a joint re-run dominated by ``I0 + I90 = I45 + I135``.
* **Stokes-subspace refinement** (:func:`stokes_subspace_refine`, optional): the
  local-correlation term is biased wherever DoLP/AoP vary (the analyzer images then differ in
  shape, not only in gain), while the Stokes term alone is unbiased for physically consistent
  data but does not fix every direction. A last Gauss-Newton stage on the Stokes residual alone
  moves the parameters only along the directions it determines to within ``max_std`` px
  (noise-predicted). It assumes ``I0 + I90 = I45 + I135`` holds in the data with equal aperture
  gains: true for rendered scenes and for ground truths that obey it, not for ground truths
  taken as four sequential rotating-polarizer shots.

``criteria(level, stokes_weight, model)`` is a
:class:`~capssim.reconstruct.registration.levels.LevelCriteria`.
"""

from __future__ import annotations

import math

import torch

from .criterion import final_fit, minimize
from .image_ops import gradient_magnitude, phase_correlation_peaks
from .motion import spline_sample


def rescue_from_more_peaks(p: torch.Tensor, ref: torch.Tensor, moving: torch.Tensor, criteria, *, threshold: float,
                           peaks: int, max_iterations: int, info: dict, margin: float = 0.02) -> torch.Tensor:
    """Images whose final local R^2 is below ``threshold`` (a wrong basin: periodic or
    self-similar targets such as a Siemens star) restart from more phase-correlation peaks of
    the full-resolution gradient images, each refined on the finest level (translation, then
    the full model); the restart is kept when its final R^2 is higher by ``margin``. Only those
    images are restarted: without the Stokes term the criterion treats each image on its own, so
    the well-matched ones need not be carried through the restarts (on 36 development captures the
    same warps, bit for bit on 29 and within 0.012 HR px on the rest, at 0.6-0.85x the time where
    some image is restarted; docs: notes/registration.md). When the warps are fitted at half resolution
    (``criteria.finest`` 1, the ``fast`` mode), only the images whose best start beats the current estimate there by
    ``margin`` are refined at full resolution (``record["promising"]``)."""
    r2, _ = final_fit(criteria, p)
    bad = ~(r2 >= threshold)
    record = {"threshold": threshold, "r2_before": r2.tolist(), "rescued": []}
    if not bool(bad.any()):
        info["rescue"] = record
        return p
    images = [int(i) for i in torch.nonzero(bad).flatten()]
    shifts, _ = phase_correlation_peaks(gradient_magnitude(ref[None])[0], gradient_magnitude(moving[images]),
                                        peaks=peaks)
    # every start refined by translation on level 1 (cheap) and scored there; the best start per
    # image is then refined with the full model on level 0 and kept if it beats the old estimate
    lvl = 1 if criteria.levels > 1 else 0
    best_t, best_s = p[images, :2].clone(), torch.full_like(r2[images], -math.inf)
    crit_t = criteria(lvl, 0.0, "translation", images=images)
    for k in range(shifts.shape[1]):
        pt, _, _ = minimize(crit_t, shifts[:, k].contiguous(), max_iterations=30)
        crit_t.fix_weights(pt)
        with torch.no_grad():
            score = crit_t.local_r2(spline_sample(crit_t.coef, crit_t.coords(pt)))
        take = torch.isfinite(pt).all(1) & (score > best_s)
        best_t = torch.where(take[:, None], pt, best_t)
        best_s = torch.where(take, score, best_s)
    if criteria.finest > 0:  # fast mode: only starts that beat the current estimate where they were scored go on
        promising = _beats_current(criteria, lvl, p, images, best_s, margin)
        record["promising"] = [i for i, ok in zip(images, promising.tolist()) if ok]
        if not bool(promising.any()):
            record["r2_after"] = r2.tolist()
            info["rescue"] = record
            return p
        best_t, images = best_t[promising], record["promising"]
    start = torch.cat([best_t, torch.zeros_like(p[images, 2:])], 1)
    cand, _, _ = minimize(criteria(0, 0.0, images=images), start, max_iterations=max_iterations)
    score, _ = final_fit(lambda level, weight: criteria(level, weight, images=images), cand)
    take = torch.isfinite(cand).all(1) & (score > r2[images] + margin)
    p, r2 = p.clone(), r2.clone()
    p[images] = torch.where(take[:, None], cand, p[images])
    r2[images] = torch.where(take, score, r2[images])
    record["rescued"] = [i for i, kept in zip(images, take.tolist()) if kept]
    record["r2_after"] = r2.tolist()
    info["rescue"] = record
    return p


def _beats_current(criteria, level: int, p: torch.Tensor, images: list[int], scores: torch.Tensor,
                   margin: float) -> torch.Tensor:
    """``(len(images),)`` bool: the restarts' best ``scores`` (local R^2 on ``level``) beat the current estimate's
    there by ``margin``. The ``fast`` mode refines only those at full resolution: on a frame whose analyzer images
    match poorly for want of texture rather than from a wrong basin (a low-contrast 2560x2048 synthetic scene, the
    512 px polarization star) every start lands where the pyramid did, and refining them cost most of the time."""
    crit = criteria(level, 0.0, images=images)
    crit.fix_weights(p[images])
    with torch.no_grad():
        current = crit.local_r2(spline_sample(crit.coef, crit.coords(p[images])))
    return torch.isfinite(scores) & (scores > current + margin)


def stokes_joint_rescue(p: torch.Tensor, criteria, *, threshold: float, refine, info: dict, weight: float = 100.0,
                        margin: float = 0.1) -> torch.Tensor:
    """Analyzer images that still match the 0 deg reference poorly (local R^2 below ``threshold``
    after :func:`rescue_from_more_peaks`; strong polarization texture such as photoelastic fringes
    makes them look unlike the 0 deg image, and the local correlation then settles pixels off) take their
    parameters from a joint re-run, started from the current estimate, in which the Stokes
    consistency ``I0 + I90 = I45 + I135`` (weight ``weight``, on every pyramid level) dominates
    the local correlation: that residual does not care how unlike the 0 deg image an analyzer
    image looks. Kept when the Stokes residual (rms, finest level) falls by more than
    ``margin`` (relative); the well-matched images keep their estimates. Works for one, two or
    three poorly matched images. ``refine(p, weight)`` re-runs the engine from ``p`` with that
    Stokes weight on every level."""
    r2, before = final_fit(criteria, p, stokes=True)
    bad = ~(r2 >= threshold)
    record = {"threshold": threshold, "weight": weight, "images": [int(i) for i in torch.nonzero(bad).flatten()]}
    info["stokes_joint"] = record
    if not bool(bad.any()):
        return p
    joint = torch.as_tensor(refine(p, weight).params, dtype=p.dtype, device=p.device)
    cand = torch.where(bad[:, None], joint, p)
    if not bool(torch.isfinite(cand).all()):
        record["skipped"] = "non-finite parameters"
        return p
    r2_after, after = final_fit(criteria, cand, stokes=True)
    take = after < (1.0 - margin) * before
    record.update({"stokes_rms_before": before, "stokes_rms_after": after, "r2_after": r2_after.tolist(),
                   "kept": bool(take)})
    return cand if take else p


def stokes_subspace_refine(p: torch.Tensor, criteria, *, max_std: float, iterations: int, info: dict) -> torch.Tensor:
    """Gauss-Newton steps on the Stokes residual ``I0 + I90 - I45 - I135`` alone (finest level),
    restricted to the eigen-directions of its Gauss-Newton Hessian ``J^T J`` along which the
    predicted standard deviation ``sqrt(s^2 / lambda)`` (``s^2``: residual mean square) is below
    ``max_std`` raw (level-0) pixels. The other directions (e.g. the two of the three shifts per
    axis that S0 texture alone cannot fix) keep the local-correlation estimate. ``J`` by central
    differences (one column per parameter: 3 x P evaluations, no per-pixel loop)."""
    crit = criteria(0, 1.0)
    crit.fix_weights(p)
    w = crit.weights.prod(dim=0).sqrt()
    shape = p.shape

    def residual(flat):
        warped = spline_sample(crit.coef, crit.coords(flat.view(shape)))
        return (w * (crit.ref + warped[1] - warped[0] - warped[2])).flatten()

    n_eff = float(w.square().sum().clamp_min(1.0))
    record = {"max_std_px": max_std, "steps": []}
    for _ in range(iterations):
        flat = p.flatten().detach()
        r0 = residual(flat)
        step = 1e-3
        cols = []
        for k in range(flat.numel()):
            e = torch.zeros_like(flat)
            e[k] = step
            cols.append((residual(flat + e) - residual(flat - e)) / (2 * step))
        jac = torch.stack(cols, 1)
        hess = jac.T @ jac
        grad = jac.T @ r0
        lam, vec = torch.linalg.eigh(hess)
        s2 = float(r0.square().sum()) / n_eff
        std = torch.sqrt(s2 / lam.clamp_min(1e-30))
        keep = std < max_std
        coef = -(vec.T @ grad) / lam.clamp_min(1e-30)
        delta = vec[:, keep] @ coef[keep]
        record["steps"].append({"kept_directions": int(keep.sum()), "std_px": std.tolist(),
                                "residual_rms": math.sqrt(s2),
                                "step_norm": float(delta.norm())})
        p = (flat + delta).view(shape)
        if float(delta.norm()) < 1e-4:
            break
    info["stokes_subspace"] = record
    return p

