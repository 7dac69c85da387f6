"""``caps-naive``: the plain camera-array pipeline (the paper's non-joint baseline, section 5.2).

Reference: the "demosaic, register, upsample" camera-array baseline of "Joint constraints of
guided filtering based confidence and nonlocal sparse tensor for color polarization
super-resolution imaging", Optics Express 32(2), 2364 (2024), section 5.2, with the Bayer
demosaicking of Menon, Andriani, Calvagno, "Demosaicing with directional filtering and a
posteriori decision", IEEE TIP 16(1), 2007 (``colour-demosaicing``).

1. Demosaick each aperture's RGGB raw frame ``(H, W)`` on its own (``bayer_method``:
   ``menon2007`` (default), ``malvar2004`` or ``bilinear``, from ``colour-demosaicing``, or
   ``ri``, the residual interpolation of :func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic`),
   clipped to [0, 1] -> ``(4, 3, H, W)``; each frame is mirror-padded by 6 pixels with its
   Bayer phase kept (:func:`demosaic_apertures`), so constant images stay exact at the border.
2. Registration: the array geometry of the CAPS method
   (:func:`capssim.reconstruct.model.observation_model.method_geometry`: estimated by
   :mod:`capssim.reconstruct.registration`, or the stored one under ``--true-warps``), whose
   aperture warps ``H_n`` map the HR reference to each aperture-HR grid.
3. One bicubic resampling per aperture onto the HR reference grid ``(2H, 2W)``: HR pixel
   ``(x, y)`` samples the demosaicked frame at raw coordinates ``R H_n (x, y, 1)``, where
   ``R = capssim.array_geometry.raw_matrix()`` (aperture-HR -> raw pixel), i.e. the x2 upsampling
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

from capssim.conventions import flip_to_rggb
from capssim.errors import InputError, UnknownNameError

from ..dofp.residual_interpolation import ri_bayer_demosaic_frames
from ..model.holdout import fill_held_out
from ..model.observation_model import calibrated_analyzer, method_geometry, unmix_analyzer
from ..pipeline import caps_option_names, coerce_option, mean_psnr
from ..registry import MethodOutput, RunContext, register_method
from .caps import REFERENCE as CAPS_REFERENCE

log = logging.getLogger(__name__)

REFERENCE = (CAPS_REFERENCE + " (camera-array baseline, 5.2); Bayer demosaicking: Menon, Andriani, Calvagno, "
             "IEEE TIP 16(1) 2007 (colour-demosaicing)")

#: the selectable Bayer demosaicking algorithms: residual interpolation (``ri``, Kiku et al. 2016, the
#: colour stage of EARI [15]; :func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic`) and three of colour-demosaicing
BAYER_METHODS = ("ri", "menon2007", "malvar2004", "bilinear")


def ri_demosaic_frame(cfa: np.ndarray, pattern: str = "RGGB") -> np.ndarray:
    """``(H, W)`` RGGB frame -> ``(H, W, 3)`` RGB by residual interpolation (colour-demosaicing's signature):
    :func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic_frames`, ``dofp-eari``'s colour stage."""

    if pattern != "RGGB":
        raise InputError("pattern", pattern, "'RGGB' (the CAPS sensors' Bayer layout)")
    rgb = ri_bayer_demosaic_frames(torch.from_numpy(np.ascontiguousarray(cfa, dtype=np.float64)))
    return rgb.permute(1, 2, 0).numpy()


def bayer_demosaic_function(name: str):
    """``(canonical name, function)`` of the Bayer demosaicking ``name`` (one of ``BAYER_METHODS``).

    The function takes an ``(H, W)`` RGGB mosaic and returns ``(H, W, 3)``; an unknown name
    raises ``UnknownNameError`` listing the valid ones.
    """
    import colour_demosaicing as cd

    key = str(name).strip().lower().replace("-", "").replace("_", "")
    table = {"ri": ri_demosaic_frame, "menon2007": cd.demosaicing_CFA_Bayer_Menon2007,
             "malvar2004": cd.demosaicing_CFA_Bayer_Malvar2004, "bilinear": cd.demosaicing_CFA_Bayer_bilinear}
    if key not in table:
        raise UnknownNameError("bayer_method", name, list(BAYER_METHODS))
    return key, table[key]


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


#: mirror padding (raw pixels, even) around each frame before demosaicking
BAYER_PAD = 6


def demosaic_apertures(raw: np.ndarray, *, bayer_method: str = "menon2007", clip_max: float = 1.0,
                       cfa: str = "RGGB") -> np.ndarray:
    """``(4, H, W)`` Bayer raw frames on [0, 1] -> ``(4, 3, H, W)`` float32 RGB, clipped to [0, ``clip_max``]
    (above 1 for flat-field-corrected frames, :func:`flat_corrected_raw`).

    A ``cfa`` other than RGGB is read by reversing rows and/or columns (:func:`capssim.conventions.flip_to_rggb`,
    exact for even H, W), demosaicking as RGGB and reversing the result back.

    Each frame is mirror-padded by :data:`BAYER_PAD` pixels (``np.pad`` ``reflect``, an even
    width, so every padded pixel keeps its Bayer colour) and cropped back after demosaicking:
    colour-demosaicing's own ``scipy.ndimage`` border handling mixes colour planes at the
    image border (its bilinear method is off by up to 0.6 on a constant 0.5 there).
    """
    key, fn = bayer_demosaic_function(bayer_method)
    raw = np.asarray(raw)
    if raw.ndim != 3 or raw.shape[1] < 2 or raw.shape[2] < 2:
        raise InputError("raw", f"shape {raw.shape}", "(N, H, W) RGGB frames with H, W >= 2")
    raw = flip_to_rggb(raw, cfa)  # the identity for RGGB
    # even: keeps the RGGB phase; ``ri`` mirror-pads by itself (any frame size)
    pad = 0 if key == "ri" else min(BAYER_PAD, raw.shape[1] - 1, raw.shape[2] - 1) // 2 * 2
    padded = np.pad(raw.astype(np.float64), ((0, 0), (pad, pad), (pad, pad)), mode="reflect")
    rgb = np.stack([np.moveaxis(np.asarray(fn(padded[n], "RGGB")), -1, 0) for n in range(raw.shape[0])])
    rgb = rgb[..., pad:pad + raw.shape[1], pad:pad + raw.shape[2]]
    return flip_to_rggb(np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, clip_max).astype(np.float32), cfa)


def flat_corrected_raw(capture, context: RunContext) -> tuple[np.ndarray, float]:
    """``(4, H, W)`` raw frames divided by the calibrated flat field ``gain_n V_n`` (unchanged without
    one) and the largest value they can hold (``1 / min(flat)``: full scale seen through the darkest
    corner), the clip level of their demosaicking."""
    raw = capture.caps_float()
    calibration = context.calibration
    if calibration is None or not calibration.rig.has_flat_field:
        return raw, 1.0
    flat = calibration.rig.flat_field(capture.raw_shape)
    return (raw / flat).astype(np.float32), float(max(1.0, 1.0 / flat.min()))


def sampling_grid(homographies: np.ndarray, out_hw: tuple[int, int], in_hw: tuple[int, int],
                  device: torch.device) -> torch.Tensor:
    """``grid_sample`` grid ``(B, Hout, Wout, 2)``: output pixel ``(x, y)`` reads input ``h (x, y, 1)``.

    ``homographies`` ``(B, 3, 3)`` map output pixel -> input pixel coordinates (x=col, y=row,
    pixel centres on integers); normalized for ``align_corners=True``.
    """
    hout, wout = out_hw
    hin, win = in_hw
    h = torch.as_tensor(np.asarray(homographies), dtype=torch.float64, device=device)
    ys, xs = torch.meshgrid(torch.arange(hout, dtype=torch.float64, device=device),
                            torch.arange(wout, dtype=torch.float64, device=device), indexing="ij")
    pts = torch.stack([xs, ys, torch.ones_like(xs)], dim=-1)  # (Hout, Wout, 3)
    src = torch.einsum("bij,hwj->bhwi", h, pts)
    sx, sy = src[..., 0] / src[..., 2], src[..., 1] / src[..., 2]
    gx = 2 * sx / max(win - 1, 1) - 1
    gy = 2 * sy / max(hin - 1, 1) - 1
    return torch.stack([gx, gy], dim=-1).to(torch.float32)


def bicubic_warp(images: torch.Tensor, homographies: np.ndarray, out_hw: tuple[int, int]) -> torch.Tensor:
    """``(B, C, Hin, Win)`` -> ``(B, C, Hout, Wout)``: bicubic samples at ``h_b (x, y, 1)``, replicate border."""
    grid = sampling_grid(homographies, out_hw, tuple(images.shape[-2:]), images.device)
    return F.grid_sample(images, grid, mode="bicubic", padding_mode="border", align_corners=True)


def demosaicked_frames(capture, context: RunContext, bayer_method: str, *, held_out=None) -> torch.Tensor:
    """Step 1: ``(4, 3, H, W)`` float32 on the context device, each aperture's raw frame (flat field divided
    out with a calibration, :func:`flat_corrected_raw`) demosaicked on its own (:func:`demosaic_apertures`).
    ``held_out`` ``(4, H, W)`` bool (optional): raw pixels replaced by their same-colour neighbours first
    (:func:`~capssim.reconstruct.model.holdout.fill_held_out`)."""
    raw, clip_max = flat_corrected_raw(capture, context)  # gain and vignetting divided out (calibrated)
    if held_out is not None:
        raw = fill_held_out(raw, held_out)
    rgb = demosaic_apertures(raw, bayer_method=bayer_method, clip_max=clip_max, cfa=capture.cfa)
    return torch.from_numpy(rgb).to(context.device)


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
    with context.timer.stage("setup"):  # option parsing; the first call imports colour-demosaicing (~1 s)
        opts, _ = NaiveOptions.from_options(context.options)
    rgb, geometry, reg_record = demosaic_and_register(capture, context, opts)
    with context.timer.stage("resample"):
        image = bicubic_warp(rgb, geometry.raw_homographies, geometry.hr_shape)  # (4, 3, 2H, 2W)
    params = {"resampling": "bicubic (a=-0.75), x2 upsampling and registration warp composed, replicate border",
              "aperture_warps": geometry.aperture_homographies.tolist()}
    return finish(capture, image, opts, context, params, reg_record, geometry=geometry)
