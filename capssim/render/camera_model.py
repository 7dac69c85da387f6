"""From rendered views to the ground truth and the raw irradiance, with the shared observation model.

Everything after the renderer uses the operators of :mod:`capssim.operators` (paper eq. 9):
``Convolve`` (the optical PSF, applied identically to the ground truth and to every
aperture), ``IntegrateDecimate`` (box pixels), ``Warp`` (the planar warp), ``Analyzer``,
``BayerMosaic`` (RGGB) and the DoFP operator of
:class:`~capssim.operators.measurement.CameraArrayMeasurement`.

Planar scenes are rendered once: the reference view is rendered ``fine`` times finer than the
ground truth and with a margin, and each aperture's view is the exact plane homography of it
(bilinear on the finer grid, then box-integrated back). Otherwise apertures 1-3 are rendered
from their own positions, each only through its own polarizer angle, and aperture 0's view is
the ground-truth render itself.

An imperfect array (:class:`capssim.camera.rig.RigModel`) goes through the same operators as
:func:`capssim.operators.camera.caps_raw_operator`: its analyzer rows (``ChannelMix``; on the
per-aperture path apertures 1-3 are rendered through polarizers at the rig's angles and
per-colour extinction ratios), one PSF per aperture (then the ground truth has none), and the
flat field (``Multiply``) on the raw irradiance after the Bayer mosaic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from capssim.camera.rig import RigModel
from capssim.conventions import N_APERTURES, POLARIZER_ANGLES_DEG
from capssim.operators import Analyzer, BayerMosaic, ChannelMix, Convolve, IntegrateDecimate, Multiply, Warp
from capssim.operators.measurement import CameraArrayMeasurement
from capssim.render.integrator import stokes_to_twelve
from capssim.render.pinhole_array import scale_matrix, shift_matrix
from capssim.render.sample_budget import to_tensor


def warp_margin(homographies: np.ndarray, size: int, psf_radius: int) -> int:
    """HR pixels of margin the reference render needs so every aperture's warp samples real content."""
    lo, hi = -psf_radius - 1.0, size - 1.0 + psf_radius + 1.0
    corners = np.array([[lo, lo, 1.0], [hi, lo, 1.0], [lo, hi, 1.0], [hi, hi, 1.0]])
    worst = 0.0
    for h in homographies:
        back = corners @ np.linalg.inv(h).T
        back = back[:, :2] / back[:, 2:3]
        worst = max(worst, float(np.max(-back)), float(np.max(back - (size - 1))))
    return int(math.ceil(max(worst, psf_radius))) + 2


def blur_crop(image: torch.Tensor, kernel: np.ndarray, margin: int) -> torch.Tensor:
    """Optical PSF (shared ``Convolve``) on an image rendered with ``margin`` extra pixels, then crop."""
    out = Convolve(kernel, tuple(image.shape))(image)
    if margin:
        out = out[..., margin:-margin, margin:-margin]
    return out.contiguous()


@dataclass
class Irradiance:
    """The ground truth ``(12, S, S)`` (the optical PSF included), the CAPS raw irradiance
    ``(4, S/2, S/2)`` and the DoFP raw irradiance ``(S, S)``, before the sensor."""

    gt: torch.Tensor
    caps: torch.Tensor
    dofp: torch.Tensor


def aperture_kernels(kernel: np.ndarray, rig: RigModel | None) -> list[np.ndarray]:
    """The optical PSF of each aperture: the rig's own ones, else ``kernel`` for all four."""
    own = rig.psf_kernels() if rig is not None else None
    return own if own is not None else [kernel] * N_APERTURES


def _analyzer(height: int, width: int, extinction_ratio: float | None, rig: RigModel | None):
    """Aperture n's polarizer per colour, ``(12, H, W) -> (4, 3, H, W)``: the rig's, else the ideal one."""
    if rig is None or rig.is_ideal:
        return Analyzer(height, width, extinction_ratio=extinction_ratio)
    return ChannelMix(rig.analyzer_matrix(), height, width, out_lead=(N_APERTURES, 3))


def _warped_apertures(twelve: torch.Tensor, homographies: np.ndarray, *, fine: int, margin: int, size: int,
                      kernel: np.ndarray, extinction_ratio: float | None, rig: RigModel | None = None) -> torch.Tensor:
    """``(4, 3, S, S)``: each aperture's analyzed view as the plane homography of the fine reference render."""
    kernels = aperture_kernels(kernel, rig)
    analyzed = _analyzer(twelve.shape[1], twelve.shape[2], extinction_ratio, rig)(twelve)
    s_k = scale_matrix(fine)
    apertures = []
    for n in range(N_APERTURES):
        kernel = kernels[n]
        psf_radius = kernel.shape[0] // 2
        out_side = fine * (size + 2 * psf_radius)
        g = s_k @ shift_matrix(psf_radius, psf_radius) @ homographies[n] @ shift_matrix(
            -margin, -margin) @ np.linalg.inv(s_k)
        warped = Warp(g[None], 3, tuple(twelve.shape[1:]), (out_side, out_side))(analyzed[n:n + 1])[0]
        hr = IntegrateDecimate(fine, tuple(warped.shape))(warped)
        apertures.append(blur_crop(hr, kernel, psf_radius))
    return torch.stack(apertures)


def _rendered_apertures(twelve: torch.Tensor, gt: torch.Tensor, aperture_views: dict[int, np.ndarray], *,
                        kernel: np.ndarray, margin: int, size: int, extinction_ratio: float | None,
                        rig: RigModel | None) -> torch.Tensor:
    """``(4, 3, S, S)`` of the per-aperture path: aperture 0 analyzes the reference render, 1-3 were
    rendered through their own polarizers (the rig's angle and per-colour extinction: the pipeline
    passes them to the renderer); each gets its own PSF."""
    kernels = aperture_kernels(kernel, rig)
    if rig is None or rig.is_ideal:
        ref = Analyzer(size, size, angles_deg=(POLARIZER_ANGLES_DEG[0],), extinction_ratio=extinction_ratio)(gt)[0]
    else:
        source = gt if rig.psf is None else blur_crop(twelve, kernels[0], margin)
        ref = ChannelMix(rig.analyzer_matrix()[0:3], size, size)(source)
    apertures = [ref]
    for n in range(1, N_APERTURES):
        apertures.append(blur_crop(to_tensor(aperture_views[n]), kernels[n], margin))
    return torch.stack(apertures)


def observe(reference_stokes: np.ndarray, aperture_views: dict[int, np.ndarray], homographies: np.ndarray, *,
            measurement: CameraArrayMeasurement, kernel: np.ndarray, size: int, fine: int, margin: int,
            use_warp: bool, rig: RigModel | None = None) -> Irradiance:
    """The ground truth and raw irradiance of a render.

    ``reference_stokes``: the reference view's Stokes render (``fine`` times finer, ``margin``
    HR pixels around); ``aperture_views``: ``n -> (3, S + 2 margin, S + 2 margin)`` analyzed
    renders of apertures 1-3 (per-aperture path only); ``homographies`` ``(4, 3, 3)`` HR
    reference -> aperture; ``kernel``: the optical PSF; ``measurement``: its DoFP operator (no
    PSF: the ground truth has it) and extinction ratio. ``rig``: an imperfect array, applied
    with the operators of :func:`capssim.operators.camera.caps_raw_operator` (its analyzer
    rows, per-aperture PSFs, and the flat field multiplying the raw irradiance after the mosaic).
    """
    extinction_ratio = measurement.extinction_ratio
    with torch.no_grad():
        twelve = to_tensor(stokes_to_twelve(reference_stokes))  # (12, Hm, Wm) on the render grid
        # with per-aperture PSFs they are the whole optical blur: the ground truth has none
        gt_kernel = np.ones((1, 1)) if rig is not None and rig.psf is not None else kernel
        if use_warp:
            gt = blur_crop(IntegrateDecimate(fine, tuple(twelve.shape))(twelve), gt_kernel, margin)
            aperture_hr = _warped_apertures(twelve, homographies, fine=fine, margin=margin, size=size, kernel=kernel,
                                            extinction_ratio=extinction_ratio, rig=rig)
        else:
            gt = blur_crop(twelve, gt_kernel, margin)
            aperture_hr = _rendered_apertures(twelve, gt, aperture_views, kernel=kernel, margin=margin, size=size,
                                              extinction_ratio=extinction_ratio, rig=rig)
        caps = BayerMosaic((N_APERTURES, 3, size // 2, size // 2))(
            IntegrateDecimate(2, tuple(aperture_hr.shape))(aperture_hr))
        if rig is not None and rig.has_flat_field:
            caps = Multiply(rig.flat_field((size // 2, size // 2)))(caps)
        dofp = measurement.dofp_operator((size, size))(gt)
    return Irradiance(gt, caps, dofp)


__all__ = ["Irradiance", "aperture_kernels", "blur_crop", "observe", "warp_margin"]
