"""The paper's CAPS reconstruction and two of its ablations (section 3-5, Fig. 3, Algorithm 1).

Reference: "Joint constraints of guided filtering based confidence and nonlocal sparse
tensor for color polarization super-resolution imaging", Optics Express 32(2), 2364 (2024).

Each method is a configuration of the CAPS pipeline (:mod:`capssim.reconstruct.pipeline`):

1. rearrangement of the 4 RGGB frames into 16 observations (``capssim.reconstruct.model.rearrange``, 3.1),
   registration (the stored homographies under ``--true-warps``, or ``capssim.reconstruct.registration``)
   and the sampling operator ``M`` (:func:`capssim.reconstruct.pipeline.front_end.caps_observations`);
2. the data term: CAGF confidence between all channel pairs (``capssim.reconstruct.model.cagf``, eq. 12-14)
   guiding the data term (``capssim.reconstruct.model.data_term``, eq. 15-16, 25-26);
3. initialization fusing all 16 observations on the HR grid (``capssim.reconstruct.model.init_fusion``);
4. the prior: NLSTR (``capssim.reconstruct.priors.nlstr_prior`` with ``capssim.reconstruct.priors.nlstr``, 3.3);
5. ADMM (``capssim.reconstruct.solvers.admm``, eq. 20-30).

Ablations (section 5.2), the same pipeline with one slot changed each:

* ``caps-no-cagf``: ``data_term=plain``, the data term uses only the observations of the same channel;
* ``caps-no-nlstr``: ``prior=none``, the data term only (steepest descent of eq. 16 from the same
  initialization, ``capssim.reconstruct.solvers.descent``).

``caps-iccp`` (the cascade) lives in :mod:`capssim.reconstruct.methods.caps_iccp`. ``-p prior=NAME``
and ``-p data_term=NAME`` swap the slots of any of them (:mod:`capssim.reconstruct.pipeline.slots`).

The sampling operator ``M`` is the shared observation model
``capssim.operators.lr_sampling_operator`` with the capture's PSF (the paper uses an
isotropic Gaussian kernel; simulated captures store a Gaussian PSF, and ``psf_sigma``
overrides it, e.g. for real captures). With a calibration (``capssim reconstruct --calibration``)
the front end models the calibrated array (:mod:`capssim.reconstruct.pipeline.front_end`).
"""

from __future__ import annotations

from ..pipeline import PRESETS, CapsOptions, PipelineConfig, run_pipeline
from ..pipeline.option_table import caps_method_options
from ..registry import MethodOutput, RunContext, register_method

__all__ = ["CAPS", "NO_CAGF", "NO_NLSTR", "PRESETS", "REFERENCE", "CapsOptions"]

REFERENCE = "Optics Express 32(2) 2364 (2024), sections 3-5"

#: the paper's method: CAGF-guided data term, NLSTR prior, ADMM
CAPS = PipelineConfig()
#: ablation 'No CAGF' (5.2): each channel's own observations only
NO_CAGF = PipelineConfig(defaults={"data_term": "plain"})
#: ablation 'No NLSTR' (5.2): the data term alone, by steepest descent
NO_NLSTR = PipelineConfig(defaults={"prior": "none"})


@register_method("caps", input_kind="caps", options=lambda: caps_method_options(CAPS.defaults), reference=REFERENCE,
                 description="CAPS: CAGF-confidence-guided data term + nonlocal sparse tensor regularization, ADMM "
                             "(joint demosaicking, 4x SR of each Bayer sub-image, denoising)")
def caps(capture, *, context: RunContext) -> MethodOutput:
    return run_pipeline(capture, context, CAPS)


@register_method("caps-no-cagf", input_kind="caps", options=lambda: caps_method_options(NO_CAGF.defaults), reference=REFERENCE + " (ablation 'No CAGF', 5.2)",
                 description="CAPS ablation: the data term uses only the observations of the same channel")
def caps_no_cagf(capture, *, context: RunContext) -> MethodOutput:
    return run_pipeline(capture, context, NO_CAGF)


@register_method("caps-no-nlstr", input_kind="caps", options=lambda: caps_method_options(NO_NLSTR.defaults), reference=REFERENCE + " (ablation 'No NLSTR', 5.2)",
                 description="CAPS ablation: confidence-guided data term only (no nonlocal sparse tensor prior)")
def caps_no_nlstr(capture, *, context: RunContext) -> MethodOutput:
    return run_pipeline(capture, context, NO_NLSTR)
