"""The CAPS pipeline: registration -> operator -> data term -> prior -> solver -> physical projection.

``caps``, its ablations and ``caps-iccp`` are configurations of it (:class:`PipelineConfig`, run by
:func:`run_pipeline`, :mod:`.run`). The data term and the prior are slots chosen by name
(``-p data_term=NAME``, ``-p prior=NAME``); :func:`register_prior` and :func:`register_data_term` add
new ones (:mod:`.slots`). The options every CAPS method shares are :class:`CapsOptions`; every method
parses its own options with :func:`coerce_option` (:mod:`.options`). The front end of ``caps`` is
:mod:`.front_end`, what it hands on :mod:`.problem`, the ground-truth diagnostics :mod:`.diagnostics`.
"""

from .diagnostics import channel_mean_psnr, mean_psnr, psnr_observer
from .front_end import caps_observations
from .options import (
    PRESETS,
    CapsOptions,
    caps_option_names,
    coerce_option,
    explain_divergence,
)
from .problem import FrontEnd, Problem
from .run import PipelineConfig, parse_pipeline_options, run_pipeline
from .slots import (
    available_data_terms,
    available_priors,
    get_data_term,
    get_prior,
    register_data_term,
    register_prior,
)

__all__ = ["PRESETS", "CapsOptions", "FrontEnd", "PipelineConfig", "Problem", "available_data_terms",
           "available_priors", "caps_observations", "caps_option_names", "channel_mean_psnr", "coerce_option",
           "explain_divergence", "get_data_term", "get_prior", "mean_psnr", "parse_pipeline_options",
           "psnr_observer", "register_data_term", "register_prior", "run_pipeline"]
