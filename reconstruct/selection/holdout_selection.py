"""``select``: the choices of ``caps-plus`` for one frame, from held-out raw pixels of a window of it.

The choices, each one a plain option value afterwards (:class:`Choices`):

- **the iteration count** ``K``. ``caps-plus`` stops early on purpose: past some iteration the prior's smoothing
  costs more than it removes, and where that iteration lies depends on the scene and the noise. A fixed
  :data:`~capssim.reconstruct.selection.holdout.HOLDOUT_SEED` draw of ``holdout_fraction`` of the raw pixels is left
  out of a validation solve of the window; after every ADMM iteration the held-out pixels are predicted through
  ``M`` (eq. 15) and ``K`` is the iteration of the lowest prediction error (the run stops
  :data:`HOLDOUT_PATIENCE` iterations after it, at most :data:`HOLDOUT_MAX_ITERATIONS`;
  :class:`~capssim.reconstruct.selection.holdout.HoldoutValidation`). This is hold-out validation for early stopping
  (Prechelt, "Early stopping - but when?", 1998).
- **the polarization filter** of the final image (:mod:`capssim.reconstruct.selection.polarization_filter`): none
  where the Stokes-consistency test of the window finds polarization structure and the held-out pixels prefer no
  filter by less than one standard error; the held-out pixels' filter where they prefer one; the most smoothing
  filter where the analyzers show no polarization structure at all
  (:mod:`capssim.reconstruct.selection.polarization_evidence`).
- **the denoiser blend** (only with the ``nlstr-denoiser`` prior and ``blends`` given): the validation runs once
  per blend, in order, until the held-out error rises; the blend of the lowest error is taken.
- **the data direction and start**, first: where the Stokes-consistency test of the window finds no polarization
  structure, :data:`STRUCTURE_CHOICES` (``caps``'s CAGF direction and fusion start), and the validation runs them;
  else the method's own. The polarization-aware direction and start keep the analyzers' disagreements as
  polarization, which without polarization structure are the apertures' own errors (parallax, aliasing).

The window: the central :data:`HOLDOUT_WINDOW` px of the HR grid (its corner and size multiples of 4 HR px), cut
from the raw frames through the frame's warps and reconstructed with them
(:func:`~capssim.reconstruct.model.window_capture.crop_window`); a frame no larger validates on itself. A tiled run
selects on the same window of the whole frame, so that tiled and untiled runs make the same choices.

A choice given as an option is not selected (``iterations`` or ``preset``: the count; ``polarization_filter``
other than ``auto``: the filter; ``denoiser_blend``: the blend; ``data_term``, ``init``: each itself); where every
choice is given nothing runs. Where the window has fewer than :data:`MIN_HELD_OUT` usable held-out samples (a tiny
or saturated frame), the count is :data:`FALLBACK_ITERATIONS` and no filter is chosen by the held-out pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from capssim.errors import InputError

from ..model.data_term import ConfidenceDataTerm
from ..model.window_capture import WINDOW_ALIGN, crop_window
from ..pipeline.front_end import caps_observations
from ..pipeline.problem import FrontEnd
from ..pipeline.run import solve_front_end
from ..pipeline.start import start_image
from ..run_context import RunContext, StageTimer
from .constants import FALLBACK_ITERATIONS, HOLDOUT_MAX_ITERATIONS, HOLDOUT_PATIENCE, HOLDOUT_WINDOW, MIN_HELD_OUT
from .holdout import HoldoutValidation, holdout_mask, split_held_out
from .polarization_evidence import problem_polarization_evidence
from .polarization_filter import UNSTRUCTURED_FILTER

__all__ = ["FALLBACK_ITERATIONS", "HOLDOUT_MAX_ITERATIONS", "HOLDOUT_PATIENCE", "HOLDOUT_WINDOW", "MIN_HELD_OUT",
           "SELECTED_NOTHING", "STRUCTURE_CHOICES", "Choices", "check_holdout_fraction", "format_filter", "parse_filter",
           "select", "selection_window"]

#: the selection record of a run whose every choice its options fixed (nothing was selected)
SELECTED_NOTHING = {"chosen_by": "options", "iterations_from": "options", "polarization_filter_from": "options"}

#: what ``caps-plus`` runs where the Stokes-consistency test finds no polarization structure in the window: ``caps``'s
#: data direction (CAGF, eq. 26) and start (the fusion, eq. 24) instead of its polarization-aware ones
STRUCTURE_CHOICES = {"data_term": "cagf", "init": "fusion"}

#: the largest guided-filter radius ``polarization_filter=R,EPS`` takes (HR px)
MAX_FILTER_RADIUS = 32


@dataclass(frozen=True)
class Choices:
    """The resolved choices of one frame: ``iterations`` (ADMM count), ``polarization_filter`` (``(radius HR px,
    eps)`` or ``None``), ``denoiser_blend`` (``None``: the prior's own), ``record`` (how each was made), and the
    ``data_term`` and ``init`` the solve runs (set by :func:`select`)."""

    iterations: int
    polarization_filter: tuple[int, float] | None
    denoiser_blend: float | None = None
    record: dict = field(default_factory=dict)
    data_term: str | None = None
    init: str | None = None

    def options(self) -> dict:
        """The choices as the ``-p`` option values that fix them: what tiles and the error budget's rungs run."""
        out = {"iterations": int(self.iterations), "polarization_filter": format_filter(self.polarization_filter)}
        out.update({name: value for name, value in (("data_term", self.data_term), ("init", self.init)) if value})
        if self.denoiser_blend is not None:
            out["denoiser_blend"] = float(self.denoiser_blend)
        return out


def parse_filter(value) -> str | tuple[int, float] | None:
    """``polarization_filter``: ``"auto"`` (selected), ``None`` (``none``) or ``(radius, eps)`` (``"R,EPS"``);
    :class:`InputError` naming the option otherwise."""
    text = str(value).strip().lower()
    if text in ("auto", "none"):
        return None if text == "none" else "auto"
    parts = text.replace(":", ",").split(",")
    try:
        radius, eps = int(parts[0]), float(parts[1])
        if len(parts) != 2 or not (1 <= radius <= MAX_FILTER_RADIUS) or not (eps > 0 and math.isfinite(eps)):
            raise ValueError
    except (ValueError, IndexError):
        raise InputError("option polarization_filter", repr(value),
                         f"auto, none, or RADIUS,EPS (an integer radius in [1, {MAX_FILTER_RADIUS}] HR px and eps > 0)",
                         "Use -p polarization_filter=auto (chosen per frame), none, or e.g. 4,0.01.") from None
    return (radius, eps)


def format_filter(choice) -> str:
    """The option value of a filter choice: ``none`` or ``R,EPS``."""
    return "none" if not choice else f"{int(choice[0])},{float(choice[1]):g}"


def check_holdout_fraction(value) -> float:
    fraction = float(value)
    if not 0.0 < fraction <= 0.5:
        raise InputError("option holdout_fraction", value, "a number in (0, 0.5] (the share of raw pixels left out)",
                         "Use -p holdout_fraction=0.05.")
    return fraction


def selection_window(hr_shape) -> tuple[int, int, int, int]:
    """``(top, left, bottom, right)``: the central :data:`HOLDOUT_WINDOW` px window of an ``hr_shape`` frame
    (the whole frame when no larger), corner on the :data:`~capssim.reconstruct.model.window_capture.WINDOW_ALIGN`
    grid."""
    h, w = (int(v) for v in hr_shape)
    rows, cols = min(h, HOLDOUT_WINDOW), min(w, HOLDOUT_WINDOW)
    top, left = (h - rows) // 2 // WINDOW_ALIGN * WINDOW_ALIGN, (w - cols) // 2 // WINDOW_ALIGN * WINDOW_ALIGN
    return (top, left, top + rows, left + cols)


def select(capture, context: RunContext, options, *, given: frozenset, init: str, polarization_filter,
           holdout_fraction: float, homographies, front: FrontEnd | None = None, blends: tuple = ()) -> Choices:
    """The choices of ``capture`` (module docstring).

    Parameters
    ----------
    capture : Capture
        The whole frame.
    context : RunContext
        The run (device, calibration; its timer gets the stage ``selection``).
    options : CapsOptions
        The method's parsed options (with its defaults).
    given : frozenset
        The option names given explicitly (``-`` read as ``_``): the choices they fix are not selected.
    init, polarization_filter, holdout_fraction : keyword-only
        The method's start, filter option (``auto``, ``none`` or ``R,EPS``) and held-out share.
    homographies : numpy.ndarray
        ``(4, 3, 3)`` the frame's aperture warps (estimated or true), HR reference -> aperture HR px.
    front : FrontEnd, optional
        The whole frame's front end, when it is built already: a frame no larger than the window, or a
        calibrated one, validates on its problem instead of a crop.
    blends : tuple of float
        Denoiser blends to choose among (``nlstr-denoiser`` prior; empty: none).

    Returns
    -------
    Choices
    """
    filter_spec = parse_filter(polarization_filter)
    count_open = not given & {"iterations", "preset"}
    has_blend = hasattr(options.prior_parameters, "denoiser_blend")  # -p prior= may choose a prior without one
    blends = tuple(blends) if has_blend and "denoiser_blend" not in given else ()
    model_open = tuple(name for name in STRUCTURE_CHOICES if name not in given)
    fixed = Choices(options.admm.iterations, None if filter_spec == "auto" else filter_spec,
                    record=dict(SELECTED_NOTHING), data_term=options.data_term, init=init)
    if not (count_open or filter_spec == "auto" or blends or model_open):
        return fixed
    with context.timer.stage("selection"):
        return _select(capture, context, options, count_open, filter_spec, blends, init, holdout_fraction,
                       homographies, front, model_open)


def _window_problem(capture, context: RunContext, options, homographies, front):
    """The validation window's ``(capture, sub-context, geometry, problem, window)``."""
    window = selection_window(capture.hr_shape)
    sub = RunContext(device=context.device, timer=StageTimer(context.device), true_warps=True,
                     calibration=context.calibration)
    whole = window == (0, 0, *capture.hr_shape)
    if front is not None and (whole or context.calibration is not None):
        return capture, sub, front.geometry, front.problems[0], (0, 0, *capture.hr_shape)
    crop = crop_window(capture, window, homographies, name="selection-window")
    sub.calibration = None  # a crop carries no rig: its validation models the ideal array
    window_front = caps_observations(crop, sub, options)
    return crop, sub, window_front.geometry, window_front.problems[0], window


def _select(capture, context, options, count_open, filter_spec, blends, init, fraction, homographies, front,
            model_open):
    crop, sub, geometry, problem, window = _window_problem(capture, context, options, homographies, front)
    record = {"window": list(window), "holdout_fraction": float(fraction),
              "iterations_from": "holdout" if count_open else "options",
              "polarization_filter_from": "holdout" if filter_spec == "auto" else "options"}
    choose_filter = filter_spec == "auto"
    chosen_filter = None if choose_filter else filter_spec
    model = {"data_term": options.data_term, "init": init}  # what the solve runs; the test may change the open ones
    if choose_filter or model_open:
        evidence = problem_polarization_evidence(problem, radius=options.cagf.radius)
        record["polarization_evidence"] = evidence
        structure = evidence["structure"]
        if not structure:
            model.update({name: STRUCTURE_CHOICES[name] for name in model_open})
            if choose_filter:
                choose_filter, chosen_filter = False, UNSTRUCTURED_FILTER
                record["polarization_filter_from"] = "stokes-consistency"
        record.update({f"{name}_from": "default" if structure else "stokes-consistency" for name in model_open})
    options = replace(options, data_term=model["data_term"])
    if not (count_open or choose_filter or blends):
        return Choices(options.admm.iterations, chosen_filter, None, record, **model)
    choices = _validate(crop, sub, geometry, problem, record, options, count_open, (choose_filter, chosen_filter),
                        blends, model["init"], fraction)
    return replace(choices, **model)


def _validate(crop, sub, geometry, problem, record, options, count_open, filters, blends, init, fraction):
    """The held-out validation solve(s) of the window: the count, the filter and the blend (module docstring)."""
    choose_filter, chosen_filter = filters
    held_out = holdout_mask(crop.caps_raw.shape, fraction)
    kept, held = split_held_out(problem.obs.weights, held_out)
    count = options.admm.iterations
    if float(held.sum()) < MIN_HELD_OUT:
        note = f"fewer than {MIN_HELD_OUT} usable held-out samples: the count {FALLBACK_ITERATIONS}, no filter chosen"
        record.update({"note": note, "iterations_from": "fallback" if count_open else "options",
                       "polarization_filter_from": "fallback" if choose_filter else record["polarization_filter_from"]})
        return Choices(FALLBACK_ITERATIONS if count_open else count, chosen_filter, None, record)
    obs = replace(problem.obs, weights=kept)
    seen = obs if problem.seen is problem.obs else replace(problem.seen, weights=kept)
    predict = ConfidenceDataTerm(obs, problem.operator, mixing=problem.mixing).forward  # M I, eq. 15
    runs = []
    for blend in blends or (None,):
        run_options = replace(options, admm=replace(options.admm, iterations=HOLDOUT_MAX_ITERATIONS if count_open
                                                    else count))
        if blend is not None:
            run_options = replace(run_options, prior_parameters=replace(options.prior_parameters,
                                                                         denoiser_blend=float(blend)))
        rule = HoldoutValidation(predict, obs.images, held, patience=HOLDOUT_PATIENCE,
                                 choose_filter=choose_filter)
        validation = replace(problem, obs=obs, seen=seen, derived={}, init=None, stopping=rule)
        validation.init = start_image(crop, sub, geometry, validation, run_options, init, held_out=held_out)
        solve_front_end(crop, sub, FrontEnd(problems=[validation], registration={}, psf={}), run_options)
        runs.append((rule.best_error, blend, rule.record()))
        if len(runs) > 1 and runs[-1][0] > runs[-2][0]:  # past the lowest error (unimodal along the blends)
            break
    error, blend, best = min(runs, key=lambda run: run[0])
    if choose_filter:
        choice = best["polarization_filter_choice"]
        chosen_filter = (choice["radius"], choice["eps"]) if choice["radius"] > 0 else None
        record["polarization_filter_candidates"] = choice["candidates"]
    record.update({"holdout_error": error, "holdout_best_iteration": best["holdout_best_iteration"],
                   "holdout_iterations_run": best["holdout_iterations_run"]})
    if blends:
        record["blend_candidates"] = [{"denoiser_blend": b, "holdout_error": e,
                                       "iterations": r["holdout_best_iteration"]} for e, b, r in runs]
    return Choices(int(best["holdout_best_iteration"]) if count_open else count, chosen_filter, blend, record)
