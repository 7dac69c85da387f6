"""``caps-plus-cv``: ``caps-plus`` whose prior is chosen for each capture by held-out raw pixels, between NLSTR
alone and NLSTR blended with a learned denoiser. Not the paper's method: capssim's own configuration beside it.

``caps-plus`` (:mod:`.caps_plus`) and ``caps-plus-pnp`` (:mod:`.caps_plus_pnp`) each win on some kinds of scene:
the learned denoiser restores fine rendered and synthetic texture, NLSTR alone keeps the real photographs, the
3-D scenes and polarization-only structure (docs: results/caps-plus.md). ``caps-plus-cv`` runs ``caps-plus``'s
held-out validation (:mod:`capssim.reconstruct.model.holdout`: 5 % of the raw pixels left out, predicted through
``M``, eq. 15, after every iteration) for the ``nlstr-denoiser`` prior's blends ``w`` in turn (``-p
blend_candidates=0,0.5,0.75``; ``w = 0`` is NLSTR alone, exactly ``caps-plus``'s prior) until the held-out error
rises, on the central 256 px window of a larger frame or on the whole of a smaller one, and solves the whole
problem with every pixel once, with the ``w`` and the iteration count of the lowest held-out error
(``-p holdout_rule=one-se`` takes the earliest count within one standard error of it instead,
:mod:`capssim.reconstruct.model.holdout`). This is model selection by hold-out validation (cross-validation with
one fold; Stone, "Cross-validatory choice and assessment of statistical predictions", J. R. Stat. Soc. B 36(2)
1974).

Its start blends the whole image by the analyzers' agreement ``alpha`` (``-p init=agree-all``: ``alpha`` times
eq. 24's fusion plus ``1 - alpha`` times the demosaicked apertures, each aperture's Bayer frame demosaicked,
registered and resampled to the HR grid as ``caps-naive`` does). ``caps-plus`` (``init=agree``) blends only the
polarization part and always takes the fusion's analyzer mean, which averages the four apertures' sampling of
detail that only some analyzers see; where the analyzers disagree (polarization-only structure) ``agree-all``
takes the apertures' own mean instead. ``-p init=agree`` restores ``caps-plus``'s start.

The denoiser's noise level falls from 0.05 to 0.005 over the first 15 iterations and then stays
(``denoiser_sigma_steps=15``), so that iteration ``k`` of a validation run is a ``k``-iteration run, which
held-out stopping assumes (``caps-plus-pnp`` spreads it over the whole run instead). ``-p`` options of
``caps-plus-pnp`` apply; ``-p denoiser_blend=W``, ``-p iterations=N`` or ``-p stopping=noise`` fix what they
name and turn the choice off. The record keeps every candidate's held-out error (``holdout_candidates``) and
the choice (``holdout_choice``).
"""

from __future__ import annotations

from dataclasses import replace

from ..pipeline import run_pipeline
from ..registry import MethodOutput, RunContext, register_method
from .caps import REFERENCE as CAPS_REFERENCE
from .caps_plus import CAPS_PLUS, frame_iterations

__all__ = ["BLEND_CANDIDATES", "CAPS_PLUS_CV", "DENOISER_SIGMA_STEPS"]

#: the ``nlstr-denoiser`` blends validated, in this order: NLSTR alone, ``caps-plus-pnp``'s half share of the
#: intensity, then three quarters
BLEND_CANDIDATES = "0,0.5,0.75"
#: iterations over which the denoiser's noise level falls (then it stays at its end level)
DENOISER_SIGMA_STEPS = 15

#: caps-plus from the agreement blend of the whole start with the ``nlstr-denoiser`` prior, whose blend and count
#: the held-out pixels choose
CAPS_PLUS_CV = replace(CAPS_PLUS,
                       defaults={**CAPS_PLUS.defaults, "prior": "nlstr-denoiser",
                                 "denoiser_sigma_steps": DENOISER_SIGMA_STEPS},
                       front_end_options={**CAPS_PLUS.front_end_options, "blend_candidates": BLEND_CANDIDATES,
                                          "init": "agree-all"})


@register_method("caps-plus-cv", input_kind="caps", frame_options=frame_iterations,
                 reference=CAPS_REFERENCE + " with capssim's changes and a learned denoiser (not the paper's)",
                 description="caps-plus with the whole start blended by the analyzers' agreement, whose prior (NLSTR "
                             "alone, or blended with a learned denoiser) and iteration count are chosen per capture "
                             "by held-out raw pixels (not the paper's)")
def caps_plus_cv(capture, *, context: RunContext) -> MethodOutput:
    return run_pipeline(capture, context, CAPS_PLUS_CV)
