"""``dofp-bilinear``: two-step bilinear demosaicking of a colour-polarization DoFP mosaic.

The algorithm and its reference: :mod:`capssim.reconstruct.dofp.bilinear`.
"""

from __future__ import annotations

import torch

from capssim.captures.capture import Capture

from ..dofp.bilinear import demosaic_dofp_bilinear, dofp_unobserved
from ..dofp.method_body import reject_unknown_options
from ..registry import MethodOutput, RunContext, register_method

REFERENCE = ("Two-step bilinear colour-polarization demosaicking: bilinear Bayer demosaicking of each polarizer "
             "sub-mosaic, then bilinear interpolation of each polarizer lattice (polanalyser COLOR_PolarRGB; "
             "'Bilinear' baseline of Morimatsu et al., ICIP 2020)")


@register_method("dofp-bilinear", input_kind="dofp", array_function=demosaic_dofp_bilinear,
                 description="DoFP colour-polarization camera, two-step bilinear demosaicking (Bayer, then polarization)",
                 reference=REFERENCE)
def dofp_bilinear(capture: Capture, *, context: RunContext) -> MethodOutput:
    """Demosaick ``capture.dofp_float()`` with :func:`demosaic_dofp_bilinear`; layout from meta.json (no options)."""

    reject_unknown_options(context.options, [])
    with context.timer.stage("load"):
        mosaic = torch.from_numpy(capture.dofp_float()).to(context.device)
        saturated = capture.dofp_saturated()
        n_saturated = int(saturated.sum())
    image = demosaic_dofp_bilinear(mosaic, layout=capture.dofp_layout, timer=context.timer)
    with context.timer.stage("to_host"):
        image = image.to("cpu", torch.float32).numpy()
    return MethodOutput(image=image, params={"layout": [list(r) for r in capture.dofp_layout]},
                        extra={"n_saturated_pixels": n_saturated,
                               "saturation_handling": "none (interpolation uses saturated samples as they are)"},
                        unobserved=lambda: dofp_unobserved(saturated, capture.dofp_layout))
