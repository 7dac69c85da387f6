"""Each aperture of the array demosaicked on its own and resampled onto the HR grid: the building blocks of
``caps-naive`` (paper section 5.2's camera-array baseline), of ``caps-plus``'s demosaicked start
(:mod:`capssim.reconstruct.pipeline.start`) and of the learned baselines' training pairs.

Bayer demosaicking: Menon, Andriani, Calvagno, "Demosaicing with directional filtering and a posteriori decision",
IEEE TIP 16(1) 2007 (:mod:`capssim.reconstruct.dofp.menon2007`, batched in torch: colour-demosaicing's result to the
bit), residual interpolation (Kiku et al. 2016, EARI's colour stage), or colour-demosaicing's Malvar 2004 and
bilinear methods.
Resampling: one bicubic ``grid_sample`` through each aperture's homography (HR reference -> aperture pixels).
Shapes: raw ``(4, H, W)`` (one RGGB frame per aperture), RGB ``(4, 3, H, W)``, channel ``c = 3 p + k`` after
resampling.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from capssim.conventions import flip_to_rggb
from capssim.errors import InputError, UnknownNameError

from ..dofp.menon2007 import menon2007_demosaic
from ..dofp.residual_interpolation import ri_bayer_demosaic_frames
from ..run_context import RunContext

__all__ = ["BAYER_METHODS", "BAYER_PAD", "bayer_demosaic_function", "bicubic_warp", "demosaic_apertures",
           "demosaicked_frames", "fill_held_out", "flat_corrected_raw", "ri_demosaic_frame", "sampling_grid"]

#: the selectable Bayer demosaicking algorithms: residual interpolation (``ri``, Kiku et al. 2016, the
#: colour stage of EARI [15]; :func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic`), Menon 2007
#: (:func:`capssim.reconstruct.dofp.menon2007.menon2007_demosaic`) and two of colour-demosaicing
BAYER_METHODS = ("ri", "menon2007", "malvar2004", "bilinear")


def ri_demosaic_frame(cfa: np.ndarray, pattern: str = "RGGB") -> np.ndarray:
    """``(H, W)`` RGGB frame -> ``(H, W, 3)`` RGB by residual interpolation (colour-demosaicing's signature):
    :func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic_frames`, ``dofp-eari``'s colour stage."""

    if pattern != "RGGB":
        raise InputError("pattern", pattern, "'RGGB' (the CAPS sensors' Bayer layout)")
    rgb = ri_bayer_demosaic_frames(torch.from_numpy(np.ascontiguousarray(cfa, dtype=np.float64)))
    return rgb.permute(1, 2, 0).numpy()


def _frame_by_frame(frame_function):
    """A colour-demosaicing-style function (one ``(H, W)`` RGGB frame -> ``(H, W, 3)``) applied to each of
    ``(N, H, W)`` frames -> ``(N, 3, H, W)``."""
    def demosaic(frames: np.ndarray) -> np.ndarray:
        return np.stack([np.moveaxis(np.asarray(frame_function(frame, "RGGB")), -1, 0) for frame in frames])
    return demosaic


def _menon2007(frames: np.ndarray) -> np.ndarray:
    """``(N, H, W)`` float64 RGGB frames -> ``(N, 3, H, W)``, all frames in one batch."""
    return menon2007_demosaic(torch.from_numpy(frames)).numpy()


def bayer_demosaic_function(name: str):
    """``(canonical name, function)`` of the Bayer demosaicking ``name`` (one of ``BAYER_METHODS``).

    The function takes ``(N, H, W)`` float64 RGGB frames and returns ``(N, 3, H, W)`` (each frame demosaicked on
    its own); an unknown name raises ``UnknownNameError`` listing the valid ones. Only ``malvar2004`` and
    ``bilinear`` import colour-demosaicing (and with it colour-science, about a second).
    """
    key = str(name).strip().lower().replace("-", "").replace("_", "")
    if key not in BAYER_METHODS:
        raise UnknownNameError("bayer_method", name, list(BAYER_METHODS))
    if key == "ri":
        return key, _frame_by_frame(ri_demosaic_frame)  # per frame: its clip level is each frame's own maximum
    if key == "menon2007":
        return key, _menon2007
    import colour_demosaicing as cd

    table = {"malvar2004": cd.demosaicing_CFA_Bayer_Malvar2004, "bilinear": cd.demosaicing_CFA_Bayer_bilinear}
    return key, _frame_by_frame(table[key])


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
    rgb = fn(padded)
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
    (:func:`fill_held_out`)."""
    raw, clip_max = flat_corrected_raw(capture, context)  # gain and vignetting divided out (calibrated)
    if held_out is not None:
        raw = fill_held_out(raw, held_out)
    rgb = demosaic_apertures(raw, bayer_method=bayer_method, clip_max=clip_max, cfa=capture.cfa)
    return torch.from_numpy(rgb).to(context.device)


def fill_held_out(raw: np.ndarray, held_out: np.ndarray) -> np.ndarray:
    """``raw`` ``(4, H, W)`` with each held-out pixel replaced by the mean of its unheld same-colour neighbours
    (the 8 raw pixels two rows or columns away, the Bayer period); the plane's mean of unheld pixels where
    all 8 are held out. Used for the demosaicked start, which must not see the held-out values
    (:mod:`capssim.reconstruct.selection.holdout`)."""
    raw = np.asarray(raw, dtype=np.float32)
    held = np.asarray(held_out, dtype=bool)
    if not held.any():
        return raw
    keep = torch.from_numpy((~held).astype(np.float32))[:, None]
    values = torch.from_numpy(raw)[:, None] * keep
    kernel = torch.zeros(1, 1, 5, 5)
    kernel[0, 0, ::2, ::2] = 1.0
    kernel[0, 0, 2, 2] = 0.0
    total = F.conv2d(values, kernel, padding=2)[:, 0]
    count = F.conv2d(keep, kernel, padding=2)[:, 0]
    plane_mean = (values.sum(dim=(1, 2, 3)) / keep.sum(dim=(1, 2, 3)).clamp_min(1.0))[:, None, None]
    filled = torch.where(count > 0, total / count.clamp_min(1.0), plane_mean.expand_as(total))
    out = raw.copy()
    out[held] = filled.numpy()[held]
    return out
