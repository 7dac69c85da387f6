"""``caps-plus``: the CAPS pipeline with a structure-aware data term, a start that takes the polarization
differences from the demosaicked apertures where the analyzers disagree, and an ADMM iteration count and a
polarization filter chosen by held-out raw pixels.
Not the paper's method: capssim's own configuration beside it.

Each ingredient answers a loss of ``caps`` that the error budget measured (docs: notes/beyond-the-paper.md):

1. **Structure-aware CAGF data term in the Stokes subspace** (``data_term=cagf-stokes``,
   :mod:`capssim.reconstruct.model.stokes_subspace`): the residual's mean over the four analyzers is
   shared by every channel with CAGF's weights, as in eq. 26; its polarization part is shared across
   analyzers only where their aligned images agree (a noise-corrected local correlation ``alpha``,
   ``data_term=cagf-agree``, :mod:`capssim.reconstruct.model.analyzer_agreement`), otherwise only between the
   colours of one analyzer (``data_term=cagf-split``), and kept to images that obey
   ``I_0 - I_45 + I_90 - I_135 = 0``, so that the 0 and 90 deg apertures both inform ``S1`` (45 and 135 deg
   ``S2``). ``caps`` shares all of it with positive weights and smears structure that only some analyzers see
   (polarization-star, the cellphone cases).
2. **Agreement initialization** (``-p init=agree``, the default): the analyzer mean of each colour from the
   fusion of eq. 24 (``caps``'s start, ``init=fusion``); the polarization differences from the fusion where
   the analyzers agree and from the demosaicked apertures where they do not (``init=naive``: each aperture's
   raw frame demosaicked on its own, Menon et al. 2007 as ``caps-naive``, resampled onto the HR grid through
   the same registration, bicubic; ``init=split``: all differences from them; ``init=agree-all``: the agreement's
   blend for the analyzer mean as well, ``caps-plus-cv``'s start). The fusion averages the analyzers' differences
   away, which is right only where they agree.
3. **Held-out stopping** (``-p stopping=holdout``, the default; :mod:`capssim.reconstruct.model.holdout`): ADMM
   from ``mu0 = 0.25`` with ``c2 = 0.01`` (``caps``: 0.5, 0.02; eq. 27-28). Past its best iteration the PSNR
   falls as the prior keeps smoothing, and where that iteration lies depends on the scene and the noise. A
   fixed 5 % of the raw pixels is left out of a validation run, which predicts them through ``M`` (eq. 15)
   after every iteration and stops 5 iterations after their prediction error stopped falling (100 at most);
   the whole problem is then solved again, with every pixel, for the best iteration's count. A frame larger
   than 256 px validates on its central 256 px window (:data:`HOLDOUT_WINDOW`), so that the validation costs
   a quarter of a run at 512 px. ``-p stopping=noise`` takes the count from the raw frames' noise level
   instead, ``clip(10 + 1000 sigma, 10, 50)`` (:func:`noise_adaptive_iterations`; ``caps-plus``'s rule before
   2026-11-27, and what a tiled run uses for every tile); ``-p iterations=N`` (or a ``preset``) fixes the count.
4. **A polarization filter** (``-p polarization_filter=auto``, the default;
   :mod:`capssim.reconstruct.model.polarization_filter`): where the analyzers' aligned images show no
   polarization structure (the Stokes-consistency test, :mod:`capssim.reconstruct.model.polarization_evidence`),
   the final image's polarization part gets the most smoothing guided filter; elsewhere the validation tries
   each filter on its best iterate and the final image gets the one that predicts the held-out pixels better by
   more than one standard error (else none). ``holdout`` skips the test; ``none`` turns both off.

Everything else is ``caps``: the registration, the operator ``M``, CAGF's confidence (eq. 12-14), NLSTR
(section 3.3) and ADMM (eq. 20-30); ``-p`` options of ``caps`` apply (e.g. ``-p iterations=25``,
``-p data_term=cagf`` to drop ingredient 1, ``-p init=fusion`` to drop 2; ``-p data_term=cagf-split -p init=naive``
is ``caps-plus`` as first shipped).

With a calibration (``--calibration``) the initialization divides the flat field out before
demosaicking and unmixes the registered images by the calibrated analyzer, as ``caps-naive`` does.
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import torch

from capssim.errors import InputError

from ..model.data_term import ConfidenceDataTerm
from ..model.holdout import HoldoutValidation, check_holdout_rule, holdout_mask, split_held_out
from ..model.observation_model import calibrated_analyzer, unmix_analyzer
from ..model.polarization_evidence import problem_polarization_evidence
from ..model.polarization_filter import UNSTRUCTURED_FILTER, apply_chosen_filter, check_polarization_filter
from ..model.polarization_split import angle_mean
from ..model.rearrange import observations_from_capture
from ..model.window_capture import WINDOW_ALIGN, crop_window
from ..pipeline import PipelineConfig, caps_observations, run_pipeline
from ..pipeline.options import CapsOptions, given_option_names
from ..pipeline.problem import FrontEnd
from ..pipeline.run import fused_initialization
from ..pipeline.slots import problem_agreement
from ..registration.image_ops import noise_sigma
from ..registry import MethodOutput, RunContext, register_method
from ..run_context import StageTimer
from .caps import REFERENCE as CAPS_REFERENCE
from .caps_naive import bicubic_warp, demosaicked_frames

__all__ = ["CAPS_PLUS", "COUNT_OPTIONS", "INITIALIZATIONS", "NOISE_ITERATIONS", "caps_plus_observations",
           "demosaicked_initialization", "frame_iterations", "noise_adaptive_iterations", "noise_adaptive_schedule",
           "polarization_filter_finish", "raw_noise_sigma"]

#: ``-p init=NAME``: ``agree`` (the default), ``naive``, ``fusion``, ``split`` or ``agree-all``
#: (:func:`caps_plus_observations` says what each is)
INITIALIZATIONS = ("naive", "fusion", "split", "agree", "agree-all")
#: the Bayer demosaicking of the initialization (``caps-naive``'s default)
INIT_BAYER_METHOD = "menon2007"


def demosaicked_initialization(capture, context: RunContext, geometry, *, held_out=None) -> torch.Tensor:
    """``(12, H, W)`` float32 on the context device: ``caps-naive``'s image under ``geometry``.

    Each aperture's raw frame (flat field divided out with a calibration) is demosaicked on its own
    (:func:`~capssim.reconstruct.methods.caps_naive.demosaicked_frames`, Menon 2007) and resampled onto the
    HR reference grid by one bicubic warp through ``geometry.raw_homographies``; channel ``c = 3 p + k``;
    unmixed by a calibrated analyzer; clipped to [0, 1]. ``held_out`` ``(4, H, W)`` bool: raw pixels the
    start must not see, filled from their same-colour neighbours first (:func:`~capssim.reconstruct.model.holdout.fill_held_out`).
    """
    rgb = demosaicked_frames(capture, context, INIT_BAYER_METHOD, held_out=held_out)
    image = bicubic_warp(rgb, geometry.raw_homographies, geometry.hr_shape).reshape(12, *geometry.hr_shape)
    analyzer = calibrated_analyzer(context)
    if analyzer is not None:
        image = unmix_analyzer(image, analyzer)
    return image.clamp(0.0, 1.0).contiguous()


def caps_plus_observations(capture, context: RunContext, options, *, init: str = "agree", stopping: str = "holdout",
                           holdout_fraction: float = 0.05, patience: int = 5, holdout_refit: bool = True,
                           holdout_rule: str = "min", blend_candidates: str = "",
                           polarization_filter: str = "auto") -> FrontEnd:
    """``caps``'s front end (:func:`~capssim.reconstruct.pipeline.front_end.caps_observations`) with the
    initial estimate of ``init`` (``naive``: :func:`demosaicked_initialization`; ``fusion``: eq. 24;
    ``split``: ``P fusion + (I - P) naive``, ``P`` the mean over the analyzers of each colour, as the
    polarization-split data term splits its residual; ``agree``: ``P fusion + (I - P) (alpha fusion +
    (1 - alpha) naive)``, ``alpha`` ``(H, W)`` the analyzers' agreement of ``data_term=cagf-agree``/``cagf-stokes``;
    ``agree-all``: ``alpha fusion + (1 - alpha) naive``).
    ``stopping="holdout"`` (the default unless ``iterations`` or ``preset`` is given) holds out
    ``holdout_fraction`` of the raw pixels for the solver's stopping rule (:func:`hold_out_pixels`; a frame
    larger than :data:`HOLDOUT_WINDOW` is validated on its central window, :func:`window_validation`).
    ``holdout_refit=False`` keeps the best validation iterate instead of solving again with all the data.
    ``holdout_rule`` names the count the final solve runs: ``min`` (the lowest held-out error) or ``one-se``
    (the earliest within one standard error of it; :class:`~capssim.reconstruct.model.holdout.HoldoutValidation`).
    ``blend_candidates`` (``caps-plus-cv``'s ``"0,0.5,0.75"``; prior ``nlstr-denoiser``): the held-out validation
    runs for each ``denoiser_blend`` listed in turn, on the central window or the whole frame, and the final solve
    takes the one whose held-out prediction error is lowest (:func:`window_validation`; a calibrated run, which
    validates in place, keeps the configured blend and says so in ``blend_note``). ``polarization_filter="holdout"``:
    the validation also chooses the guided filter of the final image's polarization part
    (:mod:`capssim.reconstruct.model.polarization_filter`; ``polarization_filter_choice`` in the record, applied by
    :func:`polarization_filter_finish`); ``auto``: the same where the analyzers show polarization structure, the
    most smoothing filter where they do not (:func:`polarization_structure_shown`); ``none``, or ``holdout`` without
    a validation, leaves the solver's image as it is."""
    name = str(init).strip()
    if name not in INITIALIZATIONS:
        raise InputError("option init", repr(init), "one of " + ", ".join(INITIALIZATIONS),
                         "Use -p init=naive (demosaicked apertures), -p init=fusion (caps's), -p init=split, agree or agree-all.")
    stopping = check_stopping(stopping, holdout_fraction, patience, holdout_rule)
    filter_mode = check_polarization_filter(polarization_filter)
    given = given_option_names(context.options)
    if given & COUNT_OPTIONS and "stopping" not in given:  # a count given fixes the count: nothing to validate
        stopping = "noise"
    candidates = blend_choices(blend_candidates, options, given)
    front = caps_observations(capture, context, options)
    full = front.problems[0]
    choose_filter = filter_mode == "holdout" or (filter_mode == "auto" and
                                                 polarization_structure_shown(front, options, context.timer.stage))
    if stopping == "holdout" and window_validation(capture, context, front, options, candidates=candidates,
                                                   rule=holdout_rule, choose_filter=choose_filter, init=name):
        stopping = "window"  # the count is chosen: the whole frame runs it with all its pixels
    elif candidates:  # a count, the noise rule, a calibration or too few pixels: nothing validates the blends
        front.params["blend_note"] = (f"no blend chosen (stopping {stopping}, calibrated "
                                      f"{context.calibration is not None}): denoiser_blend as configured")
    held_out = hold_out_pixels(capture, front, stopping, holdout_fraction, patience, refit=holdout_refit,
                               holdout_rule=holdout_rule, choose_filter=choose_filter)
    if name != "fusion":
        for problem, mask in ((front.problems[0], held_out), (full, None))[:1 if held_out is None else 2]:
            problem.init = agreement_initialization(capture, context, front, problem, options, name, held_out=mask)
    front.params["init"] = name
    return front


def polarization_structure_shown(front: FrontEnd, options, stage) -> bool:
    """``-p polarization_filter=auto``: the Stokes-consistency test on the front end's problem, over CAGF's window
    (:func:`~capssim.reconstruct.model.polarization_evidence.problem_polarization_evidence`; kept in
    ``front.params["polarization_evidence"]``). Where it finds no polarization structure the final image gets
    :data:`~capssim.reconstruct.model.polarization_filter.UNSTRUCTURED_FILTER` (``polarization_filter_choice``) and
    False is returned: the held-out pixels choose no filter."""
    with stage("polarization_evidence"):
        evidence = problem_polarization_evidence(front.problems[0], radius=options.cagf.radius)
    front.params["polarization_evidence"] = evidence
    if not evidence["structure"]:
        radius, eps = UNSTRUCTURED_FILTER
        front.params["polarization_filter_choice"] = {"radius": radius, "eps": eps, "chosen_by": "stokes-consistency"}
    return evidence["structure"]


def agreement_initialization(capture, context: RunContext, front: FrontEnd, problem, options, name: str, *,
                             held_out=None) -> torch.Tensor:
    """The start ``(C, H, W)`` of ``init=name`` (not ``fusion``) for ``problem`` (:func:`caps_plus_observations`);
    ``held_out``: raw pixels the demosaicked apertures must not see."""
    with context.timer.stage("init_demosaic"):
        start = demosaicked_initialization(capture, context, front.geometry, held_out=held_out)
        if name in ("split", "agree", "agree-all"):
            fusion = fused_initialization(problem)
            if name in ("agree", "agree-all"):  # the fusion where the analyzers agree, the apertures where not
                alpha = problem_agreement(problem, options=options, stage=context.timer.stage)
                start = start + alpha * (fusion - start)
            if name in ("split", "agree"):  # the analyzer mean from the fusion everywhere
                start = angle_mean(fusion) + start - angle_mean(start)
            start = start.clamp(0.0, 1.0)
        return start.contiguous()


#: ``-p stopping=NAME``: ``holdout`` (the default: until the held-out pixels' prediction error stops falling,
#: :mod:`capssim.reconstruct.model.holdout`) or ``noise`` (the count of :func:`noise_adaptive_iterations`);
#: ``front.params["stopping"]`` records the rule used, or ``window`` (held out on the central window)
STOPPING_RULES = ("noise", "holdout")
#: the fewest usable held-out samples a validation runs on; below, the noise rule chooses the count
MIN_HELD_OUT = 32
#: the most iterations ``stopping=holdout`` runs when ``iterations`` is not given
HOLDOUT_MAX_ITERATIONS = 100


def check_stopping(stopping: str, fraction: float, patience: int, holdout_rule: str = "min") -> str:
    """The stopping rule's name, with its options checked before any work (:class:`InputError` naming the
    option otherwise)."""
    rule = str(stopping).strip()
    if rule not in STOPPING_RULES:
        raise InputError("option stopping", repr(stopping), "one of " + ", ".join(STOPPING_RULES),
                         "Use -p stopping=noise (the count from the noise level) or -p stopping=holdout.")
    if not 0.0 < float(fraction) <= 0.5:
        raise InputError("option holdout_fraction", fraction, "a number in (0, 0.5] (the share of raw pixels left out)",
                         "Use -p holdout_fraction=0.05.")
    if int(patience) < 1:
        raise InputError("option patience", patience, "an integer >= 1", "Use -p patience=5.")
    check_holdout_rule(holdout_rule, name="option holdout_rule")
    return rule


def hold_out_pixels(capture, front: FrontEnd, stopping: str, fraction: float, patience: int, *, refit: bool = True,
                    holdout_rule: str = "min", choose_filter: bool = False):
    """For ``stopping="holdout"``: replace the front end's single problem by a copy without ``fraction`` of the
    raw pixels (data weights and the fused start), whose
    :class:`~capssim.reconstruct.model.holdout.HoldoutValidation` rule predicts them and names the whole
    problem for the final solve (the pipeline solves it again with all the data for the chosen count); the raw
    mask ``(4, H, W)`` (for the demosaicked start), or ``None``."""
    front.params["stopping"] = rule = stopping
    if rule in ("noise", "window"):  # the count from the noise level, or already chosen on the central window
        return None
    full = front.problems[0]
    held_out = holdout_mask(capture.caps_raw.shape, fraction)
    kept, held = split_held_out(full.obs.weights, held_out)
    if float(held.sum()) < MIN_HELD_OUT:  # too few usable pixels to validate on (a tiny or saturated frame)
        front.params.update({"stopping": "noise", "stopping_note": f"fewer than {MIN_HELD_OUT} usable held-out "
                             "pixels: the count from the noise level"})
        return None
    obs = replace(full.obs, weights=kept)
    seen = obs if full.seen is full.obs else replace(full.seen, weights=kept)
    validation = replace(full, obs=obs, seen=seen, derived={}, init=None)
    predict = ConfidenceDataTerm(obs, validation.operator, mixing=validation.mixing).forward  # M I, eq. 15
    validation.stopping = HoldoutValidation(predict, obs.images, held, patience=patience,
                                            refit=full if refit else None, rule=holdout_rule,
                                            choose_filter=choose_filter)
    front.problems[0] = validation
    front.params.update({"holdout_fraction": float(fraction), "patience": int(patience), "holdout_rule": holdout_rule})
    return held_out


#: frames larger than this (HR pixels, either side) choose their count by held-out validation on the central
#: window of this side (a quarter of the pixels of a 512 px frame) and run it once with every pixel
HOLDOUT_WINDOW = 256


def blend_choices(text: str, options, given: frozenset) -> tuple[dict, ...]:
    """The prior overrides :func:`window_validation` chooses among: ``({"denoiser_blend": w}, ...)`` for each
    ``w`` of the comma list ``text``; ``()`` (no choice) when ``text`` is empty or ``denoiser_blend`` was given.
    :class:`InputError` naming ``blend_candidates`` for a bad list, or for a prior without a blend."""
    has_blend = hasattr(options.prior_parameters, "denoiser_blend")
    if not str(text).strip() or "denoiser_blend" in given:
        return ()
    if not has_blend and "blend_candidates" not in given:
        return ()  # the method's default list, and -p prior= chose a prior without a blend: nothing to choose
    try:
        blends = [float(item) for item in str(text).split(",")]
    except ValueError:
        blends = []
    if len(blends) < 2 or not all(0.0 <= w <= 1.0 for w in blends):
        raise InputError("option blend_candidates", repr(text), "two or more numbers in [0, 1], comma-separated",
                         "Use -p blend_candidates=0,0.5,0.75 (the default; 0 is NLSTR alone).")
    if not has_blend:
        raise InputError("option blend_candidates", f"prior {options.prior!r}", "prior 'nlstr-denoiser'",
                         "Add -p prior=nlstr-denoiser, or leave blend_candidates out.")
    return tuple({"denoiser_blend": w} for w in blends)


def window_validation(capture, context: RunContext, front: FrontEnd, options, *, candidates: tuple[dict, ...] = (),
                      rule: str = "min", choose_filter: bool = False, init: str = "agree") -> bool:
    """For a frame larger than :data:`HOLDOUT_WINDOW` on either side, or any frame when ``candidates`` are given
    (uncalibrated): run ``caps-plus`` with ``stopping=holdout`` and no final solve on the central window's
    capture (:func:`~capssim.reconstruct.model.window_capture.crop_window`, the front end's warps re-based to
    it; the whole frame when it is no larger; from the start ``init``), once per candidate (prior option overrides, e.g.
    ``{"denoiser_blend": 0.5}``; none: once as configured) in their order until the held-out error rises (the
    error is taken to be unimodal along the candidates: one past the lowest is not worth validating), and
    record the count ``rule`` names (:class:`~capssim.reconstruct.model.holdout.HoldoutValidation`) of the run
    with the lowest held-out error in ``front.params`` (``holdout_count``,
    ``holdout_choice``, with the window and the validation's record; ``polarization_filter_choice`` with
    ``choose_filter``). False (nothing done) for a smaller frame
    without candidates or a calibrated run, which validate on the whole frame."""
    h, w = capture.hr_shape
    if (max(h, w) <= HOLDOUT_WINDOW and not candidates) or context.calibration is not None:
        return False
    rows, cols = min(h, HOLDOUT_WINDOW), min(w, HOLDOUT_WINDOW)
    top, left = (h - rows) // 2 // WINDOW_ALIGN * WINDOW_ALIGN, (w - cols) // 2 // WINDOW_ALIGN * WINDOW_ALIGN
    window = (top, left, top + rows, left + cols)
    crop = crop_window(capture, window, front.geometry.aperture_homographies, name="holdout-window")
    own = {} if options.prior_parameters is None else asdict(options.prior_parameters)  # the prior's own options
    given = {k: v for k, v in context.options.items() if str(k).replace("-", "_") != "blend_candidates"}
    runs = []
    for overrides in candidates or ({},):
        sub = RunContext(device=context.device, timer=StageTimer(), true_warps=True,
                         options={**given, "stopping": "holdout", "holdout_refit": False, "holdout_rule": rule,
                                  "polarization_filter": "holdout" if choose_filter else "none", "init": init,
                                  "prior": options.prior, "data_term": options.data_term, **own, **overrides})
        with context.timer.stage("holdout_validation"):
            params = run_pipeline(crop, sub, CAPS_PLUS).params
        if params.get("stopping") != "holdout":  # too few usable pixels in the window: validate the whole frame
            return False
        runs.append((float(params["holdout_error"]), overrides, params))
        if len(runs) > 1 and runs[-1][0] > runs[-2][0]:  # past the lowest error (unimodal along the candidates)
            break
    error, chosen, params = min(runs, key=lambda run: run[0])
    front.params.update({"holdout_count": int(params["holdout_chosen_iteration"]), "holdout_window": list(window),
                         **{k: params[k] for k in ("holdout_best_iteration", "holdout_error", "holdout_iterations_run",
                                                   "holdout_fraction", "patience", "holdout_rule")}})
    if "polarization_filter_choice" in params:
        front.params["polarization_filter_choice"] = params["polarization_filter_choice"]
    if candidates:
        front.params.update({"holdout_choice": chosen,
                             "holdout_candidates": [{**o, "holdout_error": e, "iterations": p["holdout_chosen_iteration"]}
                                                    for e, o, p in runs]})
    return True


#: the iteration count of :func:`noise_adaptive_iterations`: ``at_zero + per_sigma * sigma`` clipped to
#: ``[fewest, most]`` (fitted to where the PSNR of caps-plus peaks on the kettle at sigma 0, 0.01 and 0.02)
NOISE_ITERATIONS = {"at_zero": 10, "per_sigma": 1000.0, "fewest": 10, "most": 50}
#: options that fix the iteration count themselves: given, the count does not follow the noise
COUNT_OPTIONS = frozenset({"iterations", "preset"})


def raw_noise_sigma(images: torch.Tensor) -> float:
    """The white-noise std of the raw frames, on their [0, 1] scale: the median over the Bayer planes
    ``images`` ``(16, H/4, W/4)`` (4 apertures x RGGB) of Immerkaer's estimate
    (:func:`~capssim.reconstruct.registration.image_ops.noise_sigma`). Fine texture and sharp edges count as
    noise too: the estimate is an upper bound, close on natural scenes (1.08e-2 for noise of 1e-2 on the
    kettle), high on synthetic stars at 192 px (about 5e-2 for 1e-2). 0.0 for planes under 3 px."""
    return float(noise_sigma(images.float()).median())


def noise_adaptive_iterations(sigma: float) -> int:
    """ADMM iterations for a capture with raw noise ``sigma`` (std on [0, 1]): ``round(10 + 1000 sigma)``
    clipped to [10, 50] (:data:`NOISE_ITERATIONS`); 50 for a non-finite ``sigma``."""
    n, sigma = NOISE_ITERATIONS, float(sigma)
    if not math.isfinite(sigma):  # no usable estimate: the longest schedule
        return n["most"]
    return int(min(max(round(n["at_zero"] + n["per_sigma"] * sigma), n["fewest"]), n["most"]))


def noise_adaptive_schedule(front: FrontEnd, options: CapsOptions, given: frozenset) -> CapsOptions:
    """caps-plus's :class:`~capssim.reconstruct.pipeline.run.PipelineConfig` ``schedule``: the iteration count
    of :func:`noise_adaptive_iterations` for the noise of the front end's observations, unless ``iterations``
    or ``preset`` was given. Records ``noise_sigma_estimate`` and ``iterations_from`` in ``front.params``."""
    sigma = raw_noise_sigma(front.problems[0].obs.images)
    front.params["noise_sigma_estimate"] = sigma
    if given & COUNT_OPTIONS:
        front.params["iterations_from"] = "options"
        return options
    if front.params.get("stopping") in ("holdout", "window"):
        front.params["iterations_from"] = "holdout"
        count = front.params.get("holdout_count", HOLDOUT_MAX_ITERATIONS)  # the window's choice, or the most
        chosen = front.params.get("holdout_choice") or {}  # the candidate prior options with the lowest error
        if chosen:
            options = replace(options, prior_parameters=replace(options.prior_parameters, **chosen))
        return replace(options, admm=replace(options.admm, iterations=count))
    front.params["iterations_from"] = "noise"
    return replace(options, admm=replace(options.admm, iterations=noise_adaptive_iterations(sigma)))


def frame_iterations(capture, options: dict) -> dict:
    """What a tiled run fixes once for the whole frame: ``{"stopping": "noise", "iterations": N, "polarization_filter":
    "none"}``, ``N`` of :func:`noise_adaptive_iterations` for the whole frame's raw noise, so that every tile runs the
    same schedule and filter (held-out validation or the Stokes-consistency test per tile could choose differently in
    each); ``{}`` when ``iterations``, ``preset`` or ``stopping`` is among ``options`` (``-p stopping=holdout``
    validates each tile)."""
    if given_option_names(options) & (COUNT_OPTIONS | {"stopping"}):
        return {}
    return {"stopping": "noise", "polarization_filter": "none",
            "iterations": noise_adaptive_iterations(raw_noise_sigma(observations_from_capture(capture).images))}


def polarization_filter_finish(image: torch.Tensor, params: dict) -> torch.Tensor:
    """caps-plus's last step (:class:`~capssim.reconstruct.pipeline.run.PipelineConfig` ``finish``): the polarization
    filter the held-out pixels chose (``params["polarization_filter_choice"]``), or the image as it is."""
    return apply_chosen_filter(image, params.get("polarization_filter_choice"))


#: caps-plus: the pipeline's slots and schedule (module docstring)
CAPS_PLUS = PipelineConfig(front_end=caps_plus_observations,
                           defaults={"data_term": "cagf-stokes", "iterations": 50, "mu0": 0.25, "c2": 0.01},
                           front_end_options={"init": "agree", "stopping": "holdout", "holdout_fraction": 0.05,
                                              "patience": 5, "holdout_refit": True, "holdout_rule": "min",
                                              "polarization_filter": "auto"},
                           schedule=noise_adaptive_schedule, finish=polarization_filter_finish)


@register_method("caps-plus", input_kind="caps", frame_options=frame_iterations,
                 reference=CAPS_REFERENCE + " with capssim's changes (not the paper's)",
                 description="CAPS pipeline, not the paper's: structure-aware CAGF data term, agreement "
                             "initialization, ADMM from mu0 0.25 for the count chosen by held-out raw pixels")
def caps_plus(capture, *, context: RunContext) -> MethodOutput:
    return run_pipeline(capture, context, CAPS_PLUS)
