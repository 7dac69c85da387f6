"""``caps-plus-pnp``: ``caps-plus`` with a learned plug-and-play denoiser in its prior. Not the paper's method:
capssim's own configuration beside it.

Everything is ``caps-plus`` (:mod:`.caps_plus`: the structure-aware CAGF data term, the agreement
initialization, ADMM from ``mu0 = 0.25`` with ``c2 = 0.01`` for ``clip(10 + 1000 sigma, 10, 50)`` iterations)
except the prior: ``nlstr-denoiser`` (:mod:`capssim.reconstruct.priors.nlstr_denoiser`), NLSTR whose
analyzer-mean (intensity) part is averaged with that of a small learned Gaussian denoiser at every ADMM
iteration, the denoiser's noise level falling from 0.05 to 0.005 over the run. The denoiser
(:class:`~capssim.reconstruct.networks.denoiser.NoiseLevelDenoiser`, 7 layers, 48 features) was trained by
``capssim train examples/train-denoiser.yaml`` on the rendered training scenes only; its weights ship as
``reconstruct/weights/denoiser.pt`` (``-p denoiser_weights=RUN/model.pt`` takes another).

``-p`` options of ``caps-plus`` apply, and the prior's own: ``denoiser_blend`` (the denoiser's share of the
intensity, 0.5), ``denoiser_sigma_start``, ``denoiser_sigma_end``. Where it wins and loses:
docs/results/caps-plus.md.
"""

from __future__ import annotations

from dataclasses import replace

from ..pipeline import run_pipeline
from ..registry import MethodOutput, RunContext, register_method
from .caps import REFERENCE as CAPS_REFERENCE
from .caps_plus import CAPS_PLUS, frame_iterations

__all__ = ["CAPS_PLUS_PNP"]

#: caps-plus with the ``nlstr-denoiser`` prior, its count from the noise level (the denoiser's noise level falls
#: over the whole run, so a run's iteration ``k`` is not a ``k``-iteration run, which held-out stopping assumes)
CAPS_PLUS_PNP = replace(CAPS_PLUS, defaults={**CAPS_PLUS.defaults, "prior": "nlstr-denoiser"},
                        front_end_options={**CAPS_PLUS.front_end_options, "stopping": "noise"})


@register_method("caps-plus-pnp", input_kind="caps", frame_options=frame_iterations,
                 reference=CAPS_REFERENCE + " with capssim's changes and a learned denoiser (not the paper's)",
                 description="caps-plus whose NLSTR prior shares the intensity with a learned plug-and-play "
                             "denoiser trained on rendered scenes (not the paper's)")
def caps_plus_pnp(capture, *, context: RunContext) -> MethodOutput:
    return run_pipeline(capture, context, CAPS_PLUS_PNP)
