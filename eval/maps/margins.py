"""The numbers of a design map: per cell and metric, the best camera-array method against the best DoFP method.

For a metric (:data:`METRICS`) and a cell, each method's value is averaged over the seeds; the best array method
(``kind`` ``array``: a method whose input is the camera array, ``caps*``) and the best DoFP method (``kind``
``dofp``) are those with the best mean. The **margin** is, seed by seed, the best array method's value minus the
best DoFP method's (for a metric where lower is better, the DoFP one's minus the array one's), so that a positive
margin always means the array wins; its mean and standard error over the seeds (``std(ddof=1) / sqrt(seeds)``)
give the cell's verdict: ``array`` when the mean margin exceeds one standard error, ``dofp`` when it is below minus
one, ``undecided`` otherwise (and with a single seed, whose spread is unknown, ``array``/``dofp`` by the sign and
``se`` None).
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

#: metric key -> (label, higher is better)
METRICS = {
    "psnr_mean": ("12-channel PSNR (dB)", True),
    "ssim_mean": ("SSIM", True),
    "dolp_psnr": ("DoLP PSNR (dB)", True),
    "aop_rmse_deg": ("AoP RMSE (deg)", False),
    "mtf_magnification_hv": ("SR magnification (star, h/v)", True),
    "wall_time_s": ("time (s)", False),
}


def record_value(rec: dict, metric: str) -> float | None:
    """A record's value of ``metric`` (its metrics, or the record itself for ``wall_time_s``); None when missing."""
    value = rec.get(metric) if metric == "wall_time_s" else (rec.get("metrics") or {}).get(metric)
    return None if value is None or not math.isfinite(float(value)) else float(value)


def cell_key(rec: dict, axes: list[str]) -> tuple:
    """The axis values of a record's cell, in the map's axis order."""
    return tuple(rec["axes"][a] for a in axes)


def method_table(records: list[dict], metric: str, axes: list[str]) -> dict[tuple, dict[str, dict[int, float]]]:
    """``{cell: {method label: {seed: value}}}`` of the ``ok`` records."""
    table: dict[tuple, dict[str, dict[int, float]]] = defaultdict(lambda: defaultdict(dict))
    for rec in records:
        if rec.get("status") != "ok":
            continue
        value = record_value(rec, metric)
        if value is not None:
            table[cell_key(rec, axes)][rec["method"]][int(rec["seed"])] = value
    return table


def _mean_se(values: list[float]) -> tuple[float, float | None]:
    arr = np.asarray(values, dtype=np.float64)
    if arr.size < 2:
        return float(arr.mean()), None
    return float(arr.mean()), float(arr.std(ddof=1) / math.sqrt(arr.size))


def cell_margin(methods: dict[str, dict[int, float]], kinds: dict[str, str], higher: bool) -> dict | None:
    """The margin of one cell (module docstring) from ``{label: {seed: value}}`` and ``{label: kind}``; None when
    the cell lacks an array or a DoFP method."""
    sign = 1.0 if higher else -1.0
    best: dict[str, tuple[str, float]] = {}
    for label, by_seed in methods.items():
        kind = kinds.get(label)
        if kind not in ("array", "dofp") or not by_seed:
            continue
        mean = float(np.mean(list(by_seed.values())))
        if kind not in best or sign * mean > sign * best[kind][1]:
            best[kind] = (label, mean)
    if len(best) < 2:
        return None
    a, d = methods[best["array"][0]], methods[best["dofp"][0]]
    seeds = sorted(set(a) & set(d))
    if not seeds:
        return None
    margin, se = _mean_se([sign * (a[s] - d[s]) for s in seeds])
    if se is None:
        verdict = "array" if margin > 0 else "dofp"
    else:
        verdict = "array" if margin > se else ("dofp" if margin < -se else "undecided")
    return {"margin": margin, "se": se, "verdict": verdict, "best_array": best["array"][0],
            "best_array_mean": best["array"][1], "best_dofp": best["dofp"][0], "best_dofp_mean": best["dofp"][1],
            "seeds": len(seeds)}


def margins(records: list[dict], metric: str, axes: list[str]) -> dict[tuple, dict]:
    """``{cell: cell_margin}`` of a map's records for ``metric`` (cells without both kinds left out)."""
    kinds = {r["method"]: r.get("kind") for r in records}
    higher = METRICS.get(metric, ("", True))[1]
    out = {}
    for cell, methods in method_table(records, metric, axes).items():
        m = cell_margin(methods, kinds, higher)
        if m is not None:
            out[cell] = m
    return out


def method_curves(records: list[dict], metric: str, axes: list[str]) -> dict[str, dict[tuple, tuple]]:
    """``{method: {cell: (mean, se)}}`` over the seeds (``se`` None with one seed)."""
    out: dict[str, dict[tuple, tuple]] = defaultdict(dict)
    for cell, methods in method_table(records, metric, axes).items():
        for label, by_seed in methods.items():
            out[label][cell] = _mean_se(list(by_seed.values()))
    return out


def cell_field(records: list[dict], key: str, sub: str | None, axes: list[str]) -> dict[tuple, float]:
    """The mean over seeds of a per-capture field of the records (``theory.resolved_fraction``,
    ``registration_reached_hr_px``), by cell."""
    seen: dict[tuple, dict[int, float]] = defaultdict(dict)
    for rec in records:
        value = rec.get(key)
        if isinstance(value, dict) and sub is not None:
            value = value.get(sub)
        if isinstance(value, (int, float)) and math.isfinite(float(value)):
            seen[cell_key(rec, axes)][int(rec["seed"])] = float(value)
    return {cell: float(np.mean(list(v.values()))) for cell, v in seen.items()}
