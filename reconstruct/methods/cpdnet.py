"""``cpdnet``: the CPDNet colour-polarization demosaicking network, trained here on capssim datasets.

Reference: S. Wen, Y. Zheng, F. Lu, Q. Zhao, "Convolutional demosaicing network for joint chromatic
and polarimetric imagery", Optics Letters 44(22) 5646, 2019; the architecture and its loss:
:mod:`capssim.reconstruct.networks.cpdnet`.

Input: the capture's DoFP mosaic ``(H, W)`` on [0, 1] and its layout. Output ``(12, H, W)``
(``c = 3p + k``). Option ``weights=PATH``: a model file from ``capssim train`` (default: the shipped
``weights/cpdnet-small.pt``, trained by ``examples/train-cpdnet-small.yaml`` on rendered scenes that
exclude every scene of the quick and paper suites). Large mosaics run in 256 px tiles with a 16 px
halo (the network's receptive radius is 12 px), which gives the untiled result.
"""

from __future__ import annotations

import numpy as np
import torch

from capssim.captures.capture import Capture

from ..dofp.bilinear import dofp_unobserved
from ..dofp.mosaic import check_mosaic
from ..networks import load_model, shipped_weights, weights_option
from ..networks.cpdnet import dofp_network_input
from ..networks.tiling import apply_tiled
from ..registry import MethodOutput, RunContext, register_method
from ..run_context import stage_factory

REFERENCE = ("Wen, Zheng, Lu, Zhao, 'Convolutional demosaicing network for joint chromatic and polarimetric "
             "imagery', Optics Letters 44(22) 5646, 2019; trained with capssim train")
SHIPPED = "cpdnet-small"


def run_cpdnet(model, mosaic: torch.Tensor, layout, timer=None) -> torch.Tensor:
    """``(H, W)`` mosaic tensor -> ``(12, H, W)`` float32 on the mosaic's device."""
    stage = stage_factory(timer)
    with stage("network_input"):
        sparse, bilinear = dofp_network_input(mosaic[None], layout)
    with stage("network"):
        image = apply_tiled(lambda s, b: model(s, b)[0], (sparse, bilinear), tile=256, halo=16, step=4)[0]
    return image.clamp(0.0, max(1.0, float(mosaic.max())))


def demosaic_dofp_cpdnet(mosaic, *, layout="sony", device=None, timer=None, weights=None):
    """The plain array form: ``(H, W)`` mosaic (numpy or tensor) -> ``(12, H, W)`` with the shipped weights."""
    x = check_mosaic(mosaic, device=device)
    model, _ = load_model(weights or shipped_weights(SHIPPED), device=x.device, expect="cpdnet")
    image = run_cpdnet(model, x.to(torch.float32), layout, timer)
    return image.cpu().numpy() if isinstance(mosaic, np.ndarray) else image


@register_method("cpdnet", input_kind="dofp", array_function=demosaic_dofp_cpdnet, reference=REFERENCE,
                 description="CPDNet (colour module, then polarization module), trained with capssim train; "
                             "option weights=PATH (default: the shipped cpdnet-small)")
def cpdnet(capture: Capture, *, context: RunContext) -> MethodOutput:
    path = weights_option(context.options, SHIPPED)
    with context.timer.stage("load_model"):
        model, record = load_model(path, device=context.device, expect="cpdnet")
        mosaic = torch.from_numpy(capture.dofp_float()).to(context.device)
    image = run_cpdnet(model, mosaic, capture.dofp_layout, context.timer)
    with context.timer.stage("to_host"):
        image = image.to("cpu", torch.float32).numpy()
    training = record.get("training", {})
    return MethodOutput(image=image,
                        params={"weights": str(path), "network": record["network"], "network_params": record["params"],
                                "training_steps": training.get("steps"), "layout": [list(r) for r in capture.dofp_layout]},
                        extra={"training_validation_psnr_db": training.get("validation_psnr_db")},
                        unobserved=lambda: dofp_unobserved(capture.dofp_saturated(), capture.dofp_layout))
