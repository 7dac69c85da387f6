"""The two slots of the CAPS pipeline: the data term and the prior, each chosen by name.

``-p data_term=NAME`` and ``-p prior=NAME`` pick them (a method's configuration sets the default).
:func:`register_prior` and :func:`register_data_term` add new ones: neither the pipeline
(:mod:`.run`) nor the solvers (:mod:`capssim.reconstruct.solvers`) change, since they see only the
:class:`~capssim.reconstruct.solvers.interfaces.DataFidelity` and
:class:`~capssim.reconstruct.solvers.interfaces.Prior` protocols.

Built in:

* data terms: ``cagf``, the confidence-guided data term of eq. 15-16 / 25-26 (``caps``),
  ``plain``, the same observations with each channel's own only (``caps-no-cagf``), and
  ``cagf-split``, CAGF with the residual's polarization part shared only within one analyzer (not the
  paper's; ``caps-plus``, :mod:`capssim.reconstruct.model.polarization_split`), and ``cagf-agree``, the split
  coupled across analyzers where their images agree (not the paper's;
  :mod:`capssim.reconstruct.model.analyzer_agreement`), and ``cagf-stokes``, that direction kept to images
  linear polarization can produce (not the paper's; ``caps-plus``, :mod:`capssim.reconstruct.model.stokes_subspace`);
* priors: ``nlstr``, the nonlocal sparse tensor of section 3.3 (``caps``); ``tikhonov``, a quadratic
  smoothness prior (not the paper's; ``-p tikhonov_weight=W``); ``nlstr-denoiser``, NLSTR with its analyzer
  mean blended with a learned denoiser's (not the paper's; ``caps-plus-cv``); ``none``, the data term alone, solved
  by steepest descent (eq. 16, ``caps-no-nlstr``).

A prior's factory is called once per image shape of a run, as
``factory(shape, *, parameters, options, device)``; a data term's once per problem, as
``factory(problem, *, options, stage)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Callable

import torch

from capssim.errors import InputError

from ..model.analyzer_agreement import AgreementDataTerm, analyzer_agreement_map
from ..model.cagf import cagf_confidence
from ..model.data_term import ConfidenceDataTerm
from ..model.polarization_split import PolarizationSplitDataTerm
from ..model.stokes_subspace import StokesAgreementDataTerm
from ..priors.nlstr import NonlocalSparseTensor
from ..priors.nlstr_denoiser import DenoiserParameters, NLSTRDenoiserPrior, denoiser_model
from ..priors.nlstr_prior import NLSTRPrior
from ..priors.tikhonov import TikhonovPrior
from ..solvers.interfaces import DataFidelity, Prior, StageFactory
from .problem import Problem

__all__ = ["DEFAULT_DATA_TERM", "DEFAULT_PRIOR", "DataTermSpec", "PriorSpec", "available_data_terms",
           "available_priors", "get_data_term", "get_prior", "register_data_term", "register_prior"]

#: the paper's slots (``caps``)
DEFAULT_PRIOR = "nlstr"
DEFAULT_DATA_TERM = "cagf"

#: ``factory(shape, *, parameters, options, device)`` -> a Prior
PriorFactory = Callable[..., Prior]
#: ``factory(problem, *, options, stage)`` -> a DataFidelity
DataTermFactory = Callable[..., DataFidelity]


@dataclass(frozen=True)
class PriorSpec:
    """A registered prior: ``factory`` builds it (``None``: no prior, the solver is steepest descent);
    ``parameters`` is a dataclass whose fields (with defaults) are its own ``-p`` options, or ``None``."""

    name: str
    factory: PriorFactory | None
    description: str
    parameters: type | None = None


@dataclass(frozen=True)
class DataTermSpec:
    """A registered data term: ``factory(problem, *, options, stage)`` builds it for one problem."""

    name: str
    factory: DataTermFactory
    description: str


_PRIORS: dict[str, PriorSpec] = {}
_DATA_TERMS: dict[str, DataTermSpec] = {}


def register_prior(name: str, factory: PriorFactory | None, *, description: str = "",
                   parameters: type | None = None) -> PriorFactory | None:
    """Register the prior ``name``, chosen by ``-p prior=NAME`` in every CAPS pipeline method.

    The prior is the ``X``-step of ADMM (paper eq. 21-23, 29 for NLSTR; ``prox_{R/mu}`` for a
    regularizer ``R``): an object with the :class:`~capssim.reconstruct.solvers.interfaces.Prior`
    methods ``begin()``, ``estimate(z, *, mu, iteration, stage) -> (X, fields)`` and
    ``after_step(*, iteration, change) -> fields``, and optionally ``record() -> dict`` (fields added to
    the method's ``params`` record). Registering again under the same name replaces it.

    Parameters
    ----------
    name : str
        The prior's name, lower case, without spaces, ``=`` or ``,``.
    factory : callable or None
        ``factory(shape, *, parameters, options, device) -> Prior``, called once per image shape
        ``(C, H, W)`` of a run (``caps``: ``(12, H, W)``; ``caps-iccp``: ``(4, H, W)``, shared by the three
        colours) with the parsed ``parameters`` instance (or ``None``), the run's ``CapsOptions`` and the
        torch device. ``None`` registers "no prior": the solver is steepest descent on the data term (eq. 16).
    description : str
        One line for listings.
    parameters : type or None
        A dataclass whose fields (all with defaults) are the prior's own ``-p NAME=VALUE`` options while it
        is chosen (coerced to the defaults' types); an optional ``validate()`` method checks them. Field
        names must differ from the pipeline's shared options.

    Returns
    -------
    callable or None
        ``factory``, unchanged.

    Raises
    ------
    InputError
        A bad name, or a parameter field named like a shared option.
    """
    key = _check_name("prior", name)
    if parameters is not None:
        clash = sorted(set(parameter_defaults_of(parameters)) & _RESERVED)
        if clash:
            raise InputError("parameters", f"{parameters.__name__} with fields {clash}",
                             "fields whose names are not options of the CAPS pipeline",
                             "Prefix them with the prior's name, e.g. tikhonov_weight.")
    _PRIORS[key] = PriorSpec(key, factory, description, parameters)
    return factory


def register_data_term(name: str, factory: DataTermFactory, *, description: str = "") -> DataTermFactory:
    """Register the data term ``name``, chosen by ``-p data_term=NAME`` in every CAPS pipeline method.

    The data term is the data part ``f`` of the objective (paper eq. 15-18): an object with the
    :class:`~capssim.reconstruct.solvers.interfaces.DataFidelity` members ``image_shape``, ``value(x)``
    and ``descent_direction(x) -> (D, f(x))``, and optionally ``unobserved_mask() -> (C, H, W) bool``.
    Registering again under the same name replaces it.

    Parameters
    ----------
    name : str
        The data term's name, lower case, without spaces, ``=`` or ``,``.
    factory : callable
        ``factory(problem, *, options, stage) -> DataFidelity``, called once per
        :class:`~capssim.reconstruct.pipeline.problem.Problem` (observations, operator ``M``, homographies,
        calibrated mixing) with the run's ``CapsOptions`` and the stage timer factory ``stage(name)``.
    description : str
        One line for listings.

    Returns
    -------
    callable
        ``factory``, unchanged.
    """
    key = _check_name("data_term", name)
    _DATA_TERMS[key] = DataTermSpec(key, factory, description)
    return factory


def _check_name(kind: str, name: str) -> str:
    key = str(name).strip()
    if not key or key != key.lower() or any(c.isspace() or c in "=," for c in key):
        raise InputError(kind, repr(name), "a lower-case name without spaces, '=' or ','")
    return key


def available_priors() -> dict[str, PriorSpec]:
    """The registered priors, by name."""
    return dict(sorted(_PRIORS.items()))


def available_data_terms() -> dict[str, DataTermSpec]:
    """The registered data terms, by name."""
    return dict(sorted(_DATA_TERMS.items()))


def get_prior(name: str) -> PriorSpec:
    """The prior ``name``; an unknown name is an :class:`InputError` naming ``prior`` and the valid names."""
    return _lookup("prior", name, _PRIORS, "register_prior")


def get_data_term(name: str) -> DataTermSpec:
    """The data term ``name``; an unknown name is an :class:`InputError` naming ``data_term``."""
    return _lookup("data_term", name, _DATA_TERMS, "register_data_term")


def _lookup(kind: str, name: str, table: dict, register: str):
    key = str(name).strip()
    if key not in table:
        raise InputError(kind, repr(name), "one of " + ", ".join(sorted(table)),
                         f"Choose one with -p {kind}=NAME, or register yours first with "
                         f"capssim.reconstruct.pipeline.{register}(NAME, factory).")
    return table[key]


def parameter_defaults_of(parameters: type) -> dict:
    """``{field: default}`` of a parameters dataclass (every field needs a default)."""
    instance = parameters()
    return {f.name: getattr(instance, f.name) for f in fields(instance)}


def parameter_defaults(spec: PriorSpec) -> dict:
    """``{option: default}`` of the prior's own options (empty without ``parameters``)."""
    return {} if spec.parameters is None else parameter_defaults_of(spec.parameters)


def prior_option_names() -> frozenset[str]:
    """The own option names of every registered prior."""
    return frozenset(name for spec in _PRIORS.values() for name in parameter_defaults(spec))


#: the option names every prior shares (:mod:`.options` reserves them when it is imported)
_RESERVED: set[str] = set()


def reserve_option_names(names) -> None:
    """Keep a prior's own options from taking the names of the pipeline's shared options."""
    _RESERVED.update(names)


# -- built-in data terms ---------------------------------------------------------------------------
def problem_confidence(problem: Problem, *, options, stage: StageFactory) -> torch.Tensor:
    """CAGF's confidence ``L^H`` ``(C, C, H, W)`` between the channels of ``problem`` (eq. 12-14)."""
    obs = problem.obs
    with stage("cagf"):
        return cagf_confidence(problem.seen.images, problem.homographies, obs.channel_of, obs.n_channels,
                               problem.hr_shape, weights=obs.weights, nu=options.cagf.nu,
                               radius=options.cagf.radius, eps=options.cagf.eps)


def confidence_data_term(problem: Problem, *, options, stage: StageFactory) -> ConfidenceDataTerm:
    """Eq. 15-16 / 25-26: every observation back-projected onto every channel, weighted by CAGF (eq. 12-14)."""
    return ConfidenceDataTerm(problem.obs, problem.operator, mixing=problem.mixing,
                              confidence=problem_confidence(problem, options=options, stage=stage))


def split_data_term(problem: Problem, *, options, stage: StageFactory) -> PolarizationSplitDataTerm:
    """CAGF (eq. 12-14) with the polarization-split direction ``P L P B + (I - P) L_angle (I - P) B``
    (:mod:`capssim.reconstruct.model.polarization_split`; not the paper's)."""
    return PolarizationSplitDataTerm(problem.obs, problem.operator, mixing=problem.mixing,
                                     confidence=problem_confidence(problem, options=options, stage=stage))


def problem_agreement(problem: Problem, *, options, stage: StageFactory) -> torch.Tensor:
    """The analyzers' agreement ``alpha`` ``(H, W)`` of ``problem``, over CAGF's window and ``eps``
    (:func:`~capssim.reconstruct.model.analyzer_agreement.analyzer_agreement_map`); computed once per problem
    and window (``caps-plus``'s start and data term both use it), kept in ``problem.derived``."""
    key = ("agreement", options.cagf.radius, options.cagf.eps)
    if key not in problem.derived:
        obs = problem.obs
        with stage("agreement"):
            problem.derived[key] = analyzer_agreement_map(
                problem.seen.images, problem.homographies, obs.channel_of, obs.n_channels, problem.hr_shape,
                weights=obs.weights, radius=options.cagf.radius, eps=options.cagf.eps)
    return problem.derived[key]


def agreement_data_term(problem: Problem, *, options, stage: StageFactory,
                        term: type[AgreementDataTerm] = AgreementDataTerm) -> AgreementDataTerm:
    """``alpha L^H B + (1 - alpha)`` the split direction, ``alpha`` the analyzers' agreement
    (:mod:`capssim.reconstruct.model.analyzer_agreement`; not the paper's); ``term`` a subclass that changes only
    the mixing (``cagf-stokes``)."""
    return term(problem.obs, problem.operator, mixing=problem.mixing,
                confidence=problem_confidence(problem, options=options, stage=stage),
                agreement=problem_agreement(problem, options=options, stage=stage))


def stokes_data_term(problem: Problem, *, options, stage: StageFactory) -> StokesAgreementDataTerm:
    """``cagf-agree``'s direction projected onto the images linear polarization can produce, ``I_0 - I_45 + I_90 -
    I_135 = 0`` (:mod:`capssim.reconstruct.model.stokes_subspace`; not the paper's)."""
    return agreement_data_term(problem, options=options, stage=stage, term=StokesAgreementDataTerm)


def plain_data_term(problem: Problem, *, options, stage: StageFactory) -> ConfidenceDataTerm:
    """Eq. 15 without CAGF: each channel sees its own observations only (the ``caps-no-cagf`` ablation)."""
    return ConfidenceDataTerm(problem.obs, problem.operator, confidence=None, mixing=problem.mixing)


register_data_term("cagf", confidence_data_term,
                   description="confidence-guided data term (eq. 15-16, 25-26): all observations, weighted by CAGF")
register_data_term("cagf-split", split_data_term,
                   description="CAGF data term whose residual's polarization part is shared only within one "
                               "analyzer (not the paper's; caps-plus)")
register_data_term("cagf-agree", agreement_data_term,
                   description="cagf-split coupled across analyzers where their images agree (structure-aware "
                               "coupling; not the paper's)")
register_data_term("cagf-stokes", stokes_data_term,
                   description="cagf-agree kept to the Stokes subspace I0 - I45 + I90 - I135 = 0 (not the paper's; "
                               "caps-plus)")
register_data_term("plain", plain_data_term,
                   description="data term of each channel's own observations (eq. 15, no CAGF)")


# -- built-in priors -------------------------------------------------------------------------------
def nlstr_prior(shape: tuple[int, int, int], *, parameters, options, device: torch.device) -> NLSTRPrior:
    """NLSTR (section 3.3) over ``shape`` with the run's NLSTR parameters and block-matching schedule."""
    return NLSTRPrior(NonlocalSparseTensor(shape, options.nlstr, device=device), options.matching)


@dataclass(frozen=True)
class TikhonovParameters:
    """The ``tikhonov`` prior's option: ``tikhonov_weight``, lambda of ``R(X) = lambda/2 ||nabla X||^2``."""

    tikhonov_weight: float = 0.05

    def validate(self) -> None:
        if not (self.tikhonov_weight >= 0 and math.isfinite(self.tikhonov_weight)):
            raise InputError("tikhonov_weight", self.tikhonov_weight, "a finite number >= 0",
                             "Try -p tikhonov_weight=0.05.")


def tikhonov_prior(shape: tuple[int, int, int], *, parameters: TikhonovParameters, options,
                   device: torch.device) -> TikhonovPrior:
    """The quadratic smoothness prior of :mod:`capssim.reconstruct.priors.tikhonov` (closed-form proximal step)."""
    return TikhonovPrior(parameters.tikhonov_weight)


def nlstr_denoiser_prior(shape: tuple[int, int, int], *, parameters: DenoiserParameters, options,
                         device: torch.device) -> NLSTRDenoiserPrior:
    """NLSTR with its analyzer mean blended with the learned denoiser's (not the paper's; ``caps-plus-cv``,
    :mod:`capssim.reconstruct.priors.nlstr_denoiser`)."""
    denoiser = denoiser_model(parameters.denoiser_weights, device)
    if shape[0] != denoiser.channels:
        raise InputError("prior", f"nlstr-denoiser on {shape[0]}-channel images",
                         f"{denoiser.channels}-channel images, as its denoiser was trained (caps, caps-plus: 12)",
                         "Use it with a 12-channel CAPS method, not caps-iccp; or -p prior=nlstr.")
    return NLSTRDenoiserPrior(nlstr_prior(shape, parameters=None, options=options, device=device), denoiser,
                              parameters, options.admm.iterations)


register_prior("nlstr", nlstr_prior, description="nonlocal sparse tensor (paper section 3.3): the paper's prior")
register_prior("tikhonov", tikhonov_prior, parameters=TikhonovParameters,
               description="quadratic smoothness lambda/2 ||grad X||^2 (not the paper's; -p tikhonov_weight=W)")
register_prior("nlstr-denoiser", nlstr_denoiser_prior, parameters=DenoiserParameters,
               description="NLSTR, its analyzer mean blended with a learned denoiser's (not the paper's; "
                           "caps-plus-cv; -p denoiser_blend=W)")
register_prior("none", None, description="no prior: the data term alone, by steepest descent (eq. 16)")
