"""The ladder of oracles of one case: rungs, their scores and the telescoping steps between them.

Each rung replaces ONE imperfection of the case with the truth and keeps everything else the same,
the noise draw included, so the score difference between adjacent rungs is the cost of that one
imperfection, and the steps telescope: they sum to ``ceiling - as captured``.

Rungs of a camera-array method, in this order:

1. ``as-captured``: the capture as it is, the warps estimated by the method's registration;
2. ``true-warps``: the same capture with the true warps (``reconstruct(..., true_warps=True)``);
3. ``model-exact``: the ground truth re-simulated through the reconstruction's own forward operator,
   with the same set-up and the same noise draw (:func:`~.oracles.model_exact_capture`), true warps;
4. ``noise-free``: the same without noise; its score is the method's **ceiling**, what its prior and
   solver lose on their own.

Why this order: each oracle needs the ones before it. The capture is re-simulated with the
capture's stored (true) homographies, so it only means "what the operator does not model" once the
warps are true; without noise last, the noise step is measured on the exact model, where nothing else
differs. A DoFP method (one sensor, no registration) has rungs 1, 3 and 4 (``model-exact`` is then the
DoFP mosaic of the operator): its ceiling is the demosaicking (mosaic) loss.

A method with a selection layer (``caps-plus``: count, polarization filter, data direction and start; its record's
``resolved_options``) makes its choices once, on the as-captured rung; every later rung and view runs those values.

Second views at the ceiling, where they apply (``views``): ``converged``: the noise-free, model-exact,
true-warps case re-run with ``CONVERGED_FACTOR`` times the iterations (the solver's distance from its
limit; a selection layer's other choices unchanged); ``prior-on-truth`` (``caps``): NLSTR's group estimate (paper eq. 21-23) of the true image
itself (what the prior alone cannot represent).
"""

from __future__ import annotations

import math
import time
from contextlib import nullcontext

import numpy as np
import torch

from capssim.reconstruct.priors.nlstr import NonlocalSparseTensor
from capssim.reconstruct.priors.nlstr_prior import NLSTRPrior
from capssim.reconstruct.registry import available_methods, reconstruct

from .oracles import capture_mismatch, model_exact_capture

#: the scores of a rung: 12-channel mean PSNR (dB), intensity (S0) PSNR (dB), DoLP PSNR (dB), AoP mean
#: absolute error (deg)
BUDGET_METRICS = ("psnr_mean", "s0_psnr", "dolp_psnr", "aop_mae_deg")
CAPS_RUNGS = ("as-captured", "true-warps", "model-exact", "noise-free")
DOFP_RUNGS = ("as-captured", "model-exact", "noise-free")
#: what each step removes (the imperfection whose cost it measures)
STEP_CAUSE = {"true-warps": "registration (estimated warps)",
              "model-exact": "model mismatch (what the operator does not model of the capture)",
              "noise-free": "noise"}
CONVERGED_FACTOR = 4
TELESCOPING_TOLERANCE_DB = 1e-6


def rungs_of(method_name: str) -> tuple[str, ...]:
    """The rungs that apply to a registered method: :data:`CAPS_RUNGS` or :data:`DOFP_RUNGS`."""
    return CAPS_RUNGS if available_methods()[method_name].input_kind == "caps" else DOFP_RUNGS


def _scores(scorer, image) -> dict:
    flat = scorer.score(image).flat()
    return {k: (None if flat.get(k) is None else float(flat[k])) for k in BUDGET_METRICS}


def _run(capture, method: dict, scorer, *, true_warps: bool, device: str, options: dict | None = None) -> dict:
    t0 = time.perf_counter()
    out, record = reconstruct(capture, method["name"], device=device, true_warps=true_warps,
                              registration=method.get("registration"),
                              **{**(method.get("options") or {}), **(options or {})})
    result = {"scores": _scores(scorer, out.image), "wall_time_s": time.perf_counter() - t0,
              "iterations": (record.get("params") or {}).get("iterations")}
    if record.get("resolved_options"):  # a method with a selection layer: the values its solve ran with
        result["resolved_options"] = record["resolved_options"]
    return result


def rung_captures(capture, rungs: tuple[str, ...]) -> dict:
    """The capture each rung reconstructs: the capture itself, its model-exact and noise-free oracles."""
    captures = {"as-captured": capture, "true-warps": capture}
    if "model-exact" in rungs:
        captures["model-exact"] = model_exact_capture(capture, noise=True)
    if "noise-free" in rungs:
        captures["noise-free"] = model_exact_capture(capture, noise=False)
    return captures


def _same_input(a, b, method_name: str, a_estimated: bool, b_estimated: bool) -> bool:
    """Whether two rungs reconstruct the same input: the same raw frames and sensor, and the same warps
    (estimated or true) unless the method does not register (DoFP)."""
    if a_estimated != b_estimated and available_methods()[method_name].input_kind == "caps":
        return False
    same = lambda x, y: (x is None and y is None) or (x is not None and y is not None  # noqa: E731
                                                      and x.dtype == y.dtype and np.array_equal(x, y))
    return (a.meta.get("sensor") == b.meta.get("sensor") and same(a.caps_raw, b.caps_raw)
            and same(a.dofp_raw, b.dofp_raw))


def telescoping_steps(rungs: list[dict]) -> list[dict]:
    """``[{from, to, cause, d_<metric>}]`` between adjacent rungs (``None`` where a score is missing)."""
    steps = []
    for a, b in zip(rungs, rungs[1:]):
        step = {"from": a["rung"], "to": b["rung"], "cause": STEP_CAUSE[b["rung"]]}
        for key in BUDGET_METRICS:
            va, vb = a["scores"][key], b["scores"][key]
            step[f"d_{key}"] = None if va is None or vb is None else vb - va
        steps.append(step)
    return steps


def check_telescoping(rungs: list[dict], steps: list[dict]) -> float:
    """The largest ``|sum of steps - (last - first)|`` over the metrics, in their units; raises if over
    :data:`TELESCOPING_TOLERANCE_DB`."""
    worst = 0.0
    for key in BUDGET_METRICS:
        first, last = rungs[0]["scores"][key], rungs[-1]["scores"][key]
        if first is None or last is None or any(s[f"d_{key}"] is None for s in steps):
            continue
        if not (math.isfinite(first) and math.isfinite(last)):
            continue
        worst = max(worst, abs(math.fsum(s[f"d_{key}"] for s in steps) - (last - first)))
    if worst > TELESCOPING_TOLERANCE_DB:
        raise AssertionError(f"error budget steps do not telescope: off by {worst:g}")
    return worst


def prior_on_truth(gt: np.ndarray, *, device: str = "cpu") -> np.ndarray:
    """NLSTR's estimate (paper eq. 21-23, default parameters, one block matching) of the true image
    ``gt`` ``(12, 2H, 2W)``: what the prior keeps of an image it should leave unchanged."""
    z = torch.as_tensor(np.asarray(gt, dtype=np.float32), device=device)
    prior = NLSTRPrior(NonlocalSparseTensor(tuple(z.shape), device=device))
    with torch.no_grad():
        x, _ = prior.estimate(z, mu=1.0, iteration=0, stage=lambda name: nullcontext())
    return x.cpu().numpy()


def run_ladder(capture, method: dict, scorer, *, device: str = "cpu", views: bool = True) -> dict:
    """Every rung of ``method`` on ``capture``; its steps, total gap, ceiling and second views.

    Parameters
    ----------
    capture : Capture
        A capture with its ground truth.
    method : dict
        ``{name, options, registration}`` (a suite method entry).
    scorer : CaptureScorer
        The scorer of ``capture`` (:class:`capssim.eval.evaluate.CaptureScorer`).
    device : str, keyword-only
        Torch device of the reconstructions.
    views : bool, keyword-only
        Also compute the second views at the ceiling (module docstring).

    Returns
    -------
    dict
        ``rungs`` (``[{rung, scores, wall_time_s}]`` in ladder order), ``steps``
        (:func:`telescoping_steps`), ``gap`` (``{metric: ceiling - as captured}``), ``ceiling``
        (the last rung's scores), ``telescoping_error``, ``views``, ``model_fidelity``
        (:func:`~.oracles.capture_mismatch` of the capture and its model-exact oracle).
    """
    names = rungs_of(method["name"])
    captures = rung_captures(capture, names)
    rungs = []
    for name in names:
        previous = rungs[-1] if rungs else None
        if previous is not None and _same_input(captures[previous["rung"]], captures[name], method["name"],
                                                previous["rung"] == "as-captured", name == "as-captured"):
            # the rung's input is bit for bit the previous rung's (a simulated capture is model-exact): the same
            # deterministic run, so its result is reused and the step is exactly 0
            rungs.append({**previous, "rung": name, "wall_time_s": 0.0, "same_input_as": previous["rung"]})
            continue
        # every rung after the first runs the first rung's resolved choices (count, filter, blend): a step changes
        # one imperfection, not what a selection layer would choose on the other input
        resolved = rungs[0].get("resolved_options") if rungs else None
        result = _run(captures[name], method, scorer, true_warps=name != "as-captured", device=device,
                      options=resolved)
        rungs.append({"rung": name, **result})
    steps = telescoping_steps(rungs)
    out = {"rungs": rungs, "steps": steps, "telescoping_error": check_telescoping(rungs, steps),
           "ceiling": rungs[-1]["scores"],
           "gap": {k: (None if rungs[0]["scores"][k] is None or rungs[-1]["scores"][k] is None
                       else rungs[-1]["scores"][k] - rungs[0]["scores"][k]) for k in BUDGET_METRICS},
           "views": {}}
    if "model-exact" in captures:
        out["model_fidelity"] = capture_mismatch(capture, captures["model-exact"])
    if views:
        out["views"] = _views(captures["noise-free"], method, scorer, rungs[-1], device=device)
    return out


def _views(noise_free, method: dict, scorer, ceiling: dict, *, device: str) -> dict:
    views = {}
    iterations = ceiling.get("iterations")
    if available_methods()[method["name"]].input_kind == "caps" and isinstance(iterations, int) and iterations > 0:
        # only the count changes: the resolved choices of the ladder (if any) stay as they were
        more = {**(ceiling.get("resolved_options") or {}), "iterations": CONVERGED_FACTOR * iterations}
        views["converged"] = {**_run(noise_free, method, scorer, true_warps=True, device=device, options=more),
                              "options": more}
    if method["name"] == "caps":
        t0 = time.perf_counter()
        views["prior-on-truth"] = {"scores": _scores(scorer, prior_on_truth(noise_free.gt, device=device)),
                                   "wall_time_s": time.perf_counter() - t0}
    return views


__all__ = ["BUDGET_METRICS", "CAPS_RUNGS", "DOFP_RUNGS", "STEP_CAUSE", "check_telescoping", "prior_on_truth",
           "rung_captures", "rungs_of", "run_ladder", "telescoping_steps"]
