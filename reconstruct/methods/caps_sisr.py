"""``caps-sisr``: camera-array baseline with a pluggable x2 single-image SR model.

Reference: the single-image SR comparison of "Joint constraints of guided filtering based
confidence and nonlocal sparse tensor for color polarization super-resolution imaging",
Optics Express 32(2), 2364 (2024), section 5.2 (EDSR / SwinIR / HAT applied after
demosaicking). The shipped EDSR weights were trained here (capssim train); nothing is downloaded.

1. Demosaicking and registration as ``caps-naive`` (:mod:`capssim.reconstruct.methods.caps_naive`).
2. x2 upsampling of each demosaicked aperture frame ``(3, H, W) -> (3, 2H, 2W)`` (the
   aperture-HR grid: ``F.interpolate`` x2 with ``align_corners=False`` puts output pixel
   ``j`` at raw coordinate ``j / 2 - 1/4``, which is :func:`capssim.camera.array_geometry.raw_matrix`):

   * no ``model`` option: the shipped x2 EDSR ``weights/edsr-small.pt``
     (:mod:`capssim.reconstruct.networks.edsr`, trained by ``examples/train-edsr-small.yaml`` on
     rendered scenes that exclude every scene of the quick and paper suites), the paper's DL-SISR row;
   * ``model=PATH.pt`` written by ``capssim train`` (an ``edsr`` model file), or a TorchScript
     module (``torch.jit.save``), run on the method's device;
   * ``model=PATH.onnx``: an ONNX model run by ``onnxruntime`` (optional dependency:
     ``pip install onnxruntime``);
   * ``model=bicubic``: bicubic ``F.interpolate`` (recorded as ``upsampler: bicubic (no model)``).

   The model receives float32 ``(N, C, H, W)`` and must return ``(N, C, 2H, 2W)``:
   ``model_channels=1`` (default for TorchScript/ONNX) feeds the 12 colour-polarization channels as a batch of
   12 single-channel images (per channel), ``model_channels=3`` the 4
   apertures as RGB images (the usual input of EDSR/SwinIR/HAT; a capssim model file sets it). ``model_scale``
   multiplies the input and divides the output (e.g. 255 for models trained on 0..255).
3. Registration of the upsampled frames onto the reference grid: one bicubic warp by
   ``H_n`` (aperture-HR -> HR reference; the identity for the reference aperture with true
   warps). Unlike ``caps-naive`` this resamples twice (SR output, then warp).

Options: ``model``, ``model_channels``, ``model_scale``, ``bayer_method``, ``clip``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import CapssimError, InputError

from ..networks import is_model_file, load_model, shipped_weights, unreadable_reason
from ..pipeline import coerce_option
from ..registry import MethodOutput, RunContext, register_method
from .caps_naive import NaiveOptions, bicubic_warp, demosaic_and_register, finish

REFERENCE = ("Optics Express 32(2) 2364 (2024), section 5.2: single-image SR (EDSR/SwinIR/HAT) after "
             "demosaicking; Lim et al., 'Enhanced deep residual networks for single image super-resolution', "
             "CVPRW 2017 (the shipped x2 EDSR, trained with capssim train)")
SHIPPED = "edsr-small"


def load_upsampler(path: str | None, device: torch.device, *, scale: float = 1.0):
    """A function ``(N, C, H, W) -> (N, C, 2H, 2W)``, its description and the channels it takes (None: any)."""
    if path == "bicubic":
        return (lambda x: F.interpolate(x, scale_factor=2, mode="bicubic", align_corners=False)), \
            "bicubic (no model)", None
    p = Path(path).expanduser() if path else shipped_weights(SHIPPED)
    if p.is_file() and p.suffix.lower() != ".onnx" and is_model_file(p):
        model, record = load_model(p, device=device, expect="edsr", option="model")
        channels = int(record["params"].get("channels", 3))
        return (lambda x: model(x * scale) / scale), f"capssim-model:{p.name} (edsr, {channels} channels)", channels
    if not p.is_file():
        raise InputError("model", str(path), "an existing TorchScript (.pt/.pth) or ONNX (.onnx) file")
    if p.suffix.lower() == ".onnx":
        try:
            import onnxruntime as ort
        except ImportError:
            raise CapssimError(f"model {p} is ONNX, which needs the optional package onnxruntime "
                               "(pip install onnxruntime), or export the model to TorchScript (.pt).") from None
        try:
            session = ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])
        except Exception as exc:  # a corrupt or truncated file: onnxruntime's message runs over lines
            raise InputError("model", str(path), "an ONNX model file",
                             f"onnxruntime cannot read it: {unreadable_reason(exc)}.") from None
        input_name = session.get_inputs()[0].name

        def run_onnx(x):
            y = session.run(None, {input_name: (x * scale).detach().cpu().numpy().astype(np.float32)})[0]
            return torch.from_numpy(np.asarray(y, dtype=np.float32)).to(x.device) / scale

        return run_onnx, f"onnx:{p.name} (onnxruntime CPU)", None
    try:
        module = torch.jit.load(str(p), map_location=device)
    except Exception as exc:  # corrupt file, not TorchScript
        raise InputError("model", str(path), "a TorchScript module saved with torch.jit.save, or an .onnx file",
                         f"torch.jit.load failed: {unreadable_reason(exc)}.") from None
    module.eval()
    return (lambda x: module(x * scale) / scale), f"torchscript:{p.name}", None


@register_method("caps-sisr", input_kind="caps", reference=REFERENCE,
                 description="Camera-array baseline: demosaic each aperture, x2 SR network (the shipped EDSR, or "
                             "model=PATH: capssim train / TorchScript / ONNX; model=bicubic), register")
def caps_sisr(capture, *, context: RunContext) -> MethodOutput:
    with context.timer.stage("setup"):  # option parsing
        opts, rest = NaiveOptions.from_options(context.options, extra=("model", "model_channels", "model_scale"))
    channels = coerce_option("model_channels", rest.get("model_channels", 1), int)
    if channels not in (1, 3):
        raise InputError("model_channels", channels, "1 (per channel) or 3 (RGB per aperture)")
    given_channels = "model_channels" in rest
    scale = coerce_option("model_scale", rest.get("model_scale", 1.0), float)
    if scale <= 0:
        raise InputError("model_scale", scale, "a number > 0")
    model_path = str(rest.get("model") or "").strip() or None
    with context.timer.stage("load_model"):
        upsample, upsampler, model_takes = load_upsampler(model_path, context.device, scale=scale)
    if model_takes is not None:
        if given_channels and channels != model_takes:
            raise InputError("model_channels", channels, f"{model_takes}, the channels of {upsampler}",
                             "Leave model_channels out with a capssim model file.")
        channels = model_takes
    rgb, geometry, reg_record = demosaic_and_register(capture, context, opts)
    n, c, h, w = rgb.shape
    with context.timer.stage("sisr"), torch.no_grad():
        x = rgb.reshape(n * c, 1, h, w) if channels == 1 else rgb
        y = upsample(x.contiguous())
        if not isinstance(y, torch.Tensor) or tuple(y.shape) != (x.shape[0], x.shape[1], 2 * h, 2 * w):
            raise CapssimError(f"SR model {upsampler} returned shape {tuple(getattr(y, 'shape', ()))} for input "
                               f"{tuple(x.shape)}; an x2 model must return {(x.shape[0], x.shape[1], 2 * h, 2 * w)}.")
        y = torch.nan_to_num(y.to(device=rgb.device, dtype=torch.float32)).reshape(n, c, 2 * h, 2 * w)
    with context.timer.stage("resample"):
        image = bicubic_warp(y, geometry.aperture_homographies, geometry.hr_shape)
    params = {"upsampler": upsampler, "model_channels": channels, "model_scale": scale,
              "resampling": "x2 SR on the aperture-HR grid, then bicubic (a=-0.75) warp by H_n, replicate border",
              "aperture_warps": geometry.aperture_homographies.tolist()}
    return finish(capture, image, opts, context, params, reg_record, extra={"upsampler": upsampler},
                  geometry=geometry)
