"""Registration of the four apertures of a CAPS capture (paper section 3.1, "registration").

Estimates, from the 16 Bayer sub-images alone, the homographies ``H_m`` (HR reference
pixel -> sub-image m pixel, ``(x=col, y=row)``) that the reconstruction needs. The Bayer
sub-pixel offsets are known, so only the three aperture warps ``H_1..H_3`` (HR reference
-> aperture-HR) are estimated, against the 0 deg aperture; then ``H_{4n+q} = S_q @ H_n``
(see :mod:`capssim.homography`).

Method (it replaces the paper's feature clustering, Crab-HFP, which the issue allows):

1. **Registration image per aperture** (``luminance=``). The four RGGB sub-images of aperture n
   are put back into its raw mosaic ``(H, W)``.

   - ``binomial``: the mosaic is filtered with the 3x3 binomial kernel
     ``[1 2 1; 2 4 2; 1 2 1] / 16``. On an RGGB mosaic this returns the luminance
     ``(R + 2G + B) / 4`` of locally constant colour at every raw pixel, whatever its Bayer phase:
     no demosaicking, and for grey content the same linear blur in every aperture. At colour
     edges, though, the mosaic's chroma carriers leak into it as a pattern tied to the sensor
     grid, different in each aperture, which biases the warp (the rendered colorchecker's ground
     truth simulated with similarity warps: 0.066 HR px median; made grey: 0.003).
   - ``ri-binomial``: the mosaic is demosaicked by residual
     interpolation (:func:`reconstruct.dofp_common.ri_bayer_demosaic`, Kiku et al. 2016), and its
     luminance ``(R + 2G + B) / 4`` is filtered with the same kernel: ``binomial`` minus the leak
     as the demosaicking estimates it (the colorchecker above: 0.017; rendered colorchecker 512:
     0.076 -> 0.034). It is worse where the demosaicking errs: aliased high-frequency texture
     (a 72-cycle Siemens star at 192 px: max 0.08 -> 0.43) and fine grey fringes.
   - ``auto`` (default): the image whose registered images obey ``I0 + I90 = I45 + I135`` better
     (lower Stokes residual rms) is kept: the one with fewer aperture-specific artifacts. Step 2
     runs on ``binomial``; the ``ri-binomial`` image is judged at those warps (its residual is set
     by the image far more than by small warp differences: within 0.05 % of the residual at its own
     warps on five 256-512 px captures, 13 % on a synthetic scene whose binomial warps were 0.15 px
     off, still the same choice) and, only if it is more consistent there, refined from them on the
     finest level (:data:`AUTO_REFINE_LEVEL`), or registered from scratch when the Stokes rescue set
     some warps. This gives the same warps as registering both images in full (to 1e-4 HR px on the
     ten captures re-measured, README "Registration") in 35-65 % of that time. It picked the better
     or an equal estimate on every capture measured except qiu-cellphonecases 256 (README
     'Registration').
     With fewer than four usable apertures it is ``binomial``.

   Raw pixels with a saturated sample in their 3x3 neighbourhood are masked (for ``ri-binomial``
   a 5x5 or 7x7 mask was worse on qiu-kettle: 0.148 / 0.151 against 0.144 HR px).
2. **Registration** of apertures 1-3 to aperture 0 by :func:`reconstruct.registration_core.register_stack`:
   phase-correlation candidates, then a coarse-to-fine refinement of a local-correlation
   criterion (local gain and offset per window, so polarizer angle and colour do not matter)
   plus the Stokes consistency ``I0 + I90 = I45 + I135`` on the finest levels, with
   cubic-spline interpolation. Apertures that still match poorly restart from more
   phase-correlation peaks, and then from a joint re-run dominated by the Stokes consistency
   (kept if it lowers the Stokes residual by > 10 %; strong polarization texture such as
   photoelastic fringes).

Safeguards: constant / flat images, or frames too small for the model, fall back to the
identity (or a smaller model) with a logged warning and a flag in ``diagnostics``; a poor
final match is flagged ``unreliable``.

Raw coordinates of aperture n relate to its aperture-HR coordinates by
:func:`capssim.homography.raw_matrix`: ``H_n = R^-1 G_n R`` for the estimated raw-to-raw
matrix ``G_n``.
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from capssim.conventions import BAYER_OFFSETS, N_APERTURES, N_LR_IMAGES
from capssim.errors import CapssimError, InputError, UnknownNameError
from capssim.homography import lr_homographies as lr_from_aperture
from capssim.homography import raw_matrix, rotation_and_scale
from capssim.reconstruct.registration_core import MOTION_MODELS, noise_sigma, register_stack, stokes_residual_rms

log = logging.getLogger(__name__)

#: smallest raw side (pixels) for which each model is attempted; smaller frames use a smaller model
MIN_RAW_SIDE = {"translation": 8, "euclidean": 16, "similarity": 16, "affine": 24, "homography": 32}


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


def mosaic_from_sub_images(sub: torch.Tensor) -> torch.Tensor:
    """``(16, h, w)`` Bayer sub-images ``m = 4n + q`` -> ``(4, 2h, 2w)`` RGGB raw mosaics."""
    _, h, w = sub.shape
    raw = sub.new_zeros(N_APERTURES, 2 * h, 2 * w)
    for q, (oy, ox) in enumerate(BAYER_OFFSETS):
        raw[:, oy::2, ox::2] = sub[q::4]
    return raw


def binomial_luminance(raw: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` RGGB mosaics -> ``(B, H, W)`` luminance ``(R + 2G + B) / 4`` (3x3 binomial filter).

    The border is mirrored (row -1 = row 1: the same Bayer parity, so colours stay in place).
    """
    k = torch.tensor([1.0, 2.0, 1.0], dtype=raw.dtype, device=raw.device)
    k = (k[:, None] * k[None, :]) / 16.0
    x = F.pad(raw[:, None], (1, 1, 1, 1), mode="reflect")
    return F.conv2d(x, k[None, None])[:, 0]


def ri_binomial_luminance(raw: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` RGGB mosaics -> ``(B, H, W)``: 3x3 binomial filter of the luminance ``(R + 2G + B) / 4``
    of the residual-interpolation demosaicking
    (:func:`reconstruct.methods.dofp_eari.ri_bayer_demosaic_frames`: ``dofp-eari``'s colour stage, any size).
    """
    from capssim.reconstruct.methods.dofp_eari import ri_bayer_demosaic_frames

    rgb = ri_bayer_demosaic_frames(raw)
    return binomial_luminance((rgb[:, 0] + 2 * rgb[:, 1] + rgb[:, 2]) / 4)


#: registration images of the raw mosaics (``estimate_lr_homographies(luminance=...)``)
LUMINANCE_METHODS = {"ri-binomial": ri_binomial_luminance, "binomial": binomial_luminance}


# -- public API ----------------------------------------------------------------------------------------
def _as_tensor(x, name: str, device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x.detach()
    else:
        arr = np.asarray(x)
        if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            raise InputError(name, f"dtype {arr.dtype}", "a numeric array")
        t = torch.from_numpy(np.ascontiguousarray(arr))
    return t.to(device)


#: named registration modes (``capssim reconstruct --registration NAME``) -> keyword arguments of
#: :func:`estimate_lr_homographies`
REGISTRATION_MODES: dict[str, dict] = {
    "local-correlation": {},
    "binomial-luminance": {"luminance": "binomial"},
    "ri-luminance": {"luminance": "ri-binomial"},
    "stokes-subspace": {"stokes_subspace_std": 0.01, "luminance": "binomial"},
}


#: final local R^2 below which an aperture's estimate gets a warning (not the unreliable flag):
#: right estimates on strongly polarized scenes reach 0.4-0.8, wrong ones 0.3-0.5 (apertures whose
#: warp the Stokes-consistency rescue set get their own warning instead)
WEAK_CORRELATION = 0.6

#: the largest aperture rotation (deg) and relative scale error a camera array plausibly has; the
#: simulator draws at most 0.5 deg and 0.005. A larger estimate is a false match (e.g. a polarizing
#: wheel, whose analyzer images are rotated copies of each other) and falls back to the identity.
MAX_PLAUSIBLE_ROTATION_DEG = 5.0
MAX_PLAUSIBLE_SCALE_ERROR = 0.05
#: ``luminance='auto'``: the pyramid level on which the demosaicked image's refinement (from the
#: binomial warps) starts
AUTO_REFINE_LEVEL = 0


def registration_mode_arguments(name: str) -> dict:
    """Keyword arguments of :func:`estimate_lr_homographies` for a :data:`REGISTRATION_MODES` name."""
    if name not in REGISTRATION_MODES:
        raise UnknownNameError("registration mode", name, list(REGISTRATION_MODES))
    return dict(REGISTRATION_MODES[name])


def estimate_lr_homographies(lr_images, *, hr_shape, saturated=None, model: str = "similarity",
                             device="cpu", window_radius: int = 3, stokes_weight: float = 1.0,
                             stokes_levels: int = 2, max_iterations: int = 60,
                             min_correlation: float = 0.3, robust_power: float = 4.0, robust_levels: int = 2,
                             robust_passes: int = 2, presmooth_sigma: float = 0.0,
                             stokes_subspace_std: float = 0.0,
                             robust_window_radius: int | None = 1,
                             luminance: str = "auto", max_rotation_deg: float = MAX_PLAUSIBLE_ROTATION_DEG,
                             max_scale_error: float = MAX_PLAUSIBLE_SCALE_ERROR) -> RegistrationResult:
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
    model
        motion model of each aperture: ``translation``, ``euclidean``, ``similarity``
        (default; the paper's synthetic protocol), ``affine`` or ``homography``.
    device
        torch device for the computation (``cpu``, ``cuda``, a ``torch.device``).
    window_radius
        radius (pyramid-level pixels) of the local photometric-fit windows.
    robust_power, robust_levels, robust_passes, robust_window_radius
        IRLS on the ``robust_levels`` finest levels: ``robust_passes`` passes with windows weighted
        by their local R^2 to the power ``robust_power`` and of radius ``robust_window_radius``
        (None: ``window_radius``). The default 1 (3 x 3 windows) halves the bias from polarization
        texture (fewer windows straddle differently polarized structures; README 'Registration').
    stokes_weight, stokes_levels
        weight of the Stokes-consistency term and on how many of the finest pyramid levels it
        is used (0 turns it off: pairwise local correlation only).
    max_iterations
        L-BFGS iterations per pyramid level.
    min_correlation
        below this final local R^2 an aperture is flagged unreliable (warning + flag).
    stokes_subspace_std
        > 0: end with the Stokes-subspace refinement (``registration_core`` docstring), moving
        only along directions the Stokes residual fixes to within this many raw pixels
        (:data:`REGISTRATION_MODES` ``stokes-subspace`` uses 0.01). For Stokes-consistent data whose
        polarization texture biases the default; it makes qiu-kettle and rendered scenes with sharp
        colour edges worse (README 'Registration').

    luminance
        the registration image of each aperture: ``auto`` (default), or one of
        :data:`LUMINANCE_METHODS`, ``binomial`` or ``ri-binomial`` (module docstring, step 1).
    max_rotation_deg, max_scale_error
        an aperture warp rotated by more than this (degrees) or scaled by more than ``1 +-
        max_scale_error`` is not a camera array's: it falls back to the identity with a warning
        (``fallback`` ``identity: implausible warp``). Scenes whose analyzer images are rotated
        copies of each other (``aop-wheel``) match that way.

    Returns
    -------
    RegistrationResult
        ``lr_homographies`` ``(16, 3, 3)`` (HR reference (x=col, y=row) -> sub-image pixel),
        ``aperture_homographies`` ``(4, 3, 3)``, ``diagnostics``.
    """
    t_start = time.perf_counter()
    if model not in MOTION_MODELS:
        raise UnknownNameError("registration model", model, list(MOTION_MODELS))
    if luminance not in LUMINANCE_METHODS and luminance != "auto":
        raise UnknownNameError("luminance", luminance, [*LUMINANCE_METHODS, "auto"])
    dev = torch.device(device)
    x = _as_tensor(lr_images, "lr_images", dev)
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
    if saturated is not None:
        sat = _as_tensor(saturated, "saturated", dev)
        if tuple(sat.shape) != tuple(x.shape):
            raise InputError("saturated", f"shape {tuple(sat.shape)}", f"shape {tuple(x.shape)} like lr_images")
        sat = sat.to(torch.bool)
    else:
        sat = torch.zeros(x.shape, dtype=torch.bool, device=dev)
    if not (stokes_weight >= 0 and np.isfinite(stokes_weight)):
        raise InputError("stokes_weight", stokes_weight, "a finite number >= 0")
    if not (stokes_subspace_std >= 0 and np.isfinite(stokes_subspace_std)):
        raise InputError("stokes_subspace_std", stokes_subspace_std, "a finite number >= 0 (0: off)")
    if not (max_rotation_deg > 0 and np.isfinite(max_rotation_deg)):
        raise InputError("max_rotation_deg", max_rotation_deg, "a finite angle > 0 in degrees")
    if not (0 < max_scale_error < 1):
        raise InputError("max_scale_error", max_scale_error, "a relative scale error in (0, 1)")
    dtype = torch.float64
    x = x.to(dtype)

    diag: dict = {"method": f"{luminance} luminance; phase correlation + pyramid local correlation "
                            "+ Stokes consistency (cubic spline, L-BFGS)",
                  "luminance": "binomial" if luminance == "auto" else luminance, "model_requested": model,
                  "window_radius": window_radius, "stokes_weight": stokes_weight, "device": str(dev), "warnings": []}

    def warn(msg):
        log.warning(msg)
        diag["warnings"].append(msg)

    raw = mosaic_from_sub_images(x)
    lum = LUMINANCE_METHODS["binomial" if luminance == "auto" else luminance](raw)
    if presmooth_sigma > 0:
        from capssim.reconstruct.registration_core import gaussian_blur

        lum = gaussian_blur(lum, presmooth_sigma)
    raw_sat = mosaic_from_sub_images(sat.to(dtype))
    valid = (F.max_pool2d(raw_sat[:, None], 3, stride=1, padding=1)[:, 0] <= 0).to(dtype)
    rh, rw = raw.shape[1:]
    diag["raw_shape"] = [rh, rw]

    # the largest model (not larger than requested) that the frame size supports
    order = ["translation", "euclidean", "similarity", "affine", "homography"]
    used = None
    for cand in reversed(order[: order.index(model) + 1]):
        if cand == "euclidean" and model != "euclidean":
            continue
        if min(rh, rw) >= MIN_RAW_SIDE[cand]:
            used = cand
            break
    if used != model:
        warn(f"registration: raw frames of {rh}x{rw} px are too small for the {model!r} model; "
             + (f"using {used!r}" if used else "using the identity"))
    diag["model"] = used

    sigma = noise_sigma(lum)
    spread = lum.flatten(1).std(dim=1)
    diag["noise_sigma"] = [float(v) for v in sigma]
    diag["image_std"] = [float(v) for v in spread]
    flat = (spread <= 1e-6) | (spread <= 0.5 * sigma) | (valid.flatten(1).mean(1) < 0.05)
    per_ap = [{"aperture": n, "fallback": "none"} for n in range(N_APERTURES)]
    per_ap[0]["fallback"] = "reference"
    active = [n for n in range(1, N_APERTURES)]
    if used is None:
        for n in active:
            per_ap[n]["fallback"] = "identity: frame too small"
        active = []
    elif bool(flat[0]):
        warn("registration: the reference (0 deg) image is flat, constant or saturated; "
             "using the identity for every aperture")
        for n in active:
            per_ap[n]["fallback"] = "identity: flat reference image"
        active = []
    else:
        for n in list(active):
            if bool(flat[n]):
                warn(f"registration: aperture {n} ({45 * n} deg) image is flat, constant or saturated; "
                     "using the identity for it")
                per_ap[n]["fallback"] = "identity: flat image"
                active.remove(n)

    aperture = np.tile(np.eye(3), (N_APERTURES, 1, 1))
    if active:
        stokes = stokes_weight if len(active) == 3 else 0.0
        if stokes_weight > 0 and stokes == 0.0:
            warn("registration: the Stokes-consistency term needs all four apertures; using local correlation only")
        if stokes_subspace_std > 0 and len(active) != 3:
            warn("registration: the Stokes-subspace refinement needs all four apertures; skipped")
        def register(image, **kwargs):
            return register_stack(image[0], image[active], ref_valid=valid[0], moving_valid=valid[active], model=used,
                                  window_radius=window_radius, stokes_weight=stokes, stokes_levels=stokes_levels,
                                  max_iterations=max_iterations, robust_power=robust_power,
                                  robust_levels=robust_levels, robust_passes=robust_passes,
                                  stokes_subspace_std=stokes_subspace_std, robust_window_radius=robust_window_radius,
                                  **kwargs)

        reg = register(lum)
        if luminance == "auto" and len(active) == 3:
            # keep the registration image whose registered images obey I0 + I90 = I45 + I135 best; the
            # residual is set by the image far more than by the small warp differences, so the
            # demosaicked image is judged at the binomial warps first and refined from them only if it wins
            ri_image = ri_binomial_luminance(raw)
            rms = {"binomial": reg.info.get("stokes_residual_rms"),
                   "ri-binomial at the binomial warps": stokes_residual_rms(
                       ri_image[0], ri_image[active], reg.params, ref_valid=valid[0], moving_valid=valid[active],
                       model=used)}
            diag["luminance_stokes_residual_rms"] = rms
            if all(v is not None and np.isfinite(v) for v in rms.values()) and \
                    rms["ri-binomial at the binomial warps"] < rms["binomial"]:
                # warps set by the Stokes-consistency rescue would drift under a local-correlation
                # refinement: then the demosaicked image is registered from scratch
                rescued = reg.info.get("stokes_joint", {}).get("kept", False)
                alt = register(ri_image) if rescued else \
                    register(ri_image, initial=torch.as_tensor(reg.params), start_level=AUTO_REFINE_LEVEL)
                rms["ri-binomial"] = alt.info.get("stokes_residual_rms")
                if rms["ri-binomial"] is not None and np.isfinite(rms["ri-binomial"]) and \
                        rms["ri-binomial"] < rms["binomial"]:
                    reg = alt
                    diag["luminance"] = "ri-binomial"
        rmat = raw_matrix()
        rinv = np.linalg.inv(rmat)
        joint = reg.info.get("stokes_joint", {})
        rescued = set(joint.get("images", [])) if joint.get("kept") else set()
        for j, n in enumerate(active):
            g = reg.matrices[j]
            hn = rinv @ g @ rmat
            if not np.all(np.isfinite(hn)) or abs(np.linalg.det(hn[:2, :2])) < 1e-6:
                warn(f"registration: aperture {n} gave a degenerate warp; using the identity for it")
                per_ap[n]["fallback"] = "identity: degenerate estimate"
                continue
            hn = hn / hn[2, 2]
            rotation_deg, scale = rotation_and_scale(hn)
            if abs(rotation_deg) > max_rotation_deg or abs(scale - 1.0) > max_scale_error:
                warn(f"registration: aperture {n} ({45 * n} deg) matched at a rotation of {rotation_deg:.1f} deg and "
                     f"scale {scale:.3f}, implausible for a camera array (limits {max_rotation_deg} deg, "
                     f"1 +- {max_scale_error}); using the identity for it. The analyzer images probably differ by "
                     "design (polarization texture on flat intensity): use --true-warps or calibrated warps")
                per_ap[n]["fallback"] = "identity: implausible warp"
                per_ap[n]["rejected"] = {"rotation_deg": rotation_deg, "scale": scale}
                continue
            aperture[n] = hn
            per_ap[n]["correlation"] = float(reg.correlation[j])
            per_ap[n]["params_raw_px"] = [float(v) for v in reg.params[j]]
            if j in rescued:
                warn(f"registration: aperture {n} ({45 * n} deg) matches the reference poorly (local R^2 = "
                     f"{float(reg.correlation[j]):.3f}: strong polarization texture); its warp was set by the Stokes "
                     f"consistency I0 + I90 = I45 + I135 (residual rms {joint['stokes_rms_before']:.4g} -> "
                     f"{joint['stokes_rms_after']:.4g})")
                per_ap[n]["stokes_rescued"] = True
            elif not float(reg.correlation[j]) >= min_correlation:
                warn(f"registration: aperture {n} ({45 * n} deg) matches the reference poorly (local R^2 = "
                     f"{float(reg.correlation[j]):.3f} < {min_correlation}); its warp is unreliable")
                per_ap[n]["unreliable"] = True
            elif float(reg.correlation[j]) < WEAK_CORRELATION:
                warn(f"registration: aperture {n} ({45 * n} deg) matches the reference weakly (local R^2 = "
                     f"{float(reg.correlation[j]):.3f} < {WEAK_CORRELATION}): strong polarization texture can put "
                     "its warp pixels off, and the Stokes-consistency rescue did not lower the Stokes residual; "
                     "check the result or use --true-warps")
                per_ap[n]["weak_match"] = True
        diag["engine"] = reg.info
    diag["apertures"] = per_ap
    diag["time_s"] = time.perf_counter() - t_start
    return RegistrationResult(lr_homographies=lr_from_aperture(aperture), aperture_homographies=aperture,
                              diagnostics=diag)


# -- benchmark ------------------------------------------------------------------------------------------
def content_lr_homographies(capture, alignment_matrices) -> np.ndarray:
    """``(16, 3, 3)`` *content* warps of a capture simulated from a real ground truth.

    ``alignment_matrices``: the three ``(3, 3)`` matrices of ``capssim gt-check --json``
    (``alignment_matrices``: where the 45/90/135 deg ground-truth images' content lies relative to the
    0 deg image). Aperture n's content warp is its stored warp composed with that offset.
    """
    from capssim.homography import lr_homographies as lr_of

    g = np.asarray(alignment_matrices, dtype=np.float64)
    if g.shape != (N_APERTURES - 1, 3, 3) or not np.all(np.isfinite(g)):
        raise InputError("alignment_matrices", f"shape {g.shape}", "three finite 3x3 matrices from gt-check --json")
    aperture = capture.aperture_homographies().copy()
    for n in range(1, N_APERTURES):
        aperture[n] = aperture[n] @ g[n - 1]
    return lr_of(aperture)


def bench(capture_paths, *, stokes_weight: float = 1.0, stokes_subspace_std: float = 0.0,
          device="cpu", luminance: str = "auto", content_alignment=None) -> list[dict]:
    """Registration error (HR px, :func:`capssim.homography.registration_error_hr_px`) and time per capture.

    Returns one row per capture: median / max error over the 16 images, the mean error per
    aperture, the wall time. Captures need true homographies (simulated or rendered).
    ``content_alignment``: a ``capssim gt-check --json`` record (path or dict) of the ground truth the
    captures were simulated from; rows then also give the error against the content warps
    (:func:`content_lr_homographies`).
    """
    import json
    from pathlib import Path

    from capssim.capture import read_capture
    from capssim.homography import registration_error_hr_px

    matrices = None
    if content_alignment is not None:
        record = content_alignment
        if not isinstance(record, dict):
            try:
                record = json.loads(Path(record).read_text())
            except (OSError, ValueError) as exc:
                raise InputError("content_alignment", str(content_alignment),
                                 "a readable JSON file written by capssim gt-check --json") from exc
        if "alignment_matrices" not in record:
            raise InputError("content_alignment", "a record without 'alignment_matrices'",
                             "the JSON of capssim gt-check --json")
        matrices = record["alignment_matrices"]

    def check_record_matches(cap, path) -> None:
        """The gt-check record must describe this capture's ground truth: same size, same source."""
        shape = record.get("shape")
        if shape is not None and tuple(shape) != tuple(cap.hr_shape):
            raise InputError("content_alignment", f"a gt-check record of a {shape[0]}x{shape[1]} ground truth",
                             f"one of the {cap.hr_shape[0]}x{cap.hr_shape[1]} ground truth capture {path} was "
                             "simulated from", "Run capssim gt-check with the capture's --crop.")
        source = cap.meta.get("source") or {}
        if source.get("renderer"):
            raise InputError("content_alignment", f"a gt-check record for the rendered capture {path}",
                             "captures simulated by capssim simulate --gt from a real ground truth",
                             "Leave it out: a rendered capture's stored warps are its content warps.")
        gt, crop = record.get("gt"), record.get("crop")
        if gt is not None and source.get("path") and Path(gt).name != Path(source["path"]).name:
            raise InputError("content_alignment", f"a gt-check record of {gt}",
                             f"one of {source['path']}, the ground truth of {path}",
                             "Run capssim gt-check on the capture's ground truth.")
        if gt is not None and source.get("path") and crop != source.get("crop"):
            raise InputError("content_alignment", f"a gt-check record with --crop {crop}",
                             f"--crop {source.get('crop')}, the crop capture {path} was simulated with")

    # torch.optim imports torch._dynamo on first use (about 2 s, once per process): not the first row's cost
    torch.optim.LBFGS([torch.zeros(1, requires_grad=True)])
    captures = [read_capture(path, load_gt=False) for path in capture_paths]
    if matrices is not None:
        for path, cap in zip(capture_paths, captures):
            check_record_matches(cap, path)
    rows = []
    for path, cap in zip(capture_paths, captures):
        images, saturated = cap.lr_images()
        t0 = time.perf_counter()
        res = estimate_lr_homographies(images.astype(np.float32), hr_shape=cap.hr_shape, saturated=saturated,
                                       stokes_weight=stokes_weight, stokes_subspace_std=stokes_subspace_std,
                                       device=device, luminance=luminance)
        elapsed = time.perf_counter() - t0
        err = registration_error_hr_px(res.lr_homographies, cap.true_lr_homographies(), cap.hr_shape)
        row = {"capture": str(path), "median_hr_px": float(np.median(err)), "max_hr_px": float(err.max()),
               "per_aperture_hr_px": [float(v) for v in err.reshape(N_APERTURES, 4).mean(1)], "time_s": elapsed}
        if matrices is not None:
            content = content_lr_homographies(cap, matrices)
            err_c = registration_error_hr_px(res.lr_homographies, content, cap.hr_shape)
            gap = registration_error_hr_px(content, cap.true_lr_homographies(), cap.hr_shape)
            row.update({"content_median_hr_px": float(np.median(err_c)), "content_max_hr_px": float(err_c.max()),
                        "content_vs_true_median_hr_px": float(np.median(gap))})
        rows.append(row)
    return rows


def _main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m reconstruct.registration",
                                 description="Registration benchmark: error vs true warps and time per capture.")
    ap.add_argument("--bench", nargs="+", metavar="CAPTURE", required=True, help="capture folders")
    ap.add_argument("--stokes-weight", type=float, default=1.0)
    ap.add_argument("--mode", default="local-correlation", choices=list(REGISTRATION_MODES),
                    help="registration mode (binomial-luminance / ri-luminance: one registration image, "
                         "faster; stokes-subspace: Stokes-consistent data with polarization texture)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--content-alignment", metavar="GT_CHECK_JSON",
                    help="capssim gt-check --json record of the ground truth the captures were simulated from: "
                         "also report the error against the content warps")
    args = ap.parse_args(argv)
    try:
        rows = bench(args.bench, stokes_weight=args.stokes_weight, device=args.device,
                     content_alignment=args.content_alignment, **registration_mode_arguments(args.mode))
    except CapssimError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{'capture':<40} {'median':>8} {'max':>8} {'ap0':>7} {'ap1':>7} {'ap2':>7} {'ap3':>7} {'time s':>7}")
    for r in rows:
        a = r["per_aperture_hr_px"]
        print(f"{r['capture']:<40} {r['median_hr_px']:8.4f} {r['max_hr_px']:8.4f} "
              + " ".join(f"{v:7.4f}" for v in a) + f" {r['time_s']:7.2f}")
        if "content_median_hr_px" in r:
            print(f"{'  against the content warps':<40} {r['content_median_hr_px']:8.4f} {r['content_max_hr_px']:8.4f}"
                  f"   (content vs stored warps: {r['content_vs_true_median_hr_px']:.4f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
