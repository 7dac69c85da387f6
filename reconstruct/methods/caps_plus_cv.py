"""``caps-plus-cv``: ``caps-plus`` whose selection layer also chooses the prior, between NLSTR alone and NLSTR
blended with a learned denoiser. Not the paper's method; kept as a named ablation of ``caps-plus``.

Everything is ``caps-plus`` (:mod:`.caps_plus`), except the prior: ``nlstr-denoiser``
(:mod:`capssim.reconstruct.priors.nlstr_denoiser`), NLSTR whose analyzer-mean (intensity) part is averaged with a
small learned Gaussian denoiser's (trained on rendered scenes only; ``reconstruct/weights/denoiser.pt``). The
selection layer (:mod:`capssim.reconstruct.selection`) validates the blends ``w`` of :data:`BLEND_CANDIDATES` in
turn (``w = 0`` is NLSTR alone, ``caps-plus``'s prior) on the central window until the held-out error rises, and
the solve runs the blend and count of the lowest error (hold-out validation for model selection; Stone,
"Cross-validatory choice and assessment of statistical predictions", J. R. Stat. Soc. B 36(2) 1974). The
denoiser's noise level falls from 0.05 to 0.005 over the first 15 iterations and then stays, so that iteration
``k`` of a validation is a ``k``-iteration run. ``-p denoiser_blend=W`` fixes the blend.

Where it wins and loses against ``caps-plus``: docs/results/caps-plus.md.
"""

from __future__ import annotations

from dataclasses import replace

from ..registry import MethodOutput, RunContext, register_method
from .caps import REFERENCE as CAPS_REFERENCE
from .caps_plus import CAPS_PLUS, caps_plus_frame_choices, caps_plus_options, run_caps_plus

__all__ = ["BLEND_CANDIDATES", "CAPS_PLUS_CV", "DENOISER_SIGMA_STEPS"]

#: the ``nlstr-denoiser`` blends validated, in this order: NLSTR alone, half, three quarters of the intensity
BLEND_CANDIDATES = (0.0, 0.5, 0.75)
#: iterations over which the denoiser's noise level falls (then it stays at its end level)
DENOISER_SIGMA_STEPS = 15

#: caps-plus with the ``nlstr-denoiser`` prior; no polarization filter unless asked (caps-plus's default filter was
#: chosen without this ablation, whose scores were measured without it)
CAPS_PLUS_CV = replace(CAPS_PLUS, defaults={**CAPS_PLUS.defaults, "prior": "nlstr-denoiser",
                                            "denoiser_sigma_steps": DENOISER_SIGMA_STEPS},
                       front_end_options={**CAPS_PLUS.front_end_options, "polarization_filter": "none"})


def _options():
    return caps_plus_options(CAPS_PLUS_CV)


def _frame_choices(capture, options, *, homographies, device):
    return caps_plus_frame_choices(capture, options, homographies=homographies, device=device, config=CAPS_PLUS_CV,
                                   name="caps-plus-cv", blends=BLEND_CANDIDATES)


@register_method("caps-plus-cv", input_kind="caps", frame_options=_frame_choices, options=_options,
                 tuned_on=("baselines", "paper", "ablation", "quick"),
                 reference=CAPS_REFERENCE + " with capssim's changes and a learned denoiser (not the paper's)",
                 description="ablation of caps-plus: its selection layer also chooses the prior (NLSTR alone, or "
                             "blended with a learned denoiser) per frame by held-out raw pixels (not the paper's)")
def caps_plus_cv(capture, *, context: RunContext) -> MethodOutput:
    return run_caps_plus(capture, context, CAPS_PLUS_CV, name="caps-plus-cv", blends=BLEND_CANDIDATES)
