"""``caps-naive``: the plain camera-array pipeline (the paper's non-joint baseline, section 5.2).

Reference: the "demosaic, register, upsample" camera-array baseline of "Joint constraints of
guided filtering based confidence and nonlocal sparse tensor for color polarization
super-resolution imaging", Optics Express 32(2), 2364 (2024), section 5.2, with the Bayer
demosaicking of Menon, Andriani, Calvagno, "Demosaicing with directional filtering and a
posteriori decision", IEEE TIP 16(1), 2007 (:mod:`capssim.reconstruct.dofp.menon2007`, colour-demosaicing's
result to the bit).

1. Demosaick each aperture's RGGB raw frame ``(H, W)`` on its own (``bayer_method``:
   ``menon2007`` (default, capssim's torch port), ``malvar2004`` or ``bilinear`` (from ``colour-demosaicing``), or
   ``ri``, the residual interpolation of :func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic`),
   clipped to [0, 1] -> ``(4, 3, H, W)``; each frame is mirror-padded by 6 pixels with its
   Bayer phase kept (:func:`demosaic_apertures`), so constant images stay exact at the border.
2. Registration: the array geometry of the CAPS method
   (:func:`capssim.reconstruct.model.observation_model.method_geometry`: estimated by
   :mod:`capssim.reconstruct.registration`, or the stored one under ``--true-warps``), whose
   aperture warps ``H_n`` map the HR reference to each aperture-HR grid.
3. One bicubic resampling per aperture onto the HR reference grid ``(2H, 2W)``: HR pixel
   ``(x, y)`` samples the demosaicked frame at raw coordinates ``R H_n (x, y, 1)``, where
   ``R = capssim.camera.array_geometry.raw_matrix()`` (aperture-HR -> raw pixel), i.e. the x2 upsampling
   and the registration warp composed into one map (torch ``grid_sample``, bicubic with
   ``a = -0.75``, replicate border; the same kernel as ``F.interpolate(mode='bicubic')``).
   Pixels of the reference grid outside an aperture's field of view get its border values.
   The result is clipped to [0, 1] (``clip=false`` keeps the bicubic overshoot).

With a calibration (``--calibration``, :mod:`capssim.reconstruct.model.observation_model`): each aperture's
raw frame is divided by its flat field ``gain_n V_n`` before step 1 (:func:`flat_corrected_raw`), step 2
takes the calibration's geometry when it has one, and after step 3 the 12 registered images are
``y = A x`` per pixel with ``A`` the calibrated analyzer (row ``3n + k``: aperture n's polarizer in
colour k; one 4x4 block per colour): ``x = A^-1 y`` per pixel, the exact inverse of the mixing
(:func:`~capssim.reconstruct.model.observation_model.unmix_analyzer`), before clipping.

Output ``(12, 2H, 2W)`` float32, channel ``c = 3 p + k`` (aperture/polarizer p, colour k).
Saturated pixels are used as they are (no masking): this is the naive pipeline.

Options (``-p KEY=VALUE``): ``bayer_method``, ``clip``. Options of ``caps`` (e.g. ``iterations``
from ``capssim reconstruct -m all --iterations N``) are ignored with a warning; others are errors.

:func:`caps_sisr` in :mod:`capssim.reconstruct.methods.caps_sisr` replaces step 3's upsampling by a
user-supplied x2 single-image SR model and reuses steps 1-2 from here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import UnknownNameError

from ..model.aperture_demosaic import (  # noqa: F401  (public names of this method's building blocks)
    BAYER_METHODS,
    bayer_demosaic_function,
    bicubic_warp,
    demosaic_apertures,
    demosaicked_frames,
    flat_corrected_raw,
    sampling_grid,
)
from ..model.observation_model import calibrated_analyzer, method_geometry, unmix_analyzer
from ..pipeline import caps_option_names, coerce_option, mean_psnr
from ..registry import MethodOutput, RunContext, register_method
from .caps import REFERENCE as CAPS_REFERENCE

log = logging.getLogger(__name__)

REFERENCE = (CAPS_REFERENCE + " (camera-array baseline, 5.2); Bayer demosaicking: Menon, Andriani, Calvagno, "
             "IEEE TIP 16(1) 2007")

@dataclass
class NaiveOptions:
    bayer_method: str = "menon2007"
    clip: bool = True

    @classmethod
    def from_options(cls, options: dict, extra: tuple = ()) -> tuple["NaiveOptions", dict]:
        """Parse the options of this class; return it and the leftover options named in ``extra``."""
        known = {f.name for f in fields(cls)}
        values, rest = {}, {}
        for key, raw in (options or {}).items():
            name = str(key).replace("-", "_")
            if name in known:
                values[name] = coerce_option(name, raw, type(getattr(cls, name)))
            elif name in extra:
                rest[name] = raw
            elif name in caps_option_names():  # e.g. --iterations with -m all: meaningless here
                log.warning("option %s is a caps option; ignored by this method", key)
            else:
                raise UnknownNameError("option", key, sorted(known | set(extra)))
        opts = cls(**values)
        opts.bayer_method = bayer_demosaic_function(opts.bayer_method)[0]
        return opts, rest


def demosaic_and_register(capture, context: RunContext, opts: NaiveOptions):
    """Steps 1-2: ``(4, 3, H, W)`` demosaicked frames (tensor on the context device), the array
    geometry (true or registered) and the registration record."""
    timer = context.timer
    with timer.stage("demosaic"):
        rgb = demosaicked_frames(capture, context, opts.bayer_method)
    with timer.stage("registration"):
        lr_images, lr_saturated = capture.lr_images()
        geometry, reg_record = method_geometry(capture, context, images=lr_images, saturated=lr_saturated)
    return rgb, geometry, reg_record


def unobserved_pixels(saturated: np.ndarray, geometry, device: torch.device) -> np.ndarray:
    """``(12, 2H, 2W)`` bool: HR pixels whose source in their aperture's raw frame is out of view or within
    one raw pixel of a saturated pixel (``saturated`` ``(4, H, W)``), for channel ``c = 3 n + k``."""
    from scipy.ndimage import maximum_filter

    usable = np.stack([maximum_filter(s.astype(np.uint8), size=3) == 0 for s in np.asarray(saturated)])
    usable_t = torch.from_numpy(usable.astype(np.float32))[:, None].to(device)
    grid = sampling_grid(geometry.raw_homographies, geometry.hr_shape, tuple(usable.shape[-2:]), device)
    seen = F.grid_sample(usable_t, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[:, 0]
    return np.repeat((seen < 0.5).cpu().numpy(), 3, axis=0)


def finish(capture, image: torch.Tensor, opts: NaiveOptions, context: RunContext, params: dict,
           reg_record: dict, extra: dict | None = None, geometry=None) -> MethodOutput:
    """Clip, flatten to 12 channels ``c = 3 p + k``, copy to the host, record (with the
    :func:`unobserved_pixels` of ``geometry`` when given)."""
    with context.timer.stage("to_host"):
        image = image.reshape(12, *image.shape[-2:])
        analyzer = calibrated_analyzer(context)
        if analyzer is not None:  # registered aperture images y = A x per pixel: x = A^-1 y, exactly
            image = unmix_analyzer(image, analyzer)
        if opts.clip:
            image = image.clamp(0.0, 1.0)
        out = {"registration": reg_record, **(extra or {})}
        psnr = mean_psnr(capture, image)
        if psnr is not None:
            out["psnr_db"] = psnr
        host = image.to("cpu", torch.float32).numpy()
    params = {"bayer_method": opts.bayer_method, "clip": opts.clip, **params}
    unobserved = None if geometry is None else (
        lambda: unobserved_pixels(capture.caps_saturated(), geometry, context.device))
    return MethodOutput(image=host, params=params, extra=out, unobserved=unobserved)


@register_method("caps-naive", input_kind="caps", reference=REFERENCE,
                 description="Camera-array baseline: Menon 2007 demosaicking per aperture, CAPS registration, "
                             "bicubic x2 resampling onto the reference grid (one resampling per aperture)")
def caps_naive(capture, *, context: RunContext) -> MethodOutput:
    with context.timer.stage("setup"):  # option parsing
        opts, _ = NaiveOptions.from_options(context.options)
    rgb, geometry, reg_record = demosaic_and_register(capture, context, opts)
    with context.timer.stage("resample"):
        image = bicubic_warp(rgb, geometry.raw_homographies, geometry.hr_shape)  # (4, 3, 2H, 2W)
    params = {"resampling": "bicubic (a=-0.75), x2 upsampling and registration warp composed, replicate border",
              "aperture_warps": geometry.aperture_homographies.tolist()}
    return finish(capture, image, opts, context, params, reg_record, geometry=geometry)
