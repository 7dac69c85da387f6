"""The CAPS front end: rearrangement, registration and operator (paper section 3.1, eq. 15).

:func:`caps_observations` is the front end of ``caps`` and its joint ablations: the 4 RGGB frames
rearranged into 16 observations of the 12 channels (:mod:`capssim.reconstruct.model.rearrange`), the
array geometry (stored or registered, :func:`~capssim.reconstruct.model.observation_model.method_geometry`)
and the sampling operator ``M`` (:func:`capssim.operators.camera.lr_sampling_operator` with the capture's
PSF, or ``psf_sigma``'s Gaussian).

With a calibration (:mod:`capssim.reconstruct.model.observation_model`) ``M`` takes the per-aperture PSFs
and multiplies each observation by its flat field, the data term mixes the channels by the calibrated
analyzer (``(16, 12)``, exact adjoint), and CAGF and the initialization see flat-field-corrected
observations, the initialization unmixed per pixel by the inverse analyzer (12x12).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from capssim.operators.camera import lr_sampling_operator

from ..model.data_term import field_of_view_mask
from ..model.observation_model import (
    calibrated_analyzer,
    lr_flat_field,
    method_geometry,
    method_psf_kernels,
)
from ..model.rearrange import observations_from_capture
from ..run_context import RunContext
from .problem import FrontEnd, Problem

__all__ = ["caps_observations", "sampling_operator"]


def sampling_operator(capture, context: RunContext, geometry, psf_sigma: float):
    """The sampling operator ``M`` of the 16 observations and what the array model adds to it.

    Parameters
    ----------
    capture : Capture
        The CAPS capture (its PSF and HR shape).
    context : RunContext
        The run; ``context.calibration`` is the array model (``None``: ideal).
    geometry : ArrayGeometry
        The array geometry (stored or registered).
    psf_sigma : float
        The ``psf_sigma`` option (HR pixels; -1: the capture's PSF).

    Returns
    -------
    tuple
        ``M`` ``(16, H, W) -> (16, H/4, W/4)``, the analyzer mixing ``(16, 12)`` (``None``: ideal), the PSF
        record and the flat field ``(16, h, w)`` (``None``: ideal).
    """
    kernel, kernels, psf_record = method_psf_kernels(capture, context, psf_sigma)
    if context.calibration is None:
        return lr_sampling_operator(geometry, kernel), None, psf_record, None
    flat = lr_flat_field(capture, context)
    operator = lr_sampling_operator(geometry, kernel, psf_kernels=kernels, flat=flat)
    mixing = None if calibrated_analyzer(context) is None else context.calibration.rig.lr_channel_matrix()
    return operator, mixing, psf_record, flat


def caps_observations(capture, context: RunContext, options) -> FrontEnd:
    """The joint problem of ``caps``: 16 observations ``(16, H/4, W/4)`` of the 12 channels ``(12, H, W)``.

    Parameters
    ----------
    capture : Capture
        The CAPS capture (4 RGGB raw frames).
    context : RunContext
        The run (device, timer, registration choices, calibration).
    options : CapsOptions
        The run's options (``psf_sigma``, ``fov_mask``).

    Returns
    -------
    FrontEnd
        One :class:`Problem` over all 12 channels; the registration and PSF records; ``params``
        ``channels`` and ``reference_image``; ``extra`` ``field_of_view_weight_fraction``.
    """
    dev, timer = context.device, context.timer
    with timer.stage("rearrange"):
        obs = observations_from_capture(capture, device=dev)
        lr_images, lr_saturated = capture.lr_images()
    with timer.stage("registration"):
        geometry, reg_record = method_geometry(capture, context, images=lr_images, saturated=lr_saturated)
        homographies = geometry.lr_homographies
    with timer.stage("operator"):
        operator, mixing, psf_record, flat = sampling_operator(capture, context, geometry, options.psf_sigma)
        if options.fov_mask:
            inside = field_of_view_mask(homographies, tuple(obs.images.shape[-2:]), capture.hr_shape,
                                        half_extent=0.125)
            obs.weights = obs.weights * torch.as_tensor(inside, dtype=obs.weights.dtype, device=dev)
    seen = obs if flat is None else replace(obs, images=obs.images / torch.as_tensor(flat, dtype=obs.images.dtype,
                                                                                      device=dev))
    unmix = None if mixing is None else calibrated_analyzer(context)  # the fused channels see A x per pixel
    problem = Problem(obs=obs, operator=operator, homographies=homographies, seen=seen, mixing=mixing, unmix=unmix)
    return FrontEnd(problems=[problem], registration=reg_record, psf=psf_record,
                    params={"channels": obs.n_channels, "reference_image": 0},
                    extra={"field_of_view_weight_fraction": float(obs.weights.mean())}, geometry=geometry)
