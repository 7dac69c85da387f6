"""Full-reference metrics of a 12-channel estimate against its ground truth.

One entry point, :func:`score`, under three conventions (docs: guides/scoring.md, "Metrics"):

``capssim`` (default)
    * border crop of 8 HR pixels on every side (simulated apertures 1-3 replicate the
      ground-truth border over ~2 HR px, plus the PSF support and block-matching margins);
    * PSNR and SSIM of each of the 12 intensity channels on [0, 1] (``data_range = 1``),
      and their means; CPSNR (pooled MSE over R, G, B) per polarizer angle;
    * Stokes per colour with the project's convention ``S0 = (I0+I45+I90+I135)/2`` in
      [0, 2], ``S1 = I0 - I90`` and ``S2 = I45 - I135`` in [-1, 1]; S0/S1/S2 PSNR pooled
      over R, G, B with ``data_range = 2`` (identical to scoring ``S0/2`` and ``(S+1)/2``
      with peak 1);
    * DoLP per colour ``sqrt(S1^2+S2^2)/S0`` clipped to [0, 1], 0 where ``S0 <= min_s0``;
      DoLP PSNR pooled over R, G, B (``data_range = 1``); DoLP SSIM = mean of the three
      per-colour SSIMs;
    * AoP per colour ``0.5 atan2(S2, S1)`` in [0, 180) deg; wrap-aware error in
      [-90, 90) deg; RMSE and MAE pooled over R, G, B at the pixels where the *ground
      truth* has ``S0 > min_s0`` (default 0.02, i.e. a mean intensity of 1 % of full
      scale) and ``DoLP > min_dolp`` (default 0.05). The mask depends on the ground truth
      only, so an estimate cannot shrink it. ``aop_psnr`` = 20 log10(180 / RMSE).
    * ``*_gt_peak`` (every convention): each intensity and Stokes PSNR/SSIM again with the data
      range times the GT's peak ``P`` (its largest scored value), i.e. the scene exposed to full
      scale; they rank methods on dark scenes, where the fixed-peak ones cap (notes/scoring.md).

``tokyotech`` (Morimatsu et al. 2020, EARI; their published MATLAB evaluation)
    * border crop of 15 pixels with their indexing (rows ``15..H-15`` 1-based, i.e.
      ``14`` rows removed at the top/left and ``15`` at the bottom/right);
    * CPSNR over R, G, B per polarizer angle with peak 1;
    * S0 = mean of the four angles (peak 1); S1, S2 scored as ``(S + 1) / 2`` (peak 1);
    * DoLP clipped to [0, 1], peak 1 (0 where S0 <= 0);
    * AoP RMSE in degrees, wrap-aware, pooled over R, G, B, over *all* pixels (no mask).

``qiu`` (Qiu et al. 2021, KAUST dataset)
    * no border crop; otherwise as ``tokyotech``, and AoP also reported as PSNR
      ``20 log10(180 / RMSE_deg)``. (Their noise protocol, sigma 2/255 on the mosaic and
      8-bit quantization, belongs to the simulation, not to the metric.)

Well-defined results on hard inputs (each pinned by a test):

* identical images (MSE = 0, e.g. both all dark): PSNR is capped at :data:`PSNR_CAP_DB` (so is any
  PSNR above it; ``notes`` says when a non-zero error hit the cap); a GT of zeros: ``*_gt_peak`` None;
* constant images: SSIM is computed with the explicit data range, so its stabilizing
  constants keep it finite (1 for equal constants, < 1 otherwise);
* AoP undefined everywhere (no ground-truth pixel passes the mask, e.g. DoLP = 0 or an
  all-dark scene): the AoP metrics are ``None`` and ``notes`` says why;
* NaN/inf in either image, mismatched shapes, integer dtypes, images too small for the
  border crop and SSIM window, thresholds out of range (:func:`check_thresholds`):
  :class:`~capssim.errors.InputError`;
* results written as JSON go through :func:`json_safe`: a NaN is written as ``null``.

PSNR and SSIM come from ``skimage.metrics`` with an explicit ``data_range``; SSIM uses the
Wang et al. (2004) settings: Gaussian window sigma 1.5 (11 x 11), K1 = 0.01, K2 = 0.03,
population covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from capssim.conventions import CHANNEL_NAMES, COLOURS, N_CHANNELS, POLARIZER_ANGLES_DEG
from capssim.errors import InputError, UnknownNameError
from capssim.stokes.polarization import angle_difference_deg, aop_deg, dolp, stokes_from_12

from .metric_records import METRIC_SPECS

#: PSNR reported for identical images (zero MSE), in dB.
PSNR_CAP_DB = 100.0
#: Gaussian SSIM window (Wang et al. 2004): sigma 1.5 -> an 11 x 11 window.
SSIM_SIGMA = 1.5
SSIM_MIN_SIDE = 11


@dataclass(frozen=True)
class Convention:
    """How a published protocol crops, scales and masks (see the module docstring)."""

    name: str
    border: int
    matlab_crop: bool  # crop rows b..H-b (1-based, inclusive) as imcpsnr(X, Y, peak, b) does
    stokes_scale: str  # "capssim": S0 in [0,2], S1/S2 in [-1,1], data_range 2; "unit": S0/2, (S+1)/2, peak 1
    min_s0: float | None  # AoP/DoLP mask on the ground truth's S0 (None: no mask)
    min_dolp: float | None  # AoP mask on the ground truth's DoLP (None: no mask)
    description: str


CONVENTIONS: dict[str, Convention] = {
    "capssim": Convention("capssim", 8, False, "capssim", 0.02, 0.05,
                          "8 px border; S0=(I0+I45+I90+I135)/2; AoP over GT pixels with S0>0.02 and DoLP>0.05"),
    "tokyotech": Convention("tokyotech", 15, True, "unit", None, None,
                            "Tokyo Tech / EARI: 15 px border; CPSNR peak 1; S0=mean of 4; (S+1)/2; AoP RMSE all pixels"),
    "qiu": Convention("qiu", 0, False, "unit", None, None,
                      "Qiu et al.: no crop; as tokyotech otherwise; AoP PSNR = 20 log10(180/RMSE)"),
}

def get_convention(convention: str | Convention) -> Convention:
    if isinstance(convention, Convention):
        return convention
    key = str(convention).lower()
    if key not in CONVENTIONS:
        raise UnknownNameError("metric convention", str(convention), list(CONVENTIONS))
    return CONVENTIONS[key]


# -- input checks ---------------------------------------------------------------------------
def _as_float_array(x, argument: str) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    arr = np.asarray(x)
    if not (np.issubdtype(arr.dtype, np.floating)):
        raise InputError(argument, f"dtype {arr.dtype}", "a float array on [0, 1] full scale",
                         "Convert integer images with capssim.files.imageio.read_gt_scene or divide by the white level.")
    return arr.astype(np.float64, copy=False)


def check_pair(estimate12, gt12) -> tuple[np.ndarray, np.ndarray]:
    """Validate and return ``(estimate, gt)`` as float64 ``(12, H, W)`` arrays."""
    est = _as_float_array(estimate12, "estimate")
    gt = _as_float_array(gt12, "gt")
    for name, arr in (("gt", gt), ("estimate", est)):
        if arr.ndim != 3 or arr.shape[0] != N_CHANNELS:
            raise InputError(name, f"shape {arr.shape}", "a (12, H, W) array (channel c = 3*p + k)")
    if est.shape != gt.shape:
        raise InputError("estimate", f"shape {est.shape}", f"the ground-truth shape {gt.shape}",
                         "Score a reconstruction on the ground-truth grid (2H x 2W).")
    for name, arr in (("gt", gt), ("estimate", est)):
        bad = ~np.isfinite(arr)
        if bad.any():
            chans = sorted({CHANNEL_NAMES[c] for c in np.nonzero(bad.any(axis=(1, 2)))[0]})
            raise InputError(name, f"{int(bad.sum())} NaN/inf values (channels {', '.join(chans)})",
                             "finite values", "Metrics of a non-finite image are undefined; fix the method or input.")
    return est, gt


def crop_border(image: np.ndarray, border: int, *, matlab: bool = False) -> np.ndarray:
    """Drop ``border`` pixels on each side of the last two axes.

    ``matlab=True`` reproduces ``X(b:end-b, b:end-b)`` (1-based): ``b-1`` rows/cols are
    removed at the start and ``b`` at the end.
    """
    if border <= 0:
        return image
    h, w = image.shape[-2:]
    start = border - 1 if matlab else border
    return image[..., start:h - border, start:w - border]


def _check_size(gt: np.ndarray, conv: Convention, border: int) -> None:
    h, w = gt.shape[-2:]
    hc = h - 2 * border + (1 if conv.matlab_crop and border > 0 else 0)
    wc = w - 2 * border + (1 if conv.matlab_crop and border > 0 else 0)
    if min(hc, wc) < SSIM_MIN_SIDE:
        raise InputError("gt", f"size {h}x{w} with a {border}-pixel border crop ({conv.name} convention)",
                         f"at least {SSIM_MIN_SIDE}x{SSIM_MIN_SIDE} pixels left after the crop (SSIM window)",
                         "Use a larger image or pass border=0 (--border 0).")


# -- primitive metrics ----------------------------------------------------------------------
def psnr(estimate: np.ndarray, reference: np.ndarray, *, data_range: float) -> float:
    """skimage PSNR with an explicit ``data_range``, at most :data:`PSNR_CAP_DB` (zero MSE included)."""
    from skimage.metrics import peak_signal_noise_ratio

    mse = float(np.mean((np.asarray(estimate, np.float64) - reference) ** 2))
    if mse <= (data_range ** 2) * 10 ** (-PSNR_CAP_DB / 10):
        return PSNR_CAP_DB
    return float(peak_signal_noise_ratio(reference, estimate, data_range=data_range))


def ssim(estimate: np.ndarray, reference: np.ndarray, *, data_range: float) -> float:
    """skimage SSIM of one 2-D image, Gaussian window sigma 1.5, explicit ``data_range``."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(reference, estimate, data_range=data_range, gaussian_weights=True,
                                       sigma=SSIM_SIGMA, use_sample_covariance=False))


def _stokes_scaled(stokes: np.ndarray, scale: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``(S0, S1, S2, data_range)`` in the convention's scaling (each ``(3, H, W)``)."""
    if scale == "capssim":
        return stokes[0], stokes[1], stokes[2], 2.0
    return stokes[0] / 2.0, (stokes[1] + 1.0) / 2.0, (stokes[2] + 1.0) / 2.0, 1.0


def _gt_peak_scores(est_c, gt_c, st_e, st_g, stokes_scale: str, *, with_ssim: bool) -> tuple[dict[str, Any], list]:
    """The fixed-peak PSNRs/SSIMs of ``est_c / P`` against ``gt_c / P``, ``P = max(gt_c)``; None when ``P <= 0``."""
    peak = float(gt_c.max())
    if not peak > 0:
        undefined = dict.fromkeys(k.split(".")[0] for k in METRIC_SPECS if "_gt_peak" in k)
        return undefined, ["Scores against the ground truth's peak (*_gt_peak) undefined: it is 0 everywhere."]
    out: dict[str, Any] = {"psnr_gt_peak": {CHANNEL_NAMES[c]: psnr(est_c[c], gt_c[c], data_range=peak)
                                            for c in range(N_CHANNELS)}}
    out["psnr_gt_peak_mean"] = float(np.mean(list(out["psnr_gt_peak"].values())))
    out["ssim_gt_peak"] = out["ssim_gt_peak_mean"] = None
    if with_ssim:
        out["ssim_gt_peak"] = {CHANNEL_NAMES[c]: ssim(est_c[c], gt_c[c], data_range=peak) for c in range(N_CHANNELS)}
        out["ssim_gt_peak_mean"] = float(np.mean(list(out["ssim_gt_peak"].values())))
    out["cpsnr_gt_peak"] = {str(a): psnr(est_c[3 * p:3 * p + 3], gt_c[3 * p:3 * p + 3], data_range=peak)
                            for p, a in enumerate(POLARIZER_ANGLES_DEG)}
    (*est_s, rng_s), (*gt_s, _) = _stokes_scaled(st_e, stokes_scale), _stokes_scaled(st_g, stokes_scale)
    for i in range(3):
        out[f"s{i}_psnr_gt_peak"] = psnr(est_s[i], gt_s[i], data_range=rng_s * peak)
    return out, []


def _dark_scene_notes(est_c, gt_c, psnrs: dict[str, float], st_g, s0_guard: float | None) -> list[str]:
    """Notes when a fixed-peak score cannot tell estimates apart: PSNR at its cap, DoLP all guarded."""
    notes = []
    if any(psnrs[CHANNEL_NAMES[c]] == PSNR_CAP_DB and np.any(est_c[c] != gt_c[c]) for c in range(N_CHANNELS)):
        notes.append(f"PSNR at its {PSNR_CAP_DB:g} dB cap with a non-zero error (RMS below 1e-5 of full scale) in "
                     "some channel: the fixed-peak scores cannot rank estimates there; compare psnr_gt_peak and "
                     "ssim_gt_peak (data range = the ground truth's peak).")
    if s0_guard and not np.any(st_g[0] > s0_guard):
        notes.append(f"DoLP scores compare zeros: no ground-truth pixel has S0 > {s0_guard} (the DoLP dark guard); "
                     "pass a lower min_s0 (--min-s0) to score DoLP on a dark scene.")
    return notes


# -- the entry point ------------------------------------------------------------------------
def check_thresholds(*, min_s0: float | None = None, min_dolp: float | None = None) -> None:
    """Refuse AoP-mask thresholds outside their ranges: ``min_s0`` in [0, 2] (S0 scale), ``min_dolp`` in [0, 1]."""
    for name, value, high in (("min_s0", min_s0, 2.0), ("min_dolp", min_dolp, 1.0)):
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(value) and 0.0 <= value <= high):
            raise InputError(name, value, f"a finite number in [0, {high:g}], or nothing for the convention's default")


def resolve_settings(convention: str | Convention, *, min_s0: float | None = None, min_dolp: float | None = None,
                     border: int | None = None) -> tuple[Convention, int, float | None, float | None]:
    """``(convention, border, min_s0, min_dolp)`` of :func:`score`: the options given, else the convention's
    (border in pixels per side; thresholds on the S0 scale [0, 2] and DoLP [0, 1], None = no mask)."""
    conv = get_convention(convention)
    b = conv.border if border is None else int(border)
    if b < 0:
        raise InputError("border", b, "a non-negative number of pixels")
    check_thresholds(min_s0=min_s0, min_dolp=min_dolp)
    return (conv, b, conv.min_s0 if min_s0 is None else float(min_s0),
            conv.min_dolp if min_dolp is None else float(min_dolp))


def ground_truth_mask(stokes_gt: np.ndarray, *, min_s0: float | None, dolp_gt: np.ndarray | None = None,
                      min_dolp: float | None = None) -> np.ndarray:
    """``(3, H, W)`` bool: where the ground truth's S0 (``stokes_gt`` ``(3, 3, H, W)``) is above ``min_s0`` and,
    with ``dolp_gt`` ``(3, H, W)``, its DoLP above ``min_dolp`` (a None threshold is no condition): the AoP mask."""
    mask = np.ones(np.shape(stokes_gt)[1:], dtype=bool)
    if min_s0 is not None:
        mask &= stokes_gt[0] > min_s0
    if dolp_gt is not None and min_dolp is not None:
        mask &= dolp_gt > min_dolp
    return mask


def _intensity_scores(est_c: np.ndarray, gt_c: np.ndarray, *, with_ssim: bool) -> dict[str, Any]:
    """PSNR (and SSIM) of each of the 12 cropped channels on [0, 1], their means, and CPSNR per angle."""
    out: dict[str, Any] = {"psnr": {CHANNEL_NAMES[c]: psnr(est_c[c], gt_c[c], data_range=1.0) for c in range(N_CHANNELS)}}
    out["psnr_mean"] = float(np.mean(list(out["psnr"].values())))
    if with_ssim:
        out["ssim"] = {CHANNEL_NAMES[c]: ssim(est_c[c], gt_c[c], data_range=1.0) for c in range(N_CHANNELS)}
        out["ssim_mean"] = float(np.mean(list(out["ssim"].values())))
    else:
        out["ssim"], out["ssim_mean"] = None, None
    out["cpsnr"] = {str(a): psnr(est_c[3 * p:3 * p + 3], gt_c[3 * p:3 * p + 3], data_range=1.0)
                    for p, a in enumerate(POLARIZER_ANGLES_DEG)}
    return out


def _polarization_scores(st_e: np.ndarray, st_g: np.ndarray, *, s0_guard: float | None, dolp_min: float | None,
                         with_ssim: bool, notes: list[str]) -> dict[str, Any]:
    """DoLP and AoP scores from the Stokes maps ``(3, 3, H, W)``; appends to ``notes`` why AoP is undefined."""
    out: dict[str, Any] = {}
    # DoLP per colour, clipped to [0, 1]; dark guard on each image's own S0
    guard = s0_guard if s0_guard is not None else 0.0
    d_e = dolp(st_e, min_s0=guard, fill=0.0)
    d_g = dolp(st_g, min_s0=guard, fill=0.0)
    out["dolp_psnr"] = psnr(d_e, d_g, data_range=1.0)
    out["dolp_psnr_per_colour"] = {COLOURS[k]: psnr(d_e[k], d_g[k], data_range=1.0) for k in range(3)}
    out["dolp_ssim"] = float(np.mean([ssim(d_e[k], d_g[k], data_range=1.0) for k in range(3)])) if with_ssim else None

    # AoP per colour, wrap-aware, pooled; mask from the ground truth only
    a_e, a_g = aop_deg(st_e), aop_deg(st_g)
    diff = angle_difference_deg(a_e, a_g)
    mask = ground_truth_mask(st_g, min_s0=s0_guard, dolp_gt=d_g, min_dolp=dolp_min)
    if not np.any(np.hypot(st_g[1], st_g[2]) > 0):
        mask[:] = False
        notes.append("AoP undefined: the ground truth has S1 = S2 = 0 (DoLP = 0) at every pixel.")
    elif not mask.any():
        notes.append(f"AoP undefined: no ground-truth pixel has S0 > {s0_guard} and DoLP > {dolp_min}.")
    out["aop_fraction"] = float(mask.mean())
    if mask.any():
        dm = diff[mask]
        rmse = float(np.sqrt(np.mean(dm ** 2)))
        out["aop_rmse_deg"] = rmse
        out["aop_mae_deg"] = float(np.mean(np.abs(dm)))
        out["aop_psnr"] = PSNR_CAP_DB if rmse <= 180.0 * 10 ** (-PSNR_CAP_DB / 20) else float(20 * math.log10(180.0 / rmse))
    else:
        out["aop_rmse_deg"] = out["aop_mae_deg"] = out["aop_psnr"] = None
    return out


def _lpips_scores(est_c: np.ndarray, gt_c: np.ndarray, lpips) -> dict[str, Any]:
    """LPIPS of the RGB image at each polarizer angle and their mean; None without a model."""
    if lpips is None:
        return {"lpips": None, "lpips_mean": None}
    per_angle = {str(a): float(lpips.distance(est_c[3 * p:3 * p + 3], gt_c[3 * p:3 * p + 3]))
                 for p, a in enumerate(POLARIZER_ANGLES_DEG)}
    return {"lpips": per_angle, "lpips_mean": float(np.mean(list(per_angle.values())))}


def score(estimate12, gt12, *, convention: str | Convention = "capssim", min_s0: float | None = None,
          min_dolp: float | None = None, border: int | None = None, with_ssim: bool = True,
          lpips=None) -> dict[str, Any]:
    """Score a ``(12, H, W)`` estimate against its ``(12, H, W)`` ground truth on [0, 1].

    Parameters
    ----------
    estimate12, gt12
        Float arrays (or torch tensors), channel ``c = 3*p + k``.
    convention
        ``"capssim"`` (default), ``"tokyotech"`` or ``"qiu"`` (module docstring).
    min_s0, min_dolp
        AoP mask thresholds on the ground truth's S0 (capssim scale, [0, 2]) and DoLP;
        default: the convention's (capssim 0.02 and 0.05; tokyotech/qiu: no mask).
        ``min_s0`` is also the dark guard of the DoLP maps (DoLP = 0 there).
    border
        Pixels cropped on each side; default: the convention's.
    with_ssim
        Skip the SSIMs (faster) when False.
    lpips
        An :class:`capssim.eval.lpips.LPIPS` model (user-supplied weights) or None.

    Returns
    -------
    dict
        ``psnr`` / ``ssim`` per channel name, ``psnr_mean``, ``ssim_mean``, ``cpsnr`` per
        angle, ``s0_psnr``, ``s1_psnr``, ``s2_psnr``, ``dolp_psnr``, ``dolp_ssim``,
        ``dolp_psnr_per_colour``, ``aop_rmse_deg``, ``aop_mae_deg``, ``aop_psnr``,
        ``aop_fraction``, ``lpips_mean`` (or None), the ``*_gt_peak`` scores
        (:func:`_gt_peak_scores`), ``settings`` (with ``gt_peak``) and ``notes``.
    """
    conv = get_convention(convention)
    est, gt = check_pair(estimate12, gt12)
    conv, b, s0_guard, dolp_min = resolve_settings(conv, min_s0=min_s0, min_dolp=min_dolp, border=border)
    _check_size(gt, conv, b)
    notes: list[str] = []

    est_c = crop_border(est, b, matlab=conv.matlab_crop)
    gt_c = crop_border(gt, b, matlab=conv.matlab_crop)

    out: dict[str, Any] = {"convention": conv.name, **_intensity_scores(est_c, gt_c, with_ssim=with_ssim)}

    # Stokes (computed on the full image, then cropped: pixelwise, so the order is immaterial)
    st_e = stokes_from_12(est_c)  # (3 [S0,S1,S2], 3 [R,G,B], H, W)
    st_g = stokes_from_12(gt_c)
    e0, e1, e2, rng_s = _stokes_scaled(st_e, conv.stokes_scale)
    g0, g1, g2, _ = _stokes_scaled(st_g, conv.stokes_scale)
    out["s0_psnr"] = psnr(e0, g0, data_range=rng_s)
    out["s1_psnr"] = psnr(e1, g1, data_range=rng_s)
    out["s2_psnr"] = psnr(e2, g2, data_range=rng_s)
    peak_scores, peak_notes = _gt_peak_scores(est_c, gt_c, st_e, st_g, conv.stokes_scale, with_ssim=with_ssim)
    out.update(peak_scores)
    out.update(_polarization_scores(st_e, st_g, s0_guard=s0_guard, dolp_min=dolp_min, with_ssim=with_ssim,
                                    notes=notes))
    out.update(_lpips_scores(est_c, gt_c, lpips))

    notes += peak_notes + _dark_scene_notes(est_c, gt_c, out["psnr"], st_g, s0_guard)
    out["settings"] = {"border": b, "matlab_crop": conv.matlab_crop, "stokes_scale": conv.stokes_scale,
                       "min_s0": s0_guard, "min_dolp": dolp_min, "psnr_cap_db": PSNR_CAP_DB,
                       "ssim": {"gaussian_sigma": SSIM_SIGMA, "K1": 0.01, "K2": 0.03} if with_ssim else None,
                       "scored_shape": list(gt_c.shape),
                       "gt_peak": float(gt_c.max()), "dolp": "per colour, clipped to [0, 1]",
                       "aop": "per colour, wrap-aware, pooled over R,G,B"}
    out["notes"] = notes
    return out


#: :func:`tokyotech_scores`' names of the Tokyo Tech / EARI table columns -> :func:`score`'s keys
TOKYOTECH_COLUMNS = {"psnr_0": ("cpsnr", "0"), "psnr_45": ("cpsnr", "45"), "psnr_90": ("cpsnr", "90"),
                     "psnr_135": ("cpsnr", "135"), "psnr_s0": ("s0_psnr", None), "psnr_s1": ("s1_psnr", None),
                     "psnr_s2": ("s2_psnr", None), "psnr_dolp": ("dolp_psnr", None),
                     "aop_rmse_deg": ("aop_rmse_deg", None), "aop_mae_deg": ("aop_mae_deg", None)}


def tokyotech_scores(estimate12, gt12, *, border: int | None = None) -> dict[str, float | None]:
    """The columns of published colour-polarization demosaicking tables (Morimatsu et al. 2020, EARI).

    :func:`score` under the ``tokyotech`` convention (their MATLAB crop of ``border`` pixels,
    default 15), without SSIM: ``psnr_<angle>`` CPSNR of each polarizer image, ``psnr_s0``
    (S0 = mean of the four angles), ``psnr_s1`` and ``psnr_s2`` of ``(S + 1) / 2``, ``psnr_dolp``,
    all peak 1 in dB, and ``aop_rmse_deg`` and ``aop_mae_deg`` (the published tables' AoP error) over every
    pixel.
    """
    result = score(estimate12, gt12, convention="tokyotech", border=border, with_ssim=False)
    return {column: result[key] if sub is None else result[key][sub] for column, (key, sub) in TOKYOTECH_COLUMNS.items()}
