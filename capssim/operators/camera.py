"""The one observation model of CAPS and of the DoFP camera (paper eq. 9-11).

Simulation, rendering post-processing and every reconstruction build their operators
here, so a bug cannot hide behind a matching bug elsewhere.

CAPS raw frames (eq. 9), for the 12-channel HR image ``x`` of shape ``(12, 2H, 2W)``::

    raw = Bayer( IntegrateDecimate_2( Blur_psf( Warp_{H_n}( Analyzer(x) ) ) ) )   -> (4, H, W)

Low-resolution image m = 4n + q (eq. 11, ``M_m``), for its channel's HR image::

    y_m = Decimate_2^{(oy_q, ox_q)}( IntegrateDecimate_2( Blur_psf( Warp_{H_n}(x_c(m)) ) ) )  -> (h, w)

with ``h = H/2`` and ``n = m // 4``: its pixels land where the sub-image homography
``H_m = S_q @ H_n`` of :class:`capssim.camera.array_geometry.ArrayGeometry` says, so ``BayerSplit(raw)``
equals the 16 ``y_m`` exactly (a test pins this).

DoFP raw frame (same total pixel count ``4HW``, pixel pitch = HR pitch)::

    dofp = DoFPMosaic_layout( Analyzer_ER( Blur_psf(x) ) )                          -> (2H, 2W)
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.rig import RigModel
from capssim.conventions import (
    BAYER_OFFSETS,
    DEFAULT_DOFP_LAYOUT,
    LR_IMAGE_CHANNELS,
    N_APERTURES,
    N_CHANNELS,
    N_LR_IMAGES,
    POLARIZER_ANGLES_DEG,
)
from capssim.errors import InputError
from capssim.operators.analyzer import Analyzer, ChannelMix, analyzer_matrix
from capssim.operators.base import Composition, Multiply, Reshape
from capssim.operators.blur import Convolve
from capssim.operators.blur_sample import BlurIntegrateDecimate
from capssim.operators.cfa import BayerMosaic, DoFPMosaic
from capssim.operators.sampling import IntegrateDecimate
from capssim.operators.warp import Warp


def _check_hr_shape(hr_shape) -> tuple[int, int]:
    hh, ww = (int(v) for v in hr_shape)
    if hh < 8 or ww < 8 or hh % 4 or ww % 4:
        raise InputError("hr_shape", (hh, ww), "height and width >= 8 and divisible by 4",
                         "Crop the ground truth to a multiple of 4 (e.g. --crop).")
    return hh, ww


def caps_raw_operator(hr_shape, aperture_homographies, psf_kernel, *,
                      angles_deg: Sequence[int] = POLARIZER_ANGLES_DEG,
                      extinction_ratio: float | None = None, rig: RigModel | None = None) -> Composition:
    """``(12, 2H, 2W) -> (4, H, W)``: the four RGGB raw frames of the camera array (eq. 9).

    ``aperture_homographies`` ``(4, 3, 3)`` map HR reference -> aperture-HR coordinates.
    ``rig`` (:class:`capssim.camera.rig.RigModel`, imperfect arrays): its analyzer per aperture and
    colour replaces the ideal one (and ``extinction_ratio``), its per-aperture PSFs replace
    ``psf_kernel``, and its flat field (gain x vignetting) multiplies the raw frames.
    """
    hh, ww = _check_hr_shape(hr_shape)
    h = np.asarray(aperture_homographies, dtype=np.float64)
    n = len(angles_deg)
    if h.shape != (n, 3, 3):
        raise InputError("aperture_homographies", f"shape {h.shape}", f"shape ({n}, 3, 3)")
    if rig is None or rig.is_ideal:
        analyzer = Analyzer(hh, ww, angles_deg=angles_deg, extinction_ratio=extinction_ratio)
    else:
        if tuple(angles_deg) != tuple(POLARIZER_ANGLES_DEG):
            raise InputError("angles_deg", tuple(angles_deg), f"{POLARIZER_ANGLES_DEG} with a rig")
        analyzer = ChannelMix(rig.analyzer_matrix(), hh, ww, out_lead=(n, 3))
    kernels = rig.psf_kernels() if rig is not None else None
    ops = [
        analyzer,
        Warp(h, 3, (hh, ww)),
        Convolve(psf_kernel if kernels is None else kernels, (n, 3, hh, ww)),
        IntegrateDecimate(2, (n, 3, hh, ww)),
        BayerMosaic((n, 3, hh // 2, ww // 2)),
    ]
    if rig is not None and rig.has_flat_field:
        ops.append(Multiply(rig.flat_field((hh // 2, ww // 2))))
    return Composition(ops, name="caps_raw")


def lr_sampling_operator(geometry: ArrayGeometry, psf_kernel, *, psf_kernels=None, flat=None) -> Composition:
    """``M``: ``(16, 2H, 2W) -> (16, H/2, W/2)``; slice m is ``M_m`` applied to slice m (eq. 11).

    Sub-image ``m = 4n + q`` is aperture n's warp ``H_n`` (``geometry``), the PSF, 2x2 pixel
    integration, then the Bayer site q's decimation: its pixels land where
    :attr:`ArrayGeometry.lr_homographies` says. ``psf_kernels``: one kernel per aperture
    (replacing ``psf_kernel``); ``flat`` ``(16, H/2, W/2)``: the flat field at each sub-image's
    pixels (:meth:`capssim.camera.rig.RigModel.lr_flat_field`), multiplied last.
    """
    hh, ww = _check_hr_shape(geometry.hr_shape)
    offsets = [BAYER_OFFSETS[m % 4] for m in range(N_LR_IMAGES)]
    ops = [
        Reshape((N_LR_IMAGES, hh, ww), (N_LR_IMAGES, 1, hh, ww)),
        Warp(geometry.lr_aperture_warps, 1, (hh, ww)),
        # PSF, 2x2 integration and the Bayer site's decimation as one stride-4 convolution
        BlurIntegrateDecimate(psf_kernel if psf_kernels is None else list(psf_kernels), (N_LR_IMAGES, 1, hh, ww),
                              integrate=2, decimate=2, offsets=offsets),
        Reshape((N_LR_IMAGES, 1, hh // 4, ww // 4), (N_LR_IMAGES, hh // 4, ww // 4)),
    ]
    if flat is not None:
        flat = np.asarray(flat, dtype=np.float64)
        if flat.shape != (N_LR_IMAGES, hh // 4, ww // 4):
            raise InputError("flat", f"shape {flat.shape}", f"shape ({N_LR_IMAGES}, {hh // 4}, {ww // 4})")
        ops.append(Multiply(flat))
    return Composition(ops, name="lr_sampling")


def lr_channel_matrix(*, extinction_ratio: float | None = None, rig: RigModel | None = None) -> np.ndarray:
    """``(16, 12)``: what each low-resolution image sees of the 12 channels (analyzer + colour)."""
    if rig is not None and not rig.is_ideal:
        return rig.lr_channel_matrix()
    full = analyzer_matrix(POLARIZER_ANGLES_DEG, extinction_ratio=extinction_ratio)  # (12, 12), row 3n+k
    return np.stack([full[LR_IMAGE_CHANNELS[m]] for m in range(N_LR_IMAGES)])


def lr_observation_operator(geometry: ArrayGeometry, psf_kernel, *,
                            extinction_ratio: float | None = None, rig: RigModel | None = None) -> Composition:
    """``(12, 2H, 2W) -> (16, H/2, W/2)``: all 16 Bayer sub-images from the 12-channel image.

    With ``rig``: its analyzer, per-aperture PSFs and flat field (the sub-images of
    :func:`caps_raw_operator` with the same rig, exactly).
    """
    hh, ww = _check_hr_shape(geometry.hr_shape)
    mix = ChannelMix(lr_channel_matrix(extinction_ratio=extinction_ratio, rig=rig), hh, ww)
    kernels = rig.psf_kernels() if rig is not None else None
    flat = rig.lr_flat_field((hh // 2, ww // 2)) if rig is not None and rig.has_flat_field else None
    sampling = lr_sampling_operator(geometry, psf_kernel, psf_kernels=kernels, flat=flat)
    return Composition([mix, sampling], name="lr_observation")


def dofp_raw_operator(hr_shape, psf_kernel, *, layout=DEFAULT_DOFP_LAYOUT, extinction_ratio: float | None = None) -> Composition:
    """``(12, 2H, 2W) -> (2H, 2W)``: the DoFP colour-polarization mosaic with the same optics."""
    hh, ww = _check_hr_shape(hr_shape)
    ops = [Convolve(psf_kernel, (N_CHANNELS, hh, ww))]
    if extinction_ratio is not None and not np.isinf(extinction_ratio):
        ops.append(ChannelMix(analyzer_matrix(POLARIZER_ANGLES_DEG, extinction_ratio=extinction_ratio), hh, ww))
    ops.append(DoFPMosaic(hh, ww, layout=layout))
    return Composition(ops, name="dofp_raw")


__all__ = [
    "N_APERTURES",
    "caps_raw_operator",
    "dofp_raw_operator",
    "lr_channel_matrix",
    "lr_observation_operator",
    "lr_sampling_operator",
]
