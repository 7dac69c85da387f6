"""The metrics as records: their names and directions, a score's flat keys, and JSON that has no NaN.

:data:`METRIC_SPECS` names every scalar metric that :func:`flatten` produces from a result of
:func:`capssim.eval.metrics.score` (the docs' metric table, guides/scoring.md, comes from it);
:func:`metric_direction` says whether higher or lower is better (the regression check reads it);
:func:`json_safe` writes NaN and infinities as ``null``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["METRIC_SPECS", "flatten", "json_safe", "metric_direction"]

#: Every scalar metric :func:`flatten` produces: (direction, unit, definition). ``+1`` means
#: higher is better, ``-1`` lower is better. The metric table of the docs (guides/scoring.md) is generated from it.
METRIC_SPECS: dict[str, tuple[int, str, str]] = {
    "psnr_mean": (+1, "dB", "mean over the 12 channels of PSNR(channel), data_range 1"),
    "ssim_mean": (+1, "", "mean over the 12 channels of SSIM(channel), data_range 1"),
    "psnr.<channel>": (+1, "dB", "PSNR of one channel (0-R ... 135-B), data_range 1"),
    "ssim.<channel>": (+1, "", "SSIM of one channel, data_range 1, Gaussian window sigma 1.5"),
    "cpsnr.<angle>": (+1, "dB", "CPSNR: PSNR of the MSE pooled over R, G, B at one polarizer angle, peak 1"),
    "s0_psnr": (+1, "dB", "PSNR of S0 pooled over R, G, B (S0 in [0,2], range 2 == S0/2 with peak 1)"),
    "s1_psnr": (+1, "dB", "PSNR of S1 = I0 - I90 pooled over R, G, B (range 2 == (S1+1)/2 with peak 1)"),
    "s2_psnr": (+1, "dB", "PSNR of S2 = I45 - I135 pooled over R, G, B (range 2 == (S2+1)/2 with peak 1)"),
    "dolp_psnr": (+1, "dB", "PSNR of per-colour DoLP in [0,1] pooled over R, G, B, data_range 1"),
    "dolp_psnr_per_colour.<colour>": (+1, "dB", "PSNR of the DoLP of one colour, data_range 1"),
    "dolp_ssim": (+1, "", "mean over R, G, B of SSIM(DoLP), data_range 1"),
    "aop_rmse_deg": (-1, "deg", "RMSE of the wrap-aware AoP difference in [-90, 90), per colour, pooled, masked"),
    "aop_mae_deg": (-1, "deg", "mean |wrap-aware AoP difference|, per colour, pooled, masked"),
    "aop_psnr": (+1, "dB", "20 log10(180 / aop_rmse_deg) (Qiu et al.)"),
    "aop_fraction": (0, "", "fraction of colour-pixels inside the AoP mask (not a quality metric)"),
    "psnr_gt_peak_mean": (+1, "dB", "mean over the 12 channels of PSNR(channel), data_range = P, the GT's peak"),
    "psnr_gt_peak.<channel>": (+1, "dB", "PSNR of one channel, data_range = P (GT's largest value, 12 channels)"),
    "ssim_gt_peak_mean": (+1, "", "mean over the 12 channels of SSIM(channel), data_range = P, the GT's peak"),
    "ssim_gt_peak.<channel>": (+1, "", "SSIM of one channel, data_range = P (the scene exposed to full scale)"),
    "cpsnr_gt_peak.<angle>": (+1, "dB", "CPSNR at one polarizer angle, peak = P (GT's largest value)"),
    "s0_psnr_gt_peak": (+1, "dB", "as s0_psnr with the data range times P (GT's largest value)"),
    "s1_psnr_gt_peak": (+1, "dB", "as s1_psnr with the data range times P (GT's largest value)"),
    "s2_psnr_gt_peak": (+1, "dB", "as s2_psnr with the data range times P (GT's largest value)"),
    "lpips.<angle>": (-1, "", "LPIPS (AlexNet) of the RGB image at one polarizer angle; user-supplied weights"),
    "lpips_mean": (-1, "", "mean of lpips.<angle> over the four angles (paper Table 1)"),
}


def metric_direction(name: str) -> int:
    """+1 when higher is better, -1 when lower is better, 0 when not a quality metric."""
    if name in METRIC_SPECS:
        return METRIC_SPECS[name][0]
    head = name.split(".", 1)[0]
    for key, spec in METRIC_SPECS.items():
        if "." in key and key.split(".", 1)[0] == head:
            return spec[0]
    if head.startswith("mtf") or head.endswith("magnification") or head.endswith("limit_resolution"):
        return +1
    if "time" in head or head.endswith("_s") or "memory" in head:
        return -1
    return 0


def json_safe(obj: Any) -> Any:
    """``obj`` with every NaN or infinite float replaced by ``None`` (JSON ``null``), numpy scalars as Python ones.

    Standard JSON has no NaN; ``json.dumps(json_safe(obj), allow_nan=False)`` always succeeds
    for results of :func:`score`.
    """
    if isinstance(obj, dict):
        return {key: json_safe(value) for key, value in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(value) for value in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def flatten(result: dict[str, Any], *, prefix: str = "") -> dict[str, float | None]:
    """The scalar metrics of a :func:`~capssim.eval.metrics.score` result, flat.

    Parameters
    ----------
    result : dict
        A :func:`~capssim.eval.metrics.score` result (``settings`` and ``notes`` are left out).
    prefix : str
        Prepended to every key.

    Returns
    -------
    dict of str to float or None
        ``{"psnr_mean": ..., "psnr.0-R": ...}``: nested mappings as ``key.sub``.
    """
    flat: dict[str, float | None] = {}
    for key, value in result.items():
        if key in ("settings", "notes", "convention"):
            continue
        if isinstance(value, dict):
            for sub, v in value.items():
                flat[f"{prefix}{key}.{sub}"] = None if v is None else float(v)
        elif value is None or isinstance(value, (int, float)):
            flat[f"{prefix}{key}"] = None if value is None else float(value)
    return flat
