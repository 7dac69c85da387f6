"""The CAPS pipeline: registration -> operator -> data term -> prior -> solver -> physical projection.

Paper sections 3-4 (Fig. 3, Algorithm 1). Every CAPS method is a :class:`PipelineConfig` run by
:func:`run_pipeline`:

1. **front end** (``PipelineConfig.front_end``): the observations, their registration and the sampling
   operator ``M`` (eq. 15), as one or more :class:`~capssim.reconstruct.pipeline.problem.Problem` values
   (``caps``: :func:`~capssim.reconstruct.pipeline.front_end.caps_observations`; ``caps-iccp``: one
   problem per colour after demosaicking);
2. **data term** (``-p data_term=NAME``, :mod:`.slots`): ``cagf`` (eq. 15-16, 25-26) or ``plain``;
3. **initialization**: all observations fused on the HR grid
   (:func:`capssim.reconstruct.model.init_fusion.fuse_initial_estimate`), unmixed by a calibrated analyzer,
   unless the front end provides one (``Problem.init``; ``caps-plus``);
4. **prior** (``-p prior=NAME``, :mod:`.slots`): ``nlstr`` (section 3.3), ``tikhonov``, ``none``, or a
   registered one; one instance per image shape, reset by the solver for each problem;
5. **solver**: ADMM (eq. 20-30, :func:`capssim.reconstruct.solvers.admm.admm`) with a prior, steepest
   descent on the data term (eq. 16, :func:`capssim.reconstruct.solvers.descent.steepest_descent`)
   without one; a diverging run names the options set away from the configuration's defaults;
6. **physical projection**: the dispatcher's, after every method
   (:func:`capssim.reconstruct.registry.reconstruct`, ``physical_projection``).

The solver sees only the data-fidelity and prior protocols
(:mod:`capssim.reconstruct.solvers.interfaces`): a new prior or data term is registered
(:func:`~capssim.reconstruct.pipeline.slots.register_prior`,
:func:`~capssim.reconstruct.pipeline.slots.register_data_term`), with no edit here or in a solver.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
import torch

from capssim.conventions import N_CHANNELS
from capssim.runtime.allocator import reuse_freed_memory

from ..model.init_fusion import fuse_initial_estimate
from ..model.observation_model import unmix_analyzer
from ..run_context import MethodOutput, RunContext
from ..solvers.admm import admm
from ..solvers.descent import steepest_descent
from ..solvers.interfaces import DivergenceError
from .diagnostics import mean_psnr, psnr_observer
from .front_end import caps_observations
from .options import CapsOptions, coerce_option, explain_divergence, given_option_names
from .problem import FrontEnd, Problem
from .slots import get_data_term, get_prior

__all__ = ["PipelineConfig", "fused_initialization", "parse_pipeline_options", "run_pipeline", "solve_front_end"]


@dataclass(frozen=True)
class PipelineConfig:
    """A CAPS method as a configuration of the pipeline.

    Parameters
    ----------
    front_end : callable
        ``front_end(capture, context, options, **front_end_options) -> FrontEnd``: the observations,
        their registration and the operator ``M`` (default: ``caps``'s,
        :func:`~capssim.reconstruct.pipeline.front_end.caps_observations`).
    defaults : mapping
        The method's own option defaults over the pipeline's, e.g. ``{"prior": "none"}`` or
        ``{"c1": 0.001, "c2": 0.01}``; explicit ``-p`` options still win.
    front_end_options : mapping
        Options only the front end takes, with their defaults (e.g. ``{"bayer_method": "ri"}``).
    schedule : callable, optional
        ``schedule(front, options, given) -> CapsOptions``: the method's own choice of options from what
        its front end measured, run after the
        front end; ``given`` holds the option names set explicitly (``-p``, ``-`` read as ``_``), which
        a schedule leaves as given. None (``caps``): the options as parsed.
    finish : callable, optional
        ``finish(image, params) -> image``: the method's last step on the solved ``(12, H, W)`` image, given the
        run's record (e.g. ``caps-plus``'s polarization filter chosen by held-out pixels); before the physical
        projection. None (``caps``): the solver's image.
    """

    front_end: Callable[..., FrontEnd] = caps_observations
    defaults: Mapping[str, object] = field(default_factory=dict)
    front_end_options: Mapping[str, object] = field(default_factory=dict)
    schedule: Callable[..., CapsOptions] | None = None
    finish: Callable[..., torch.Tensor] | None = None


@dataclass
class _Solved:
    problem: Problem
    data: object
    init: torch.Tensor
    image: torch.Tensor
    history: list[dict]
    stopping: object = None


def parse_pipeline_options(options: dict, config: PipelineConfig) -> tuple[CapsOptions, dict]:
    """The run's :class:`CapsOptions` (over ``config.defaults``) and the front end's own options.

    Parameters
    ----------
    options : dict
        ``{name: value}`` as given (``-p NAME=VALUE``; ``-`` and ``_`` are the same in names).
    config : PipelineConfig
        The method's configuration.

    Returns
    -------
    tuple
        The parsed options and ``{front-end option: value}`` (every one of ``config.front_end_options``).
    """
    own, rest = {}, {}
    for key, raw in dict(options or {}).items():
        name = str(key).replace("-", "_")
        if name in config.front_end_options:
            own[name] = coerce_option(name, raw, type(config.front_end_options[name]))
        else:
            rest[key] = raw
    return CapsOptions.from_options(rest, **config.defaults), {**config.front_end_options, **own}


def run_pipeline(capture, context: RunContext, config: PipelineConfig = PipelineConfig()) -> MethodOutput:
    """Run the CAPS pipeline configured by ``config`` on ``capture``.

    Parameters
    ----------
    capture : Capture
        A CAPS capture (4 RGGB raw frames ``(H/2, W/2)``).
    context : RunContext
        The run: device, timer, ``options`` (``-p``), registration and calibration choices.
    config : PipelineConfig
        The method (``caps`` by default).

    Returns
    -------
    MethodOutput
        ``image`` ``(12, H, W)`` float32 (channel ``c = 3 p + k``), ``params`` (every option, the PSF, the
        front end's and the prior's record), the solver's ``history`` and the unobserved pixels.
    """
    opts, front_options = parse_pipeline_options(context.options, config)
    opts.validated_parameters()
    front = config.front_end(capture, context, opts, **front_options)
    if config.schedule is not None:
        opts = config.schedule(front, opts, given_option_names(context.options))
    return solve_front_end(capture, context, front, opts, config)


def solve_front_end(capture, context: RunContext, front: FrontEnd, opts: CapsOptions,
                    config: PipelineConfig = PipelineConfig()) -> MethodOutput:
    """Steps 2-5 of the pipeline (data term, initialization, prior, solver) and ``config.finish`` on the problems
    of ``front``, with the options ``opts``: :func:`run_pipeline` after its front end, and what a method that
    builds its own front end (``caps-plus``: the selection layer between front end and solve) runs.

    Returns
    -------
    MethodOutput
        As :func:`run_pipeline`.
    """
    defaults = CapsOptions.from_options({}, **config.defaults)
    priors: dict[tuple, object] = {}  # one prior per image shape, shared by the problems of that shape
    # the iterations allocate the same large temporaries again and again: keep freed memory for reuse
    with reuse_freed_memory(enabled=context.device.type == "cpu"):
        solved = [_solve_problem(capture, context, opts, defaults, front.problems, index, priors)
                  for index in range(len(front.problems))]
    image = _assemble(solved, "image", capture.hr_shape)
    init = _assemble(solved, "init", capture.hr_shape)
    params = opts.to_dict()
    params.update({"psf": front.psf, "use_cagf": opts.data_term.startswith("cagf"),
                   "use_nlstr": opts.prior in ("nlstr", "nlstr-denoiser"), **front.params})
    for owner in [*priors.values(), *(s.stopping for s in solved)]:
        if callable(getattr(owner, "record", None)):
            params.update(owner.record())
    if config.finish is not None:
        with context.timer.stage("finish"):
            image = config.finish(image, params)
    extra = {"registration": front.registration, **front.extra}
    init_psnr = mean_psnr(capture, init)
    if init_psnr is not None:
        extra["init_psnr_db"] = init_psnr
        extra["psnr_db"] = mean_psnr(capture, image)
    history = [{**h, **s.problem.history_fields} for s in solved for h in s.history]
    return MethodOutput(image=image.detach().cpu().numpy().astype(np.float32), params=params, history=history,
                        extra=extra, unobserved=_unobserved(solved, capture.hr_shape))


def fused_initialization(problem: Problem) -> torch.Tensor:
    """The pipeline's initial estimate of ``problem`` ``(C, H, W)``: all its observations fused on the HR grid
    (eq. 24, :func:`~capssim.reconstruct.model.init_fusion.fuse_initial_estimate`), unmixed per pixel by a
    calibrated analyzer (``problem.unmix``)."""
    init = fuse_initial_estimate(problem.seen, problem.homographies, problem.hr_shape)
    if problem.unmix is not None:  # the fused channels see the calibrated analyzer: A x per pixel
        init = unmix_analyzer(init, problem.unmix)
    return init


def _solve_problem(capture, context: RunContext, opts: CapsOptions, defaults: CapsOptions, problems: list[Problem],
                   index: int, priors: dict) -> _Solved:
    """Data term, initialization, prior and solver of ``problems[index]``."""
    problem, timer, admm_params = problems[index], context.timer, opts.admm
    data = get_data_term(opts.data_term).factory(problem, options=opts, stage=timer.stage)
    with timer.stage("init"):
        if problem.init is not None:  # the front end's start (it may hold a warm start, see caps-plus)
            init = problem.init
        elif context.start is not None:  # a warm start given by the caller (the bootstrap's replicates)
            init = torch.as_tensor(context.start, dtype=torch.float32, device=context.device)[problem.channels]
            init = init.contiguous()
        else:
            init = fused_initialization(problem)
    spec = get_prior(opts.prior)
    shape = problem.image_shape
    if spec.factory is not None and shape not in priors:
        with timer.stage(f"{spec.name}_setup"):
            priors[shape] = spec.factory(shape, parameters=opts.prior_parameters, options=opts,
                                         device=context.device)
    prior = priors.get(shape)
    observer = psnr_observer(capture, context.device, problem.channels) if opts.track_psnr else None
    progress = context.report
    if len(problems) > 1 or problem.label:
        iterations, count, label = admm_params.iterations, len(problems), problem.label

        def progress(done, _total, message):
            context.report(index * iterations + done, count * iterations, f"{label}: {message}" if label else message)

    hooks = {"stage": timer.stage, "progress": progress, "observer": observer}
    image, history = _run_solver(data, init, prior, admm_params, opts, defaults, stopping=problem.stopping, **hooks)
    return _Solved(problem, data, init, image, history, problem.stopping)


def _run_solver(data, init, prior, admm_params, opts: CapsOptions, defaults: CapsOptions, **hooks):
    """ADMM with ``prior``, steepest descent on the data term (eq. 16) without one; a divergence explained."""
    try:
        if prior is None:  # the data term alone (eq. 16)
            return steepest_descent(data, init, admm_params, **hooks)
        return admm(data, init, prior, admm_params, **hooks)
    except DivergenceError as exc:
        raise explain_divergence(exc, opts, defaults) from None


def _assemble(solved: list[_Solved], name: str, hr_shape) -> torch.Tensor:
    """The 12 output channels ``(12, H, W)`` from the problems' ``image`` or ``init``."""
    if len(solved) == 1 and solved[0].problem.channels == slice(None):
        return getattr(solved[0], name)
    first = getattr(solved[0], name)
    out = torch.empty(N_CHANNELS, *hr_shape, dtype=torch.float32, device=first.device)
    for s in solved:
        out[s.problem.channels] = getattr(s, name)
    return out


def _unobserved(solved: list[_Solved], hr_shape):
    """A function giving the ``(12, H, W)`` unobserved pixels of the data terms (None if one cannot tell)."""
    masks = [getattr(s.data, "unobserved_mask", None) for s in solved]
    if any(mask is None for mask in masks):
        return None
    if len(solved) == 1 and solved[0].problem.channels == slice(None):
        return masks[0]

    def unobserved() -> np.ndarray:
        out = np.zeros((N_CHANNELS, *hr_shape), dtype=bool)
        for s, mask in zip(solved, masks):
            out[s.problem.channels] = mask()
        return out

    return unobserved
