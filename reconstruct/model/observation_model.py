"""A capture's observation model as a reconstruction method sees it: array geometry, PSF and array model.

The geometry is either the one stored with the capture (``true_warps``) or the one the
registration estimates from the 16 Bayer sub-images (:mod:`capssim.reconstruct.registration`);
either way it is one :class:`capssim.camera.array_geometry.ArrayGeometry`, from which every method takes the
16 sub-image homographies (paper section 3.1) or the 4 aperture homographies.
The PSF is the capture's (``meta.json["psf"]``) unless the method's ``psf_sigma`` option names a
Gaussian (the paper's isotropic Gaussian kernel; useful for real captures).

With a calibration (``RunContext.calibration``, :mod:`capssim.reconstruct.calibration_model`) the
array is a :class:`capssim.camera.rig.RigModel`: its per-aperture PSFs replace the capture's PSF
(:func:`method_psf_kernels`), its flat field ``gain_n V_n`` (:func:`lr_flat_field`) multiplies
each observation and divides the images that CAGF, the initialization and the registration see,
and its analyzer (:func:`calibrated_analyzer`) mixes the channels each observation sees
(:func:`unmix_analyzer` inverts it per pixel).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.homography import registration_error_hr_px
from capssim.camera.psf import PSF
from capssim.captures.capture import Capture
from capssim.errors import CapssimError, InputError
from capssim.runtime.threads import registration_threads

from ..registration.estimate import estimate_lr_homographies, identity_fallbacks
from ..registration.parameters import registration_parameters
from ..registration.store import stored_or_computed
from ..run_context import RunContext


def truth_known(capture: Capture) -> bool:
    """Whether the capture's stored warps and PSF are the true ones (simulated or rendered)."""
    return capture.meta.get("kind") in ("simulated", "rendered")


#: the ``psf_sigma`` option's value that means "the capture's own PSF" (the default)
CAPTURE_PSF_SIGMA = -1.0


def method_psf(capture: Capture, psf_sigma: float) -> tuple[np.ndarray, dict]:
    """The sampling kernel on the HR grid ``(k, k)`` and its record.

    ``psf_sigma`` (HR pixels): a finite number ``>= 0`` names a Gaussian; exactly
    :data:`CAPTURE_PSF_SIGMA` (-1) takes the capture's PSF; anything else is refused. A kernel
    wider than the image, or too large to convolve, is refused before it is built.
    """
    valid = "-1 (the capture's PSF, the default) or a finite number >= 0 (Gaussian std, HR pixels; 0 = no blur)"
    if isinstance(psf_sigma, bool) or not isinstance(psf_sigma, (int, float, np.floating, np.integer)):
        raise InputError("psf_sigma", repr(psf_sigma), valid)
    if psf_sigma == CAPTURE_PSF_SIGMA:
        psf = capture.psf
        spec = dict(capture.meta.get("psf") or {"type": "none"})
        spec["source"] = "capture meta.json"
        psf.check_extent(capture.hr_shape, option="meta.json psf")
        return capture.psf_kernel(), spec
    if not (math.isfinite(psf_sigma) and psf_sigma >= 0):
        raise InputError("psf_sigma", psf_sigma, valid)
    psf = PSF.gaussian(psf_sigma)
    psf.check_extent(capture.hr_shape, option="psf_sigma")
    return psf.kernel(), {"type": "gaussian", "sigma_hr_px": psf_sigma, "source": "option psf_sigma"}


def method_psf_kernels(capture: Capture, context: RunContext, psf_sigma: float) -> tuple[np.ndarray, list | None, dict]:
    """The HR-grid kernel ``(k, k)`` of :func:`method_psf`, the calibrated rig's per-aperture kernels
    (a list of 4, or ``None``: the one kernel for all) and the PSF record.

    The calibration's PSFs replace the capture's PSF; an explicit ``psf_sigma`` option (``>= 0``) wins
    over both.
    """
    kernel, record = method_psf(capture, psf_sigma)
    calibration = context.calibration
    if calibration is None or calibration.rig.psf is None or psf_sigma != CAPTURE_PSF_SIGMA:
        return kernel, None, record
    record = {"type": "per aperture", "apertures": [dict(p) for p in calibration.rig.psf],
              "source": f"calibration ({calibration.record['source']})"}
    return kernel, calibration.rig.psf_kernels(), record


def calibrated_analyzer(context: RunContext) -> np.ndarray | None:
    """``(12, 12)`` the calibrated analyzer (:meth:`capssim.camera.rig.RigModel.analyzer_matrix`: row ``3n + k`` is
    aperture n's polarizer in colour k), or ``None`` when there is no calibration or its analyzer is ideal."""
    calibration = context.calibration
    if calibration is None:
        return None
    analyzer = calibration.rig.analyzer_matrix()
    return None if np.array_equal(analyzer, np.eye(analyzer.shape[0])) else analyzer


def unmix_analyzer(image: torch.Tensor, analyzer: np.ndarray) -> torch.Tensor:
    """``x = A^-1 y`` per pixel: the ``(C, H, W)`` channels from images ``y`` that see ``A x``.

    ``analyzer`` ``(C, C)``: :meth:`capssim.camera.rig.RigModel.analyzer_matrix` (``C = 12``, rows ``3n + k``:
    aperture n in colour k; block diagonal per colour, so 3 independent 4x4 systems) or one colour's
    ``(4, 4)`` block. Its exact inverse undoes the angle offsets and the finite extinction; the matrix
    is close to the identity and well conditioned (condition number about 1.15 for angle errors of
    2 degrees and extinction ratios down to 30).
    """
    inverse = torch.as_tensor(np.linalg.inv(np.asarray(analyzer, dtype=np.float64)), dtype=image.dtype,
                              device=image.device)
    return torch.einsum("ij,jhw->ihw", inverse, image)


def lr_flat_field(capture: Capture, context: RunContext) -> np.ndarray | None:
    """``(16, H/2, W/2)`` the calibrated flat field at each sub-image's pixels, or ``None`` (ideal array)."""
    calibration = context.calibration
    if calibration is None or not calibration.rig.has_flat_field:
        return None
    return calibration.rig.lr_flat_field(capture.raw_shape)


def method_geometry(capture: Capture, context: RunContext, *, images: np.ndarray,
                    saturated: np.ndarray) -> tuple[ArrayGeometry, dict]:
    """The array geometry a method reconstructs with (true, calibrated or estimated) and a record of it.

    ``--true-warps`` takes the capture's stored warps; otherwise a calibration's geometry (when its
    file has one) replaces the registration; otherwise the sub-images are registered (divided by
    the calibrated flat field first, when there is one, so that vignetting does not bias them).

    ``images`` ``(16, H/2, W/2)`` and ``saturated`` (same shape, bool) are the Bayer sub-images
    the registration works on. Estimated warps are registered once per capture and input and
    stored with it (:mod:`capssim.reconstruct.registration.store`); the record's ``store`` and
    ``reused_from`` say whether they were computed or reused. When the capture's truth is known,
    the record holds the registration error in HR pixels per sub-image.
    """
    hr_shape = capture.hr_shape
    calibration = context.calibration
    if context.true_warps:
        geometry = capture.geometry
        record = {"source": "true (meta.json)"}
        if calibration is not None and calibration.geometry is not None:
            record["note"] = "--true-warps: the calibration's geometry is not used"
    elif calibration is not None and calibration.geometry is not None:
        geometry = calibration.geometry
        record = {"source": f"calibration ({calibration.record['source']})"}
    else:
        if calibration is not None and calibration.rig.has_flat_field:  # register what the scene looks like
            images = (images / calibration.rig.lr_flat_field(capture.raw_shape)).astype(np.float32)
        mode = context.registration
        aperture, record = stored_or_computed(
            capture.path, lambda: _estimated_aperture_warps(images, saturated, hr_shape, mode, context.device),
            images=images, saturated=saturated, hr_shape=hr_shape, mode=mode,
            parameters=registration_parameters(mode), reuse=context.reuse_registration)
        geometry = ArrayGeometry(aperture, hr_shape)
    record["aperture_homographies"] = np.asarray(geometry.aperture_homographies, dtype=float).tolist()
    if truth_known(capture):
        err = registration_error_hr_px(geometry.lr_homographies, capture.true_lr_homographies(), hr_shape)
        record.update({"error_hr_px_median": float(np.median(err)), "error_hr_px_max": float(np.max(err)),
                       "error_hr_px": [float(e) for e in err]})
    return geometry, record


def _estimated_aperture_warps(images: np.ndarray, saturated: np.ndarray, hr_shape, mode: str,
                              device) -> tuple[np.ndarray, dict]:
    """Register the sub-images (:func:`~capssim.runtime.threads.registration_threads`: one torch thread, or under
    ``auto`` the free cores for large images); the aperture homographies ``(4, 3, 3)`` and the record."""
    with registration_threads(int(images.shape[-2]) * int(images.shape[-1])):
        result = estimate_lr_homographies(images.astype(np.float32), hr_shape=hr_shape, saturated=saturated,
                                          parameters=registration_parameters(mode), device=str(device))
    aperture = np.asarray(result.aperture_homographies, dtype=np.float64)
    if aperture.shape != (4, 3, 3) or not np.all(np.isfinite(aperture)):
        raise CapssimError(f"registration returned invalid homographies (shape {aperture.shape}, "
                           f"finite: {bool(np.all(np.isfinite(aperture)))})")
    return aperture, _registration_record(result, mode)


def _registration_record(result, mode: str) -> dict:
    diagnostics = result.diagnostics
    record = {"source": "estimated (capssim.reconstruct.registration)", "mode": mode,
              "luminance": diagnostics.get("luminance"), "time_s": diagnostics.get("time_s"),
              "warnings": list(diagnostics.get("warnings", [])),
              "fallbacks": {str(n): why for n, why in identity_fallbacks(diagnostics.get("apertures", [])).items()}}
    for key in ("intensity_texture_ratio", "polarization_cue", "wide_window_retry"):
        if key in diagnostics:
            record[key] = diagnostics[key]
    return record
