"""Consistency check of a 12-channel polarization ground truth (four analyzer images).

A ground truth taken as four sequential shots through a rotating polarizer (the Qiu et al.
2021 scenes in ``shared/data/gt``) is not a single physical scene: the image wanders as the
polarizer turns (a slightly wedged or tilted filter deviates the beam), the light drifts
between shots, highlights clip. A CAPS capture simulated from it inherits that: its "true"
warps (the ones the simulator applied) are not where the analyzer images' content lines up,
so a registration error measured against them includes the ground truth's own offsets, and
``I0 + I90 = I45 + I135`` (Malus's law, which the ``stokes-subspace`` registration relies on)
does not hold exactly. This module measures both, so a benchmark can say how much of an
error is the data's.

:func:`check_ground_truth` reports, for the luminance ``(R + G + B) / 3`` of each analyzer
image:

* **alignment** of the 45/90/135 deg images to the 0 deg one (similarity model, the
  registration engine of :mod:`capssim.reconstruct.registration.engine` at full resolution, pixels
  clipped in any image left out): shift at the image centre (px, ``x`` = column), rotation
  (deg), scale (parts per million) and the mean displacement over the frame (px). The same
  is repeated on the weakly polarized pixels only (block DoLP < ``dolp_max``) as a
  cross-check: where the two disagree, polarization texture biases the estimate (skipped below
  :data:`MIN_WEAKLY_POLARIZED_SHARE` of the frame: on qiu-cellphonecases 256, 6 % of weakly
  polarized pixels let it drift 13-36 px). The estimate
  assumes the four images share their structure up to a local gain; strong polarization
  texture biases it (a consistent synthetic scene with smooth random DoLP up to 0.6 and random
  AoP, 96 px: up to 0.13 px apparent offset, ``tests/test_eval_gt_check.py``; qiu-cellphonecases,
  photoelastic plastics: 2 px), so the verdict rests on the Stokes residual and the offsets
  explain it. **alignment check**: the luminance Stokes residual before and after resampling
  with the estimate; a true offset leaves a residual at edges that correct alignment lowers, a
  misled estimate raises it and is reported unreliable.
* **Stokes residual** ``I0 + I90 - I45 - I135`` per colour: RMS in percent of the mean
  ``S0``, and the share of it that is low-frequency (31 px box mean: illumination drift);
  the per-image gains ``g`` that best satisfy ``I0 + g90 I90 = g45 I45 + g135 I135 + c``.
* **clipping**: share of pixels at the top code in each image.

:func:`aligned_ground_truth` resamples the 45/90/135 deg images onto the 0 deg one with the
estimated alignment (interpolating cubic B-spline) to build a content-consistent ground
truth (``capssim gt-check GT --write-aligned OUT.tiff``).

All computations are vectorized torch (no per-pixel loop); ``device`` may be ``cuda``.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import torch
import torch.nn.functional as F

from capssim.camera.homography import rotation_and_scale
from capssim.conventions import POLARIZER_ANGLES_DEG
from capssim.errors import InputError
from capssim.reconstruct.registration.engine import register_stack
from capssim.reconstruct.registration.motion import spline_coefficients, spline_sample

log = logging.getLogger(__name__)

#: threshold of the one-line verdict: RMS Stokes residual in % of the mean S0, above the floor
#: that quantization of the four images leaves (``2 q / sqrt(12)``, ``q`` one code: 0.45 % of an
#: S0 of 0.5 for 8-bit images)
CONSISTENT_STOKES_PERCENT = 0.5

#: smallest share of weakly polarized pixels for the cross-check alignment (fewer let it drift)
MIN_WEAKLY_POLARIZED_SHARE = 0.2


def _check_gt(gt) -> np.ndarray:
    arr = np.asarray(gt)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.floating):
        raise InputError("gt", f"dtype {arr.dtype}", "a float array on [0, 1] (capssim.files.imageio.read_gt_scene)")
    if arr.ndim != 3 or arr.shape[0] != 12:
        raise InputError("gt", f"shape {arr.shape}", "shape (12, H, W), channels c = 3 p + k")
    if min(arr.shape[1:]) < 32:
        raise InputError("gt", f"size {arr.shape[1]}x{arr.shape[2]}", "at least 32x32 pixels")
    if not np.all(np.isfinite(arr)):
        raise InputError("gt", f"{int(np.sum(~np.isfinite(arr)))} NaN/inf values", "finite values")
    return arr


def _box_mean(x: torch.Tensor, radius: int) -> torch.Tensor:
    k = 2 * radius + 1
    return F.avg_pool2d(F.pad(x[:, None], (radius,) * 4, mode="replicate"), k, stride=1)[:, 0]


def _describe(matrices: np.ndarray, shape) -> list[dict]:
    """Similarity matrices (reference pixel -> moving pixel) -> shift / rotation / scale rows."""
    h, w = shape
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    ys, xs = np.meshgrid(np.linspace(0, h - 1, 9), np.linspace(0, w - 1, 9), indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    rows = []
    for g in matrices:
        c = g @ centre
        rotation_deg, scale = rotation_and_scale(g)
        q = g @ pts
        disp = q[:2] / q[2:] - pts[:2]
        rows.append({"shift_x_px": float(c[0] / c[2] - centre[0]), "shift_y_px": float(c[1] / c[2] - centre[1]),
                     "rotation_deg": rotation_deg, "scale_ppm": (scale - 1.0) * 1e6,
                     "mean_displacement_px": float(np.hypot(disp[0], disp[1]).mean())})
    return rows


def _moving_coords(matrices, shape, device) -> torch.Tensor:
    """``(3, H, W, 2)`` moving-image ``(x, y)`` of every reference pixel under ``matrices`` ``(3, 3, 3)``."""
    h, w = shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64, device=device),
                            torch.arange(w, dtype=torch.float64, device=device), indexing="ij")
    pts = torch.stack([xs.flatten(), ys.flatten(), torch.ones(h * w, dtype=torch.float64, device=device)])
    q = torch.as_tensor(np.asarray(matrices), dtype=torch.float64, device=device) @ pts     # (3, 3, HW)
    return (q[:, :2] / q[:, 2:]).transpose(1, 2).reshape(len(q), h, w, 2)


def _alignment_check(lum: torch.Tensor, valid: torch.Tensor, matrices: np.ndarray, *, margin: int = 8) -> dict:
    """RMS luminance Stokes residual (% of mean S0) before and after resampling the 45/90/135 deg
    images with the estimated alignment. A true offset between the shots always leaves a
    residual at edges, so aligning correctly lowers it; an estimate misled by polarization
    texture raises it (``reliable`` False beyond 5 % + 0.01 % of S0: resampling alone changes it
    slightly)."""
    h, w = lum.shape[1:]
    xy = _moving_coords(matrices, (h, w), lum.device)
    inside = ((xy[..., 0] >= 0) & (xy[..., 0] <= w - 1) & (xy[..., 1] >= 0) & (xy[..., 1] <= h - 1)).all(0)
    warped = spline_sample(spline_coefficients(lum[1:]), xy)
    m = valid.bool() & inside
    m[:margin], m[-margin:], m[:, :margin], m[:, -margin:] = False, False, False, False
    s0 = float((lum.sum(0) / 2)[m].mean()) if bool(m.any()) else 1.0
    before = float((lum[0] + lum[2] - lum[1] - lum[3])[m].square().mean().sqrt())
    after = float((lum[0] + warped[1] - warped[0] - warped[2])[m].square().mean().sqrt())
    before_pct, after_pct = 100.0 * before / max(s0, 1e-12), 100.0 * after / max(s0, 1e-12)
    return {"stokes_rms_percent_unaligned": before_pct, "stokes_rms_percent_aligned": after_pct,
            "reliable": bool(after_pct <= 1.05 * before_pct + 0.01)}


def _alignment(lum: torch.Tensor, valid: torch.Tensor, weak: torch.Tensor) -> dict:
    """Similarity alignment of the 45/90/135 deg luminance ``(4, H, W)`` to the 0 deg one, its check, and the
    same on the weakly polarized pixels (``weak`` weights) when there are enough of them."""
    shape, dev = tuple(lum.shape[1:]), lum.device
    result: dict = {}
    reg = register_stack(lum[0], lum[1:], ref_valid=valid, moving_valid=valid.expand(3, -1, -1),
                         model="similarity", stokes_weight=0.0, robust_power=4.0)
    result["alignment"] = _describe(reg.matrices, shape)
    result["alignment_matrices"] = reg.matrices.tolist()
    result["alignment_check"] = _alignment_check(lum, valid, reg.matrices)
    if float(weak.mean()) >= MIN_WEAKLY_POLARIZED_SHARE:
        reg_weak = register_stack(lum[0], lum[1:], ref_valid=weak, moving_valid=valid.expand(3, -1, -1),
                                  model="similarity", stokes_weight=0.0, robust_power=4.0, rescue_below=0.0, initial=torch.as_tensor(
                                      reg.params, dtype=torch.float64, device=dev))
        result["alignment_weakly_polarized"] = _describe(reg_weak.matrices, shape)
    else:
        result["alignment_weakly_polarized"] = None
    return result


def _stokes_consistency(x: torch.Tensor, valid: torch.Tensor, *, bit_depth: int) -> dict:
    """The Stokes residual ``I0 + I90 - I45 - I135`` per colour over the unclipped pixels (``x`` ``(4, 3, H, W)``),
    against the quantization floor of ``bit_depth``, and the analyzer gains that best explain it."""
    dev = x.device
    lum = x.mean(dim=1)
    s0 = lum.sum(0) / 2
    res = x[0] + x[2] - x[1] - x[3]                                     # (3, H, W)
    s0c = x.sum(0) / 2
    m = valid.bool()
    n = max(int(m.sum()), 1)
    stokes = []
    for k in range(3):
        r = res[k][m]
        rms = float(r.square().mean().sqrt())
        low = _box_mean(res[k:k + 1] * valid, 15)[0] / _box_mean(valid[None], 15)[0].clamp_min(1e-9)
        low_rms = float(low[m].square().mean().sqrt())
        mean_s0 = max(float(s0c[k][m].mean()), 1e-12)
        floor = 2.0 / (2 ** bit_depth - 1) / math.sqrt(12.0) if bit_depth > 0 else 0.0
        stokes.append({"colour": "RGB"[k], "rms_percent_of_s0": 100.0 * rms / mean_s0,
                       "quantization_floor_percent": 100.0 * floor / mean_s0,
                       "excess_percent": 100.0 * math.sqrt(max(rms * rms - floor * floor, 0.0)) / mean_s0,
                       "low_frequency_share": low_rms / max(rms, 1e-30)})
    # gains: least squares of I0 = -g90 I90 + g45 I45 + g135 I135 + c over all colours
    a = torch.stack([-lum[2][m], lum[1][m], lum[3][m], torch.ones(n, dtype=torch.float64, device=dev)], 1)
    sol = torch.linalg.lstsq(a, lum[0][m][:, None]).solution[:, 0]
    fit_rms = float((a @ sol - lum[0][m]).square().mean().sqrt())
    return {"per_colour": stokes,
            "gains": {"g45": float(sol[1]), "g90": float(sol[0]), "g135": float(sol[2]), "offset": float(sol[3])},
            "rms_percent_after_gain_fit": 100.0 * fit_rms / max(float(s0[m].mean()), 1e-12)}


def _verdict(result: dict, worst_stokes: float) -> str:
    """One line: consistent or not, the worst Stokes excess, and the offsets (or why their estimate is unreliable)."""
    worst_shift = max(r["mean_displacement_px"] for r in result["alignment"])
    check = result["alignment_check"]
    if check["reliable"]:
        offsets = f"analyzer images offset by up to {worst_shift:.3f} px (mean over the frame)"
    else:
        offsets = (f"alignment estimate unreliable ({worst_shift:.3f} px; it raises the Stokes residual of the "
                   f"luminance from {check['stokes_rms_percent_unaligned']:.2f} to "
                   f"{check['stokes_rms_percent_aligned']:.2f} % of S0: polarization texture misleads it)")
    return (("consistent" if result["consistent"] else "inconsistent")
            + f": Stokes residual I0+I90-I45-I135 up to {worst_stokes:.2f} % of S0 above quantization (threshold "
            f"{CONSISTENT_STOKES_PERCENT} %); " + offsets)


def check_ground_truth(gt, *, dolp_max: float = 0.1, bit_depth: int = 0, device="cpu") -> dict:
    """Measure the inter-image alignment and the Stokes consistency of a ground truth.

    Parameters
    ----------
    gt
        ``(12, H, W)`` float on [0, 1], channels ``c = 3 p + k`` (p: 0/45/90/135 deg, k: RGB).
    dolp_max
        block DoLP (16 px box) below which a pixel counts as weakly polarized for the
        cross-check alignment.
    bit_depth
        bits of the source images (8, 16; 0 for float sources): sets the quantization floor
        of the Stokes residual.
    device
        torch device.

    Returns
    -------
    dict
        ``alignment`` and ``alignment_weakly_polarized`` (one row per 45/90/135 deg image:
        ``shift_x_px``, ``shift_y_px``, ``rotation_deg``, ``scale_ppm``,
        ``mean_displacement_px``), ``stokes`` (per colour ``rms_percent_of_s0``,
        ``low_frequency_share``; ``gains``), ``alignment_check`` (luminance Stokes residual before
        and after the alignment; ``reliable`` when the alignment lowers it), ``clipped_share`` per
        image, ``consistent`` (bool),
        ``verdict`` (one line), ``time_s``.
    """
    if not (0 < dolp_max <= 1):
        raise InputError("dolp_max", dolp_max, "a number in (0, 1]")
    if bit_depth not in (0, 8, 10, 12, 14, 16):
        raise InputError("bit_depth", bit_depth, "0 (float source), 8, 10, 12, 14 or 16")
    t0 = time.perf_counter()
    arr = _check_gt(gt)
    dev = torch.device(device)
    x = torch.as_tensor(arr, dtype=torch.float64, device=dev).reshape(4, 3, *arr.shape[1:])
    top = float(x.max())
    clipped = (x >= top - 1e-6).any(dim=1) if top >= 0.99 else torch.zeros_like(x[:, 0], dtype=torch.bool)
    bad = F.max_pool2d(clipped.any(0)[None, None].double(), 3, stride=1, padding=1)[0, 0] > 0
    valid = (~bad).double()
    lum = x.mean(dim=1)
    s0, s1, s2 = lum.sum(0) / 2, lum[0] - lum[2], lum[1] - lum[3]
    blocks = _box_mean(torch.stack([s0, s1, s2]), 8)
    dolp = torch.hypot(blocks[1], blocks[2]) / blocks[0].clamp_min(1e-6)
    weak = valid * (dolp < dolp_max).double()

    result: dict = {"shape": list(arr.shape[1:]), "angles_deg": list(POLARIZER_ANGLES_DEG[1:]),
                    "clipped_share": [float(v) for v in clipped.double().mean(dim=(1, 2))],
                    "weakly_polarized_share": float(weak.mean())}
    result.update(_alignment(lum, valid, weak))
    result["stokes"] = _stokes_consistency(x, valid, bit_depth=bit_depth)
    worst_stokes = max(c["excess_percent"] for c in result["stokes"]["per_colour"])
    # Malus's law is the test: an offset or a gain drift between the shots always leaves a
    # Stokes residual where there is texture; the alignment estimate explains it (and is itself
    # biased by strong polarization texture, see the module docstring)
    result["consistent"] = bool(worst_stokes < CONSISTENT_STOKES_PERCENT)
    result["verdict"] = _verdict(result, worst_stokes)
    result["time_s"] = time.perf_counter() - t0
    log.info("gt-check: %s (%.1f s)", result["verdict"], result["time_s"])
    return result


def aligned_ground_truth(gt, matrices, *, device="cpu") -> np.ndarray:
    """Resample the 45/90/135 deg images of ``gt`` onto the 0 deg one.

    ``matrices`` ``(3, 3, 3)``: reference pixel -> moving-image pixel (``alignment_matrices`` of
    :func:`check_ground_truth`). Interpolating cubic B-spline; pixels mapped from outside the
    image take the nearest edge value. Returns ``(12, H, W)`` float32 clipped to [0, 1].
    """
    arr = _check_gt(gt)
    g = np.asarray(matrices, dtype=np.float64)
    if g.shape != (3, 3, 3) or not np.all(np.isfinite(g)):
        raise InputError("matrices", f"shape {g.shape}", "three finite 3x3 homographies (45, 90, 135 deg)")
    dev = torch.device(device)
    h, w = arr.shape[1:]
    x = torch.as_tensor(arr, dtype=torch.float64, device=dev)
    coords = _moving_coords(g, (h, w), dev)
    coords = torch.stack([coords[..., 0].clamp(0, w - 1), coords[..., 1].clamp(0, h - 1)], -1)
    out = x.clone()
    for j in range(3):
        xy = coords[j:j + 1]
        sl = slice(3 * (j + 1), 3 * (j + 2))
        out[sl] = spline_sample(spline_coefficients(x[sl]), xy.expand(3, h, w, 2))
    return out.clamp(0.0, 1.0).to(torch.float32).cpu().numpy()
