"""``array-kr``: a fast, non-iterative camera-array reconstruction by kernel regression of the raw samples.

Reference: B. Wronski et al., "Handheld multi-frame super-resolution", ACM TOG 38(4) (SIGGRAPH 2019): the raw
Bayer samples of a burst merged straight onto the output grid by anisotropic kernel regression steered by the
local structure tensor. Here the burst is the array's four apertures, with known polarizers.

**The default (``samples=demosaicked``).** Each aperture demosaicked (Menon 2007) and registered by one bicubic
warp, as in ``caps-naive``; the mean of the four is the intensity (sharpened where its detail leads) and each
analyzer keeps its smooth polarization and, where the intensity does not explain it, its own detail
(:mod:`capssim.reconstruct.kernel_regression.fusion`). Its noise std is the capture's Gaussian sensor sigma when
the set-up states one, else a robust estimate. On the ``dev`` suite it beats ``samples=raw``, described next, by
2 dB (docs/guides/methods.md).

**The raw model (``samples=raw``).** Every raw sample ``v`` of aperture ``n`` (polarizer ``45 n`` deg) measures
``I_n = (S0 + S1 cos 2a_n + S2 sin 2a_n) / 2`` of its colour at a known sub-pixel position of the HR grid (the
project's registration, reused when stored: :func:`~capssim.reconstruct.model.observation_model.method_geometry`,
or the true warps under ``--true-warps``; each sample's HR position is the inverse of the map
``raw_matrix() @ H_n``). Since ``I_0 + I_90 = I_45 + I_135 = S0``, the four apertures together sample the
intensity ``S0`` at four sub-pixel phases: ``2 v`` of all of them is merged onto the 2x grid by kernel regression
(green first, with Gaussian kernels steered by the structure tensor of the merged green, then red and blue as
colour differences to green), and each analyzer's image is the merged intensity times the ratio of that
aperture's own samples to it, ``I_n = S0 / 2 * KR_n(v / (S0(q) / 2))``, merged over that aperture alone, so that
structure only in the polarization is not smeared by the other apertures
(:mod:`capssim.reconstruct.kernel_regression.merge`). The kernels widen where the merged intensity is flat at
the noise level (Immerkaer's noise estimate of the sub-images). No iteration: five gather passes of batched
torch over chunks of HR rows, the same code on CUDA (the run context's device).

Weights: saturated raw samples get weight 0 (they decide only where no unsaturated sample is in reach) and
samples outside an aperture's frame weight 0. Not Wronski's: no per-sample robustness weight from a
registration residual (the array's warps are global; a residual test would also reject strongly polarized
samples, which differ from ``S0 / 2`` by design). With a calibration (``--calibration``) the raw frames are
divided by the flat field first and the result is unmixed by the calibrated analyzer, as in ``caps-naive``.

Options (``-p KEY=VALUE``, ``capssim reconstruct --options array-kr``): ``samples``, ``detail``, ``sharpen``;
for ``samples=raw`` ``scale`` (kernel size), ``steer``, ``polarization`` (``ratio`` or ``difference``); ``clip``. Output ``(12, 2H, 2W)`` float32, channel ``c = 3 p + k``.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from capssim.conventions import CFA_PATTERNS, cfa_pattern
from capssim.errors import InputError

from ..kernel_regression.fusion import demosaicked_fusion, unseen_pixels
from ..kernel_regression.gather import SampleField
from ..kernel_regression.merge import POLARIZATION_MODES, merge_apertures
from ..kernel_regression.steering import noise_sigma
from ..model.aperture_demosaic import flat_corrected_raw
from ..model.observation_model import calibrated_analyzer, method_geometry, unmix_analyzer
from ..pipeline import caps_option_names, coerce_option, mean_psnr
from ..pipeline.option_table import MethodOption, check_option_names
from ..registry import MethodOutput, RunContext, register_method
from .caps_naive import unobserved_pixels

__all__ = ["ARRAY_KR_OPTIONS", "TUNED_ON", "array_kr", "array_kr_options", "parse_options", "raw_noise_sigma",
           "reconstruct_raw"]

log = logging.getLogger(__name__)

REFERENCE = ("Wronski et al., 'Handheld multi-frame super-resolution', ACM TOG 38(4) (SIGGRAPH 2019): kernel "
             "regression of raw Bayer samples with structure-tensor steered kernels; capssim's polarization step")
#: the suite the constants of :mod:`capssim.reconstruct.kernel_regression` were chosen on
TUNED_ON = ("dev",)
#: name -> (default, valid, meaning)
ARRAY_KR_OPTIONS = {
    "samples": ("demosaicked", "demosaicked or raw", "demosaicked: each aperture demosaicked and registered, the four "
                "fused (intensity) with each analyzer's own detail; raw: the raw Bayer samples merged by steered kernel "
                "regression"),
    "detail": (True, "true or false", "demosaicked: keep each analyzer's detail where the intensity does not explain "
               "it (false: smooth polarization only)"),
    "sharpen": (0.5, "number in [0, 2]", "demosaicked: unsharp-mask gain of the fused intensity"),
    "scale": (1.0, "number in [0.25, 4]", "multiplies every kernel std (larger: smoother, less noise)"),
    "steer": (True, "true or false", "steer the kernels by the structure tensor (false: isotropic)"),
    "polarization": ("ratio", "ratio or difference", "each analyzer's own samples against the merged intensity: "
                     "their ratio or their difference is merged"),
    "clip": (True, "true or false", "clip the result to [0, 1]"),
}


def array_kr_options() -> list[MethodOption]:
    """Every ``-p`` option of ``array-kr``, one line each."""
    return [MethodOption(name, default, valid, meaning) for name, (default, valid, meaning) in ARRAY_KR_OPTIONS.items()]


def parse_options(options: dict) -> dict:
    """The options as values (defaults filled in); an unknown name or a value out of range is refused. An option
    of ``caps`` (e.g. ``iterations`` from ``capssim reconstruct -m all --iterations N``) is ignored with a warning,
    as ``caps-naive`` does."""
    own = {o.name for o in array_kr_options()}
    options = dict(options or {})
    for key in [k for k in options if str(k).replace("-", "_") not in own
                and str(k).replace("-", "_") in caps_option_names()]:
        log.warning("option %s is a caps option; ignored by array-kr", key)
        options.pop(key)
    check_option_names("array-kr", options, array_kr_options())
    values = {name: spec[0] for name, spec in ARRAY_KR_OPTIONS.items()}
    for key, raw in options.items():
        name = str(key).replace("-", "_")
        values[name] = coerce_option(name, raw, type(ARRAY_KR_OPTIONS[name][0]))
    if not 0.0 <= values["sharpen"] <= 2.0:
        raise InputError("option sharpen", values["sharpen"], ARRAY_KR_OPTIONS["sharpen"][1], "e.g. -p sharpen=0.5")
    if str(values["samples"]).strip().lower() not in ("demosaicked", "raw"):
        raise InputError("option samples", repr(values["samples"]), "demosaicked or raw", "e.g. -p samples=raw")
    values["samples"] = str(values["samples"]).strip().lower()
    if not 0.25 <= values["scale"] <= 4.0:
        raise InputError("option scale", values["scale"], ARRAY_KR_OPTIONS["scale"][1], "e.g. -p scale=1.0")
    mode = str(values["polarization"]).strip().lower()
    if mode not in POLARIZATION_MODES:
        raise InputError("option polarization", repr(values["polarization"]), " or ".join(POLARIZATION_MODES),
                         "e.g. -p polarization=ratio")
    values["polarization"] = mode
    return values


def raw_noise_sigma(raw: torch.Tensor) -> float:
    """Immerkaer's noise estimate of the frames' ``(4, H, W)`` Bayer sub-images (0 for frames under 2x2)."""
    h2, w2 = raw.shape[1] // 2 * 2, raw.shape[2] // 2 * 2
    if min(h2, w2) < 2:
        return 0.0
    subs = raw[:, :h2, :w2].reshape(4, h2 // 2, 2, w2 // 2, 2).permute(0, 2, 4, 1, 3)
    return noise_sigma(subs.reshape(16, h2 // 2, w2 // 2))


def reconstruct_raw(raw, saturated, raw_homographies, hr_shape, *, cfa: str = "RGGB", device="cpu",
                    scale: float = 1.0, steer: bool = True, polarization: str = "ratio",
                    sigma_n: float | None = None) -> tuple[torch.Tensor, dict]:
    """The merge of raw frames ``(4, H, W)`` (any ``H, W >= 1``) with saturation masks ``(4, H, W)`` and the
    HR -> raw maps ``(4, 3, 3)``: ``(4, 3, Ho, Wo)`` on ``device`` and the merge's record
    (:func:`~capssim.reconstruct.kernel_regression.merge.merge_apertures`). ``sigma_n``: the raw noise std
    (default: Immerkaer's estimate of the frames' Bayer sub-images)."""
    raw_t = torch.as_tensor(np.asarray(raw, dtype=np.float32), device=device)
    sat = np.asarray(saturated, dtype=bool)
    if raw_t.ndim != 3 or raw_t.shape[0] != 4 or sat.shape != tuple(raw_t.shape):
        raise InputError("raw", f"shape {tuple(raw_t.shape)} with saturated {sat.shape}",
                         "(4, H, W) frames and a saturation mask of the same shape")
    hr_shape = (int(hr_shape[0]), int(hr_shape[1]))
    if min(hr_shape) < 2:
        raise InputError("hr_shape", hr_shape, "an HR grid of at least 2x2 pixels")
    field = SampleField.build(raw_t, torch.as_tensor(~sat, device=device), raw_homographies,
                              CFA_PATTERNS[cfa_pattern(cfa)])
    if sigma_n is None:
        sigma_n = raw_noise_sigma(raw_t)
    image, record = merge_apertures(field, hr_shape, sigma_n, scale=scale, steer=steer, polarization=polarization)
    record["noise_sigma"] = float(sigma_n)
    return image, record


@register_method("array-kr", input_kind="caps", reference=REFERENCE, tuned_on=TUNED_ON, options=array_kr_options,
                 registration="fast",
                 description="Fast camera-array method, no iterations: the apertures demosaicked and registered as "
                             "caps-naive, their mean as the intensity, each analyzer's own detail where the intensity "
                             "does not explain it (samples=raw: steered kernel regression of the raw samples)")
def array_kr(capture, *, context: RunContext) -> MethodOutput:
    timer = context.timer
    with timer.stage("setup"):
        opts = parse_options(context.options)
        raw, _ = flat_corrected_raw(capture, context)  # gain and vignetting divided out (calibrated)
        saturated = capture.caps_saturated()
    with timer.stage("registration"):
        lr_images, lr_saturated = capture.lr_images()
        geometry, reg_record = method_geometry(capture, context, images=lr_images, saturated=lr_saturated)
    usable = torch.as_tensor(~np.asarray(saturated, bool), device=context.device)
    if opts["samples"] == "raw":
        with timer.stage("merge"):
            image, record = reconstruct_raw(raw, saturated, geometry.raw_homographies, geometry.hr_shape,
                                            cfa=capture.cfa, device=context.device, scale=opts["scale"],
                                            steer=opts["steer"], polarization=opts["polarization"])
    else:
        with timer.stage("merge"):  # the apertures demosaicked and fused
            image, sigma_n = demosaicked_fusion(capture, context, geometry, detail=opts["detail"],
                                                sharpen=opts["sharpen"])
            record = {"noise_sigma": sigma_n}
    with timer.stage("to_host"):
        image = image.reshape(12, *image.shape[-2:])
        analyzer = calibrated_analyzer(context)
        if analyzer is not None:  # y = A x per pixel: x = A^-1 y, as caps-naive
            image = unmix_analyzer(image, analyzer)
        if opts["clip"]:
            image = image.clamp(0.0, 1.0)
        extra = {"registration": reg_record, "noise_sigma": record["noise_sigma"]}
        psnr = mean_psnr(capture, image)
        if psnr is not None:
            extra["psnr_db"] = psnr
        host = image.to("cpu", torch.float32).numpy()
    params = {**opts, "aperture_warps": geometry.aperture_homographies.tolist()}
    return MethodOutput(image=host, params=params, extra=extra,
                        unobserved=lambda: unobserved_pixels(saturated, geometry, context.device)
                        if opts["samples"] == "raw" else unseen_pixels(usable, geometry.raw_homographies, geometry.hr_shape))
