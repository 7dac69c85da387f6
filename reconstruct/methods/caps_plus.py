"""``caps-plus``: ``caps`` with a data direction that respects polarization, a start that keeps each analyzer's own
structure, and an iteration count and polarization filter chosen once per frame by held-out raw pixels.
Not the paper's method: capssim's own model beside it (docs: notes/caps-plus-model.md states it in full).

**The model.** The observation model, registration, CAGF confidence (eq. 12-14) and NLSTR prior (section 3.3) are
``caps``'s. Three things differ:

1. **the data direction** (``data_term=cagf-stokes``, :mod:`capssim.reconstruct.model.stokes_subspace`): ADMM's
   data step (eq. 25-26) moves along ``-D grad f`` with ``D = Q T Q``: ``T`` shares the residual's analyzer mean
   across channels with CAGF's weights as ``caps`` does, and its polarization part only where the analyzers'
   aligned images agree (:mod:`capssim.reconstruct.model.analyzer_agreement`); ``Q`` projects onto images that
   linear polarization can produce (``I_0 - I_45 + I_90 - I_135 = 0``). ``D`` is symmetric positive semi-definite
   per pixel, so it is a descent direction of ``caps``'s data term ``f``, but it is not its gradient: a fixed
   point satisfies ``mu (z - x) = D (-grad f)``, so ``D`` moves the balance between data and prior at each pixel.
   The iteration therefore minimizes no single stated objective; it is stopped early on purpose (3).
2. **the start** (``init=agree``, :mod:`capssim.reconstruct.pipeline.start`): eq. 24's fusion where the analyzers
   agree, each aperture demosaicked on its own where they disagree (the polarization part only).
3. **the count of the frame** (:mod:`capssim.reconstruct.selection`): ADMM from ``mu0 = 0.25`` with ``c2 = 0.01``
   (``caps``: 0.5, 0.02) runs for the count ``K`` whose prediction of 5 % held-out raw pixels is best, on the
   central 256 px window, never more than the paper's 25 iterations. The final image's polarization part is also
   guided-filtered by its intensity where the held-out pixels, or the absence of polarization structure (the
   Stokes-consistency test), ask for it
   (``polarization_filter=auto``; the default since 2026-11-29, when the development suites together chose it:
   docs/results/caps-plus.md).

Where the Stokes-consistency test of the window finds no polarization structure, 1 and 2 have nothing to keep and
would keep the apertures' disagreements (parallax, aliasing) as polarization: the frame then runs ``caps``'s
direction and start (``data_term=cagf``, ``init=fusion``), and its count is chosen with them.

Options beyond ``caps``'s (``capssim reconstruct --options caps-plus``): ``init``, ``polarization_filter``
(``auto``, the default, ``none`` or ``R,EPS``), ``holdout_fraction``. Giving ``iterations`` (or a ``preset``) fixes
the count; a ``polarization_filter`` other than ``auto`` fixes the filter; a given ``data_term`` or ``init`` fixes
that one; nothing else changes meaning. The record's ``selection`` says how each choice was made, and
``resolved_options`` holds the values the solve ran with: a tiled run and the error budget pass them to every tile
and rung.

With a calibration (``--calibration``) the start divides the flat field out before demosaicking and unmixes the
registered images by the calibrated analyzer, as ``caps-naive`` does; the choices are made on the whole frame.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from ..model.polarization_split import angle_mean
from ..pipeline import PipelineConfig, caps_observations
from ..pipeline.option_table import MethodOption, caps_method_options, check_option_names
from ..pipeline.options import given_option_names
from ..pipeline.run import fused_initialization, parse_pipeline_options, solve_front_end
from ..pipeline.slots import available_priors, parameter_defaults
from ..pipeline.start import INITIALIZATIONS, check_initialization, start_image
from ..registry import MethodOutput, RunContext, register_method, resolve_device
from ..run_context import StageTimer
from ..selection import HOLDOUT_MAX_ITERATIONS, check_holdout_fraction, parse_filter, select
from ..selection.constants import C2, HOLDOUT_FRACTION, MU0, TUNED_ON
from ..selection.polarization_filter import apply_chosen_filter
from .caps import REFERENCE as CAPS_REFERENCE

__all__ = ["CAPS_PLUS", "TUNED_ON", "caps_plus_frame_choices", "caps_plus_options", "run_caps_plus"]

#: caps-plus: caps's pipeline options it changes, and its own (module docstring)
CAPS_PLUS = PipelineConfig(front_end=caps_observations,
                           defaults={"data_term": "cagf-stokes", "mu0": MU0, "c2": C2},
                           front_end_options={"init": "agree", "polarization_filter": "auto",
                                              "holdout_fraction": HOLDOUT_FRACTION})

#: one line of meaning of caps-plus's own options
OWN_OPTIONS = {
    "init": (f"one of {', '.join(INITIALIZATIONS)}", "the solver's start (the fusion where the analyzers agree, the "
                                                     "demosaicked apertures where not)"),
    "polarization_filter": ("auto, none, or RADIUS,EPS", "the guided filter of the final image's polarization part "
                                                        "(auto: chosen per frame by held-out pixels)"),
    "holdout_fraction": ("number in (0, 0.5]", "the share of raw pixels held out to choose the count and the filter"),
}


def caps_plus_options(config: PipelineConfig = CAPS_PLUS) -> list[MethodOption]:
    """Every ``-p`` option of ``caps-plus``: ``caps``'s with caps-plus's defaults, then its own."""
    listed = []
    for option in caps_method_options(config.defaults):
        if option.name == "iterations":
            option = replace(option, default="chosen", valid=f"integer in [0, 1000]; not given: chosen per frame "
                                                            f"(at most {HOLDOUT_MAX_ITERATIONS})")
        listed.append(option)
    for name, default in config.front_end_options.items():
        valid, meaning = OWN_OPTIONS[name]
        listed.append(MethodOption(name, default, valid, meaning))
    return listed


def _check_options(name: str, config: PipelineConfig, options: dict) -> None:
    """Refuse an option the method does not take (every valid name listed, the nearest suggested)."""
    prior = str(dict(options).get("prior", config.defaults.get("prior", "nlstr"))).strip()
    own = parameter_defaults(available_priors()[prior]) if prior in available_priors() else {}
    check_option_names(name, options, caps_plus_options(config), also=own)


def _own_options(own: dict) -> dict:
    return {"init": check_initialization(own["init"]), "polarization_filter": own["polarization_filter"],
            "holdout_fraction": check_holdout_fraction(own["holdout_fraction"])}


def run_caps_plus(capture, context: RunContext, config: PipelineConfig = CAPS_PLUS, *, name: str = "caps-plus",
                  blends: tuple = ()) -> MethodOutput:
    """Front end (registration, operator) -> selection layer (:func:`~capssim.reconstruct.selection.select`) ->
    the solve from the resolved choices -> the chosen polarization filter (module docstring)."""
    _check_options(name, config, context.options)
    opts, own = parse_pipeline_options(context.options, config)
    own = _own_options(own)
    parse_filter(own["polarization_filter"])  # checked before any work
    opts.validated_parameters()
    given = given_option_names(context.options)
    front = caps_observations(capture, context, opts)
    choices = select(capture, context, opts, given=given, homographies=front.geometry.aperture_homographies,
                     front=front, blends=blends, **own)
    opts = replace(opts, admm=replace(opts.admm, iterations=int(choices.iterations)),
                   data_term=choices.data_term)
    own["init"] = choices.init
    if choices.denoiser_blend is not None:
        opts = replace(opts, prior_parameters=replace(opts.prior_parameters, denoiser_blend=choices.denoiser_blend))
    problem = front.problems[0]
    problem.init = start_image(capture, context, front.geometry, problem, opts, own["init"])
    if context.start is not None:  # a warm start: its analyzer mean, and this capture's own polarization part
        problem.init = warm_start(context, problem.init if problem.init is not None else fused_initialization(problem))
    chosen = choices.polarization_filter
    finish = (lambda image, params: apply_chosen_filter(image, {"radius": chosen[0], "eps": chosen[1]})) \
        if chosen else None
    out = solve_front_end(capture, context, front, opts, replace(config, finish=finish))
    out.params.update({"init": own["init"], "holdout_fraction": own["holdout_fraction"],
                       "polarization_filter": choices.options()["polarization_filter"], "selection": choices.record})
    out.extra["resolved_options"] = choices.options()
    return out


def warm_start(context: RunContext, own_start):
    """The start of a warm-started run (the bootstrap's replicates, :attr:`RunContext.start`): the warm image's
    analyzer mean with ``own_start``'s polarization part. The data direction moves the polarization part only where
    the analyzers agree, so elsewhere it stays what the start made it: a replicate must draw it from its own data."""
    warm = torch.as_tensor(context.start, dtype=torch.float32, device=own_start.device)
    return (angle_mean(warm) + own_start - angle_mean(own_start)).clamp(0.0, 1.0).contiguous()


def caps_plus_frame_choices(capture, options: dict, *, homographies, device, config: PipelineConfig = CAPS_PLUS,
                            name: str = "caps-plus", blends: tuple = ()) -> dict:
    """What a tiled run fixes once for the whole frame (``frame_options`` of the registration): the choices of the
    central window of the whole frame (:func:`~capssim.reconstruct.selection.select`, the same window and warps
    as an untiled run), as option values every tile runs with."""
    _check_options(name, config, options)
    opts, own = parse_pipeline_options(options, config)
    dev = resolve_device(device)
    context = RunContext(device=dev, timer=StageTimer(dev), options=dict(options), true_warps=True)
    choices = select(capture, context, opts, given=given_option_names(options), homographies=homographies,
                     blends=blends, **_own_options(own))
    return choices.options()


@register_method("caps-plus", input_kind="caps", frame_options=caps_plus_frame_choices, tuned_on=TUNED_ON,
                 options=caps_plus_options, reference=CAPS_REFERENCE + " with capssim's changes (not the paper's)",
                 description="CAPS pipeline, not the paper's: polarization-aware CAGF data direction in the Stokes "
                             "subspace, agreement start, ADMM count chosen per frame by held-out raw pixels "
                             "(a polarization filter on request)")
def caps_plus(capture, *, context: RunContext) -> MethodOutput:
    return run_caps_plus(capture, context)
