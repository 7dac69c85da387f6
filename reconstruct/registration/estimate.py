"""Registration of the four apertures of a CAPS capture (paper section 3.1, "registration").

Estimates, from the 16 Bayer sub-images alone, the homographies ``H_m`` (HR reference
pixel -> sub-image m pixel, ``(x=col, y=row)``) that the reconstruction needs. The Bayer
sub-pixel offsets are known, so only the three aperture warps ``H_1..H_3`` (HR reference
-> aperture-HR) are estimated, against the 0 deg aperture; then ``H_{4n+q} = S_q @ H_n``
(:func:`capssim.camera.array_geometry.lr_homographies`).

Method (it replaces the paper's feature clustering, Crab-HFP); its
options are a :class:`~capssim.reconstruct.registration.parameters.RegistrationParameters`:

1. **Registration image per aperture** (``luminance``, :mod:`~capssim.reconstruct.registration.luminance`):
   ``binomial`` (the 3x3 binomial filter of the raw mosaic: its luminance ``(R + 2G + B) / 4``,
   no demosaicking) or ``ri-binomial`` (the same filter of the luminance of a residual-interpolation
   demosaicking, Kiku et al. 2016, which removes most of the colour-edge leak of ``binomial``).
   ``auto`` (default) keeps the image whose registered images obey ``I0 + I90 = I45 + I135``
   better (lower Stokes residual rms). Step 2 runs on ``binomial``; the ``ri-binomial`` image is
   judged at those warps and, only if it is more consistent there, refined from them on the finest
   level (:data:`AUTO_REFINE_LEVEL`), or registered from scratch when the Stokes-consistency rescue
   set some warps. With fewer than four usable apertures it is ``binomial``. Raw pixels with a
   saturated sample in their 3x3 neighbourhood are masked.
2. **Registration** of apertures 1-3 to aperture 0 by
   :func:`~capssim.reconstruct.registration.engine.register_stack`: phase-correlation candidates,
   then a coarse-to-fine refinement of a local-correlation criterion (local gain and offset per
   window, so polarizer angle and colour do not matter) plus the Stokes consistency
   ``I0 + I90 = I45 + I135`` on the finest levels, with cubic-spline interpolation. Apertures that
   still match poorly restart from more phase-correlation peaks, and then from a joint re-run
   dominated by the Stokes consistency (kept if it lowers the Stokes residual by > 10 %).

Safeguards: constant / flat images, or frames too small for the model, fall back to the
identity (or a smaller model) with a logged warning and a flag in ``diagnostics``; a warp no
camera array has (rotation, scale) falls back to the identity; a poor final match is flagged
``unreliable``. On a scene whose structure is in its polarization only (flat S0), the motion common to the 45
and 135 deg apertures, which no intensity criterion sees, is set by the smoothness of the linear polarization
(:mod:`~capssim.reconstruct.registration.polarization_cue`) and a warning says so.

Raw coordinates of aperture n relate to its aperture-HR coordinates by
:func:`capssim.camera.array_geometry.raw_matrix`: ``H_n = R^-1 G_n R`` for the estimated raw-to-raw
matrix ``G_n``. Measurements of the choices above: ``docs/notes/registration-internals.md``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from capssim.camera.array_geometry import lr_homographies as lr_from_aperture
from capssim.camera.homography import rotation_and_scale
from capssim.conventions import N_APERTURES, N_LR_IMAGES
from capssim.errors import InputError

from ..filters import gaussian_blur
from .criterion import stokes_residual_rms
from .engine import StackRegistration, register_stack
from .image_ops import noise_sigma
from .luminance import (
    LUMINANCE_METHODS,
    mosaic_from_sub_images,
    ri_binomial_luminance,
    usable_pixels,
)
from .parameters import (
    REGISTRATION_MODES,
    RegistrationParameters,
    registration_parameters,
)
from .plausibility import aperture_warp, implausible_apertures, is_plausible
from .polarization_cue import check_polarization_only

__all__ = ["REGISTRATION_MODES", "RegistrationParameters", "RegistrationResult", "estimate_lr_homographies",
           "identity_fallbacks", "registration_parameters"]

log = logging.getLogger(__name__)

#: smallest raw side (pixels) for which each model is attempted; smaller frames use a smaller model
MIN_RAW_SIDE = {"translation": 8, "euclidean": 16, "similarity": 16, "affine": 24, "homography": 32}
_MODELS_BY_SIZE = ["translation", "euclidean", "similarity", "affine", "homography"]

#: final local R^2 below which an aperture's estimate gets a warning (not the unreliable flag):
#: right estimates on strongly polarized scenes reach 0.4-0.8, wrong ones 0.3-0.5 (apertures whose
#: warp the Stokes-consistency rescue set get their own warning instead)
WEAK_CORRELATION = 0.6

#: ``luminance='auto'``: the pyramid level on which the demosaicked image's refinement (from the
#: binomial warps) starts
AUTO_REFINE_LEVEL = 0


@dataclass
class RegistrationResult:
    """What :func:`estimate_lr_homographies` returns.

    ``lr_homographies`` ``(16, 3, 3)`` float64: HR reference pixel -> sub-image m pixel
    (``m = 4n + q``), as stored in ``meta.json``. ``aperture_homographies`` ``(4, 3, 3)``:
    HR reference -> aperture-HR (aperture 0 is the identity). ``diagnostics``: per aperture
    the final local R^2 (``correlation``), fallbacks and flags; per pyramid level the
    iterations and time; warnings; the total time.
    """

    lr_homographies: np.ndarray
    aperture_homographies: np.ndarray
    diagnostics: dict = field(default_factory=dict)


# -- inputs ---------------------------------------------------------------------------------------------
def _as_tensor(x, name: str, device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x.detach()
    else:
        arr = np.asarray(x)
        if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            raise InputError(name, f"dtype {arr.dtype}", "a numeric array")
        t = torch.from_numpy(np.ascontiguousarray(arr))
    return t.to(device)


def _checked_inputs(lr_images, hr_shape, saturated, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The sub-images ``(16, h, w)`` and their saturation mask (bool) as tensors on ``device``, checked."""
    x = _as_tensor(lr_images, "lr_images", device)
    if x.ndim != 3 or x.shape[0] != N_LR_IMAGES:
        raise InputError("lr_images", f"shape {tuple(x.shape)}", "shape (16, h, w): the Bayer sub-images m = 4n + q")
    if not torch.is_floating_point(x):
        raise InputError("lr_images", f"dtype {x.dtype}", "a float array (values on [0, 1] full scale)")
    _, h, w = x.shape
    try:
        hh, ww = (int(v) for v in hr_shape)
    except Exception as exc:
        raise InputError("hr_shape", hr_shape, "a pair (2H, 2W) of ints") from exc
    if (hh, ww) != (4 * h, 4 * w):
        raise InputError("hr_shape", (hh, ww), f"(4h, 4w) = {(4 * h, 4 * w)} for sub-images of {h}x{w}")
    if not bool(torch.isfinite(x).all()):
        raise InputError("lr_images", f"{int((~torch.isfinite(x)).sum())} NaN/inf values", "finite values")
    if saturated is None:
        return x, torch.zeros(x.shape, dtype=torch.bool, device=device)
    sat = _as_tensor(saturated, "saturated", device)
    if tuple(sat.shape) != tuple(x.shape):
        raise InputError("saturated", f"shape {tuple(sat.shape)}", f"shape {tuple(x.shape)} like lr_images")
    return x, sat.to(torch.bool)


def _warn(diag: dict, message: str) -> None:
    """Log ``message`` and keep it in ``diag["warnings"]``."""
    log.warning(message)
    diag["warnings"].append(message)


# -- steps ----------------------------------------------------------------------------------------------
def _usable_model(model: str, raw_shape, diag: dict) -> str | None:
    """The largest motion model, not larger than ``model``, that raw frames of ``raw_shape`` support (None: none)."""
    rh, rw = raw_shape
    used = None
    for cand in reversed(_MODELS_BY_SIZE[: _MODELS_BY_SIZE.index(model) + 1]):
        if cand == "euclidean" and model != "euclidean":
            continue
        if min(rh, rw) >= MIN_RAW_SIDE[cand]:
            used = cand
            break
    if used != model:
        _warn(diag, f"registration: raw frames of {rh}x{rw} px are too small for the {model!r} model; "
              + (f"using {used!r}" if used else "using the identity"))
    return used


def _active_apertures(lum: torch.Tensor, valid: torch.Tensor, model: str | None, diag: dict
                      ) -> tuple[list[int], list[dict]]:
    """The apertures 1-3 to register and a record per aperture; flat, constant or saturated images
    (and all of them when the reference is, or no model fits) keep the identity."""
    sigma = noise_sigma(lum)
    spread = lum.flatten(1).std(dim=1)
    diag["noise_sigma"] = [float(v) for v in sigma]
    diag["image_std"] = [float(v) for v in spread]
    flat = (spread <= 1e-6) | (spread <= 0.5 * sigma) | (valid.flatten(1).mean(1) < 0.05)
    per_ap = [{"aperture": n, "fallback": "none"} for n in range(N_APERTURES)]
    per_ap[0]["fallback"] = "reference"
    active = [n for n in range(1, N_APERTURES)]
    if model is None:
        for n in active:
            per_ap[n]["fallback"] = "identity: frame too small"
        return [], per_ap
    if bool(flat[0]):
        _warn(diag, "registration: the reference (0 deg) image is flat, constant or saturated; "
              "using the identity for every aperture")
        for n in active:
            per_ap[n]["fallback"] = "identity: flat reference image"
        return [], per_ap
    for n in list(active):
        if bool(flat[n]):
            _warn(diag, f"registration: aperture {n} ({45 * n} deg) image is flat, constant or saturated; "
                  "using the identity for it")
            per_ap[n]["fallback"] = "identity: flat image"
            active.remove(n)
    return active, per_ap


def _register_apertures(raw: torch.Tensor, lum: torch.Tensor, valid: torch.Tensor, active: list[int],
                        model: str, parameters: RegistrationParameters, diag: dict) -> StackRegistration:
    """Register the ``active`` apertures' images to aperture 0's; with ``luminance='auto'`` keep the
    more Stokes-consistent of the binomial and the demosaicked registration images."""
    stokes = parameters.stokes_weight if len(active) == 3 else 0.0
    if parameters.stokes_weight > 0 and stokes == 0.0:
        _warn(diag, "registration: the Stokes-consistency term needs all four apertures; using local correlation only")
    if parameters.stokes_subspace_std > 0 and len(active) != 3:
        _warn(diag, "registration: the Stokes-subspace refinement needs all four apertures; skipped")

    def register(image, **kwargs):
        return register_stack(image[0], image[active], ref_valid=valid[0], moving_valid=valid[active], model=model,
                              window_radius=parameters.window_radius, stokes_weight=stokes,
                              stokes_levels=parameters.stokes_levels, max_iterations=parameters.max_iterations,
                              robust_power=parameters.robust_power, robust_levels=parameters.robust_levels,
                              robust_passes=parameters.robust_passes,
                              stokes_subspace_std=parameters.stokes_subspace_std,
                              robust_window_radius=parameters.robust_window_radius,
                              half_resolution_min_size=parameters.half_resolution_min_size, **kwargs)

    reg = register(lum)
    if parameters.luminance != "auto" or len(active) != 3:
        return reg
    # the residual is set by the image far more than by the small warp differences, so the
    # demosaicked image is judged at the binomial warps first and refined from them only if it wins
    ri_image = ri_binomial_luminance(raw)
    rms = {"binomial": reg.info.get("stokes_residual_rms"),
           "ri-binomial at the binomial warps": stokes_residual_rms(
               ri_image[0], ri_image[active], reg.params, ref_valid=valid[0], moving_valid=valid[active], model=model)}
    diag["luminance_stokes_residual_rms"] = rms
    if not (all(v is not None and np.isfinite(v) for v in rms.values())
            and rms["ri-binomial at the binomial warps"] < rms["binomial"]):
        return reg
    # warps set by the Stokes-consistency rescue would drift under a local-correlation
    # refinement: then the demosaicked image is registered from scratch
    rescued = reg.info.get("stokes_joint", {}).get("kept", False)
    alt = register(ri_image) if rescued else \
        register(ri_image, initial=torch.as_tensor(reg.params), start_level=AUTO_REFINE_LEVEL)
    rms["ri-binomial"] = alt.info.get("stokes_residual_rms")
    if rms["ri-binomial"] is not None and np.isfinite(rms["ri-binomial"]) and rms["ri-binomial"] < rms["binomial"]:
        diag["luminance"] = "ri-binomial"
        return alt
    return reg


def _flag_match_quality(n: int, correlation: float, rescue: dict | None, min_correlation: float,
                        record: dict, diag: dict) -> None:
    """Warn about and flag an aperture whose warp the Stokes rescue set, or that matches poorly or weakly."""
    where = f"registration: aperture {n} ({45 * n} deg) matches the reference"
    if rescue is not None:
        _warn(diag, f"{where} poorly (local R^2 = {correlation:.3f}: strong polarization texture, or texture finer "
              "than the Bayer sub-images resolve); its warp was set by the Stokes consistency I0 + I90 = I45 + I135 "
              f"(residual rms {rescue['stokes_rms_before']:.4g} -> {rescue['stokes_rms_after']:.4g})")
        record["stokes_rescued"] = True
    elif not correlation >= min_correlation:
        _warn(diag, f"{where} poorly (local R^2 = {correlation:.3f} < {min_correlation}); its warp is unreliable")
        record["unreliable"] = True
    elif correlation < WEAK_CORRELATION:
        _warn(diag, f"{where} weakly (local R^2 = {correlation:.3f} < {WEAK_CORRELATION}): strong polarization "
              "texture can put its warp pixels off, and the Stokes-consistency rescue did not lower the Stokes "
              "residual; check the result or use --true-warps")
        record["weak_match"] = True


def _retry_wider_windows(reg: StackRegistration, raw: torch.Tensor, lum: torch.Tensor, valid: torch.Tensor,
                         active: list[int], model: str, parameters: RegistrationParameters,
                         diag: dict) -> StackRegistration:
    """When some warp of ``reg`` is implausible, register again with windows of ``parameters.retry_window_radius``
    and keep that result if all its warps are plausible and its registered binomial images are more
    Stokes-consistent (``diag["wide_window_retry"]`` records the comparison)."""
    radius = parameters.retry_window_radius
    rejected = implausible_apertures(reg, active, parameters)
    if not rejected or len(active) != 3 or radius in (0, parameters.window_radius):
        return reg
    retry_diag: dict = {"warnings": [], "luminance": diag["luminance"]}
    wide = _register_apertures(raw, lum, valid, active, model, parameters.replace(window_radius=radius), retry_diag)

    def residual(result):
        return stokes_residual_rms(lum[0], lum[active], torch.as_tensor(result.params), ref_valid=valid[0],
                                   moving_valid=valid[active], model=model)

    before, after = residual(reg), residual(wide)
    kept = (not implausible_apertures(wide, active, parameters) and all(np.isfinite(v) for v in (before, after))
            and after < before)
    diag["wide_window_retry"] = {"window_radius": radius, "implausible_apertures": rejected,
                                 "stokes_residual_rms": {"first": before, "retry": after}, "kept": kept}
    if not kept:
        return reg
    log.info("registration: implausible warp for apertures %s; the retry with %d px windows is plausible and more "
             "Stokes-consistent (%.4g -> %.4g): kept", rejected, radius, before, after)
    diag["luminance"] = retry_diag["luminance"]
    if "luminance_stokes_residual_rms" in retry_diag:
        diag["luminance_stokes_residual_rms"] = retry_diag["luminance_stokes_residual_rms"]
    diag["warnings"].extend(retry_diag["warnings"])
    return wide


def _accept_warps(reg: StackRegistration, active: list[int], parameters: RegistrationParameters,
                  aperture: np.ndarray, per_ap: list[dict], diag: dict) -> None:
    """Write the estimated aperture warps ``H_n = R^-1 G_n R`` into ``aperture`` ``(4, 3, 3)``; degenerate
    and implausible ones (beyond the parameters' rotation and scale limits) keep the identity."""
    joint = reg.info.get("stokes_joint", {})
    rescued = set(joint.get("images", [])) if joint.get("kept") else set()
    max_rotation, max_scale_error = parameters.max_rotation_deg, parameters.max_scale_error
    for j, n in enumerate(active):
        hn = aperture_warp(reg.matrices[j])
        if hn is None:
            _warn(diag, f"registration: aperture {n} gave a degenerate warp; using the identity for it")
            per_ap[n]["fallback"] = "identity: degenerate estimate"
            continue
        if not is_plausible(hn, parameters):
            rotation_deg, scale = rotation_and_scale(hn)
            _warn(diag, f"registration: aperture {n} ({45 * n} deg) matched at a rotation of {rotation_deg:.1f} deg "
                  f"and scale {scale:.3f}, implausible for a camera array (limits {max_rotation} deg, "
                  f"1 +- {max_scale_error}); using the identity for it. The analyzer images probably differ by "
                  "design (polarization texture on flat intensity) or alias texture finer than the Bayer sub-images "
                  "resolve (a Siemens star rendered small): use --true-warps or calibrated warps, or a larger frame")
            per_ap[n]["fallback"] = "identity: implausible warp"
            per_ap[n]["rejected"] = {"rotation_deg": rotation_deg, "scale": scale}
            continue
        aperture[n] = hn
        per_ap[n]["correlation"] = float(reg.correlation[j])
        per_ap[n]["params_raw_px"] = [float(v) for v in reg.params[j]]
        _flag_match_quality(n, float(reg.correlation[j]), joint if j in rescued else None,
                            parameters.min_correlation, per_ap[n], diag)


# -- public API -----------------------------------------------------------------------------------------
def identity_fallbacks(apertures: list[dict]) -> dict[int, str]:
    """``{aperture: why}`` for the apertures of ``diagnostics["apertures"]`` whose warp fell back to the identity."""
    return {a["aperture"]: a["fallback"] for a in apertures if a.get("fallback") not in ("none", "reference")}


def estimate_lr_homographies(lr_images, *, hr_shape, saturated=None, parameters: RegistrationParameters | None = None,
                             device="cpu") -> RegistrationResult:
    """Estimate the 16 HR reference -> sub-image homographies from the 16 Bayer sub-images.

    Parameters
    ----------
    lr_images
        ``(16, h, w)`` float (numpy or torch), the Bayer sub-images ``m = 4n + q`` (n: aperture,
        polarizer ``45 n`` deg; q over R, G1, G2, B), ``h = H/2`` of the raw ``H x W``.
    hr_shape
        ``(2H, 2W) = (4h, 4w)``: the HR reference grid.
    saturated
        optional ``(16, h, w)`` bool, True at clipped pixels (left out of the criterion).
    parameters
        the options (:class:`~capssim.reconstruct.registration.parameters.RegistrationParameters`;
        None: its defaults, the ``local-correlation`` mode); a named mode's are
        :func:`~capssim.reconstruct.registration.parameters.registration_parameters` ``(name)``.
    device
        torch device for the computation (``cpu``, ``cuda``, a ``torch.device``).

    Returns
    -------
    RegistrationResult
        ``lr_homographies`` ``(16, 3, 3)`` (HR reference (x=col, y=row) -> sub-image pixel),
        ``aperture_homographies`` ``(4, 3, 3)``, ``diagnostics``.
    """
    t_start = time.perf_counter()
    if parameters is None:
        parameters = RegistrationParameters()
    if not isinstance(parameters, RegistrationParameters):
        raise InputError("parameters", type(parameters).__name__, "a RegistrationParameters (or None: the defaults)")
    parameters.validate()
    dev = torch.device(device)
    x, sat = _checked_inputs(lr_images, hr_shape, saturated, dev)
    x = x.to(torch.float64)
    luminance = parameters.luminance
    diag: dict = {"method": f"{luminance} luminance; phase correlation + pyramid local correlation "
                            "+ Stokes consistency (cubic spline, L-BFGS)",
                  "luminance": "binomial" if luminance == "auto" else luminance, "model_requested": parameters.model,
                  "window_radius": parameters.window_radius, "stokes_weight": parameters.stokes_weight,
                  "device": str(dev), "warnings": []}

    raw = mosaic_from_sub_images(x)
    lum = LUMINANCE_METHODS["binomial" if luminance == "auto" else luminance](raw)
    if parameters.presmooth_sigma > 0:
        lum = gaussian_blur(lum, parameters.presmooth_sigma, padding="replicate")
    valid = usable_pixels(mosaic_from_sub_images(sat.to(torch.float64)))
    diag["raw_shape"] = list(raw.shape[1:])
    model = diag["model"] = _usable_model(parameters.model, raw.shape[1:], diag)
    active, per_ap = _active_apertures(lum, valid, model, diag)
    aperture = np.tile(np.eye(3), (N_APERTURES, 1, 1))
    if active:
        reg = _register_apertures(raw, lum, valid, active, model, parameters, diag)
        reg = _retry_wider_windows(reg, raw, lum, valid, active, model, parameters, diag)
        _accept_warps(reg, active, parameters, aperture, per_ap, diag)
        if len(active) == 3:
            aperture = check_polarization_only(reg, lum, valid, aperture, model, parameters, diag, warn=_warn,
                                               fallbacks=frozenset(identity_fallbacks(per_ap)))
        diag["engine"] = reg.info
    diag["apertures"] = per_ap
    diag["time_s"] = time.perf_counter() - t_start
    return RegistrationResult(lr_homographies=lr_from_aperture(aperture), aperture_homographies=aperture,
                              diagnostics=diag)
