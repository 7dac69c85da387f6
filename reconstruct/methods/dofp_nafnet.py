"""``dofp-nafnet``: a learned colour-polarization DoFP demosaicker, a NAFNet-style U-Net over IGRI2.

References: Chen, Chu, Zhang, Sun, "Simple Baselines for Image Restoration", ECCV 2022 (NAFNet, the
block); Morimatsu, Monno, Tanaka, Okutomi, IEEE Sensors Journal 21(23) 2021 (IGRI2, the start); the
architecture and its loss: :mod:`capssim.reconstruct.networks.nafnet`.

Input: the capture's DoFP mosaic ``(H, W)`` on [0, 1], its layout and its sensor's noise model (the
noise std at each sample, :func:`capssim.camera.sensor.noise_std_map`; 0 for a capture without
noise). Output ``(12, H, W)`` (``c = 3p + k``): IGRI2 plus the network's correction, which removes
noise and demosaicking errors together. The network reads the noise std clamped to
:data:`TRAINED_NOISE_STD_MAX`, the largest it was trained on: beyond it the correction is an extrapolation
(a flat mosaic said to have std 0.2 came out up to 0.16 off, 0.01 with the clamp). Option
``weights=PATH``: a model file from ``capssim train`` (default: the shipped ``weights/dofp-nafnet.pt``,
trained by ``examples/train-dofp-nafnet.yaml`` on development data only: renders and the real scenes that
the frozen test suite does not use).
Option ``guard`` (default false): the discrepancy guard (:mod:`capssim.reconstruct.networks.discrepancy_guard`):
where the network's output, sampled as the sensor samples it, departs from the mosaic by more than its noise
explains (noise std at least :data:`TRAINED_NOISE_STD_MIN`), it is moved towards IGRI2. The share it takes, or
would take, from IGRI2 is always computed: the record gives it (``discrepancy_share``) and a warning names it
above :data:`DISCREPANCY_WARNING`. On development data the guard rescues a network on a scene unlike its training
data (+1.6 dB on the Qiu scenes for weights trained without them) but costs the shipped weights 0.13 dB on their
development suites (up to 1 dB on dense Siemens stars and noise-free captures), so it is off by default
(docs/results/dofp-nafnet.md).
Mosaics larger than :data:`TILE` px run in tiles with a :data:`HALO` px halo; the network's channel
attention averages over its input, so a tiled result differs slightly from an untiled one.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from capssim.camera.sensor import noise_std_map
from capssim.captures.capture import Capture
from capssim.errors import InputError

from ..dofp.bilinear import dofp_unobserved
from ..dofp.mosaic import check_mosaic
from ..kernel_regression.steering import noise_sigma
from ..networks import load_model, shipped_weights, weights_option
from ..networks.cpdnet import sparse_channels
from ..networks.discrepancy_guard import discrepancy_guard, discrepancy_share
from ..networks.tiling import apply_tiled
from ..pipeline import coerce_option
from ..pipeline.option_table import MethodOption
from ..registry import MethodOutput, RunContext, register_method
from ..run_context import stage_factory
from .dofp_igri2 import demosaic_dofp_igri2

log = logging.getLogger(__name__)

REFERENCE = ("Chen, Chu, Zhang, Sun, 'Simple Baselines for Image Restoration', ECCV 2022 (NAFNet); over IGRI2 "
             "(Morimatsu et al., IEEE Sensors Journal 21(23) 2021); trained with capssim train")
SHIPPED = "dofp-nafnet"
NETWORK = "dofp-nafnet"
#: the suites that score scenes it was trained on (examples/dataset-train-dofp.yaml: the development real scenes)
TUNED_ON = ("dev", "quick", "ablation", "baselines", "calibration", "full", "learned", "paper")
#: the largest noise std (on [0, 1]) of the shipped weights' training set (examples/dataset-train-dofp.yaml: white
#: Gaussian sigma 0.002-0.02; the imx250myr sensor reaches 0.0098); the network reads at most this. Measured on a
#: 64 px natural scene against reading the true std: -0.12 dB at sigma 0.05, -0.43 at 0.1, +0.58 at 0.2 (IGRI2 is
#: 2-3 dB lower at each)
TRAINED_NOISE_STD_MAX = 0.02
#: the smallest noise std of its training set: the discrepancy guard's floor (on a noise-free mosaic the output may
#: depart from each sample by about this much before the guard acts)
TRAINED_NOISE_STD_MIN = 0.002
#: tiles of the network's input (px, a multiple of 16) and their halo (px)
TILE, HALO = 1024, 64
#: the mean share the discrepancy guard would take from IGRI2 above which the method warns (the shipped weights: at
#: most 0.035 on the development captures other than the stars, 0.04-0.69 on the Siemens and polarization stars,
#: 0.07-0.09 on two of the test suite's twelve real-scene cases, both with the imx250myr sensor)
DISCREPANCY_WARNING = 0.05


def dofp_nafnet_input(mosaic: torch.Tensor, layout, noise_std: torch.Tensor,
                      timer=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(N, H, W)`` mosaics and noise stds -> ``(sparse, igri2, noise_std)``: ``(N, 12, H, W)`` twice and
    ``(N, 1, H, W)``, float32 on the mosaics' device."""
    stage = stage_factory(timer)
    mosaic = mosaic.to(torch.float32)
    with stage("igri2"):
        base = torch.stack([demosaic_dofp_igri2(m, layout=layout) for m in mosaic])
    return sparse_channels(mosaic, layout), base, noise_std.to(mosaic)[:, None]


def run_dofp_nafnet(model, mosaic: torch.Tensor, layout, noise_std: torch.Tensor, timer=None, *,
                    guard: bool = False) -> tuple[torch.Tensor, float]:
    """``(H, W)`` mosaic and noise std tensors -> ``(12, H, W)`` float32 on the mosaic's device (the std read at
    most :data:`TRAINED_NOISE_STD_MAX`), with the discrepancy guard applied if ``guard``, and the mean share the
    guard takes (or would take) from IGRI2."""
    stage = stage_factory(timer)
    inputs = dofp_nafnet_input(mosaic[None], layout, noise_std[None].clamp(max=TRAINED_NOISE_STD_MAX), timer)
    with stage("network"):
        image = apply_tiled(model, inputs, tile=TILE, halo=HALO, step=16)[0]
    image = image.clamp(0.0, max(1.0, float(mosaic.max())))
    with stage("guard"):
        if guard:
            image, share = discrepancy_guard(image, inputs[1][0], mosaic, noise_std, layout,
                                             noise_floor=TRAINED_NOISE_STD_MIN)
        else:
            share = discrepancy_share(image, mosaic, noise_std, layout, noise_floor=TRAINED_NOISE_STD_MIN)
    mean_share = float(share.mean())
    if mean_share > DISCREPANCY_WARNING and not guard:
        log.warning("dofp-nafnet: its output departs from the raw samples by more than their noise explains on "
                    "about %.0f %% of the frame (a scene unlike its training data, or detail finer than the sensor "
                    "samples, such as a dense star); -p guard=true moves it towards IGRI2 there", 100 * mean_share)
    return image, mean_share


def dofp_nafnet_options() -> list[MethodOption]:
    """Every ``-p`` option of ``dofp-nafnet`` (``capssim reconstruct --options dofp-nafnet``)."""
    return [MethodOption("weights", "(the shipped dofp-nafnet)", "a model file written by capssim train",
                         "the network's weights"),
            MethodOption("guard", False, "true or false",
                         "the discrepancy guard: move the output towards IGRI2 where it contradicts the raw samples")]


def nafnet_options(options: dict) -> tuple[Path, bool]:
    """The model file (``weights=PATH``, default the shipped one) and ``guard`` (default false) of ``options``."""
    opts = dict(options)
    raw = opts.pop("guard", False)
    try:
        guard = coerce_option("guard", raw, bool)
    except InputError:
        raise InputError("option guard", repr(raw), "true or false",
                         "Write -p guard=true to turn the discrepancy guard on, -p guard=false to leave it off.") from None
    return weights_option(opts, SHIPPED, also=("guard",)), guard


def mosaic_noise_std(mosaic: torch.Tensor) -> float:
    """White-noise std on [0, 1] of an ``(H, W)`` mosaic with no noise model: Immerkaer's estimate over its 16
    single-channel sub-mosaics (period 4: the 2x2 polarizer cell under the 2x2 Bayer cell), their median."""
    h, w = (s - s % 4 for s in mosaic.shape)
    subs = mosaic[:h, :w].reshape(h // 4, 4, w // 4, 4).permute(1, 3, 0, 2).reshape(16, h // 4, w // 4)
    return noise_sigma(subs)


def demosaic_dofp_nafnet(mosaic, *, layout="sony", noise_std=None, device=None, timer=None, weights=None,
                         guard: bool = False):
    """The plain array form: ``(H, W)`` mosaic (numpy or tensor) -> ``(12, H, W)`` with the shipped weights.

    ``noise_std``: the noise std on [0, 1], a number or an ``(H, W)`` map (0: a noise-free mosaic; None:
    estimated from the mosaic, :func:`mosaic_noise_std`, as for a real raw frame without a noise model).
    ``guard``: the discrepancy guard (module docstring).
    """
    x = check_mosaic(mosaic, device=device).to(torch.float32)
    noise_std = mosaic_noise_std(x) if noise_std is None else noise_std
    sigma = torch.as_tensor(np.asarray(noise_std, dtype=np.float32), device=x.device).expand(x.shape)
    model, _ = load_model(weights or shipped_weights(SHIPPED), device=x.device, expect=NETWORK)
    image, _ = run_dofp_nafnet(model, x, layout, sigma, timer, guard=guard)
    return image.cpu().numpy() if isinstance(mosaic, np.ndarray) else image


@register_method("dofp-nafnet", input_kind="dofp", array_function=demosaic_dofp_nafnet, reference=REFERENCE,
                 tuned_on=TUNED_ON, options=dofp_nafnet_options,
                 description="NAFNet-style U-Net over IGRI2 with the sensor's noise map, trained with capssim train on "
                             "development data; options weights=PATH (default: the shipped dofp-nafnet), guard=true|false (the "
                             "discrepancy guard, default false)")
def dofp_nafnet(capture: Capture, *, context: RunContext) -> MethodOutput:
    path, guard = nafnet_options(context.options)
    with context.timer.stage("load_model"):
        model, record = load_model(path, device=context.device, expect=NETWORK)
        mosaic = capture.dofp_float()
        noise_std = torch.from_numpy(noise_std_map(capture.sensor, mosaic)).to(context.device)
        mosaic = torch.from_numpy(mosaic).to(context.device)
    image, share = run_dofp_nafnet(model, mosaic, capture.dofp_layout, noise_std, context.timer, guard=guard)
    with context.timer.stage("to_host"):
        image = image.to("cpu", torch.float32).numpy()
    training = record.get("training", {})
    return MethodOutput(image=image,
                        params={"weights": str(path), "network": record["network"], "network_params": record["params"],
                                "training_steps": training.get("steps"), "layout": [list(r) for r in capture.dofp_layout],
                                "noise_model": capture.sensor.model,
                                "noise_std_read_at_most": TRAINED_NOISE_STD_MAX, "guard": guard,
                                "guard_noise_floor": TRAINED_NOISE_STD_MIN, "discrepancy_share": share},
                        extra={"training_validation_psnr_db": training.get("validation_psnr_db")},
                        unobserved=lambda: dofp_unobserved(capture.dofp_saturated(), capture.dofp_layout))
