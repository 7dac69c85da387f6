"""Score every reconstruction of a capture folder: ``capssim evaluate`` and the benchmark share it.

For each ``recon/NAME.tiff`` the metrics of :func:`eval.metrics.score` against ``gt.tiff``,
the wall time and stage times from ``recon/NAME.json``, and, for Siemens-star scenes, the
MTF / SR magnification of :mod:`eval.mtf`. Results go to ``CAPTURE/metrics.json``
(atomic write).

Star scenes: the geometry comes from ``meta["scene"]["star"]`` (``cycles``, optional
``center_rowcol`` and ``radius_px``, in HR = ground-truth pixels) when the renderer records
it; a missing centre is found on the ground truth. Each method's MTF is normalized by the
target's modulation: the scene's known ``contrast`` when recorded (modulation of every
channel: the intensity contrast of ``siemens-star``, the DoLP of ``polarization-star``), else
the ground truth's own modulation extrapolated to f = 0 per channel. The magnification is
reported per Bayer sub-image pixel (``reference_pitch = 4`` HR pixels).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from capssim.capture import list_reconstructions, read_capture
from capssim.conventions import CHANNEL_NAMES, N_CHANNELS
from capssim.errors import CapssimError, CaptureFormatError, InputError
from capssim.eval import metrics as M
from capssim.eval.mtf import StarMTF, measure_star
from capssim.imageio import atomic_write_json, read_tiff

log = logging.getLogger(__name__)

#: one Bayer sub-image pixel spans 4 HR (ground-truth) pixels in capssim
SUB_IMAGE_PITCH_HR = 4.0


def star_geometry(meta: dict) -> dict | None:
    """``{"cycles", "center_rowcol" or None, "radius_px" or None}`` of a star scene, else None."""
    candidates = [meta.get("scene", {}).get("star") if isinstance(meta.get("scene"), dict) else None,
                  meta.get("star"),
                  meta.get("source", {}).get("star") if isinstance(meta.get("source"), dict) else None]
    for star in candidates:
        if isinstance(star, dict) and star.get("cycles"):
            centre = star.get("center_rowcol")
            contrast = star.get("contrast")
            return {"cycles": int(star["cycles"]),
                    "center_rowcol": [float(v) for v in centre] if centre is not None else None,
                    "radius_px": float(star["radius_px"]) if star.get("radius_px") else None,
                    "contrast": float(contrast) if contrast else None}
    return None


def mtf_summary(result: StarMTF) -> dict:
    """Compact JSON of a :class:`StarMTF`: per-channel limits, the channel-mean curve in full."""
    res = result.results
    key = "mean" if "mean" in res else next(iter(res))
    channels = {name: {"limit_cyc_per_ref_px": {g: v * r.reference_pitch for g, v in r.limit.items()},
                       "magnification": {g: r.magnification(g) for g in r.limit},
                       "limited_by": dict(r.limited_by), "reference_modulation": r.reference_modulation}
                for name, r in res.items() if name != "mean"}
    head = res[key]
    return {"cycles": head.cycles, "center_rowcol": list(head.center_rowcol), "radius_px": head.radius_px,
            "reference_pitch": head.reference_pitch, "channels": channels, "mean": head.to_dict()}


def star_mtfs(gt12: np.ndarray, estimates: dict[str, np.ndarray], star: dict) -> tuple[dict, dict[str, Any]]:
    """MTF of the ground truth and of each estimate; returns (gt summary, {name: summary or error})."""
    cycles = star["cycles"]
    gt_res = measure_star(gt12, cycles, names=list(CHANNEL_NAMES), center_rowcol=star.get("center_rowcol"),
                          radius=star.get("radius_px"), reference_modulation=star.get("contrast"),
                          reference_pitch=SUB_IMAGE_PITCH_HR)
    head = gt_res.results["mean"]
    centre, radius = head.center_rowcol, head.radius_px
    refs = [gt_res.results[n].reference_modulation for n in CHANNEL_NAMES]
    out = {}
    for name, est in estimates.items():
        try:
            r = measure_star(est, cycles, names=list(CHANNEL_NAMES), center_rowcol=centre, radius=radius,
                             reference_modulation=refs, reference_pitch=SUB_IMAGE_PITCH_HR)
            out[name] = mtf_summary(r)
        except CapssimError as exc:
            out[name] = {"error": str(exc)}
    return mtf_summary(gt_res), out


def flat_mtf(summary: dict | None) -> dict[str, float]:
    """Scalar MTF figures for results.jsonl / baselines (channel-mean curve)."""
    if not summary or "mean" not in summary:
        return {}
    mean = summary["mean"]
    out = {}
    for g in ("hv", "diagonal"):
        out[f"mtf_limit_{g}"] = float(mean["limit_cyc_per_ref_px"][g])
        out[f"mtf_magnification_{g}"] = float(mean["magnification"][g])
    return out


def read_estimate(path: Path, hr_shape: tuple[int, int]) -> np.ndarray:
    img = read_tiff(path, argument=f"recon/{path.name}")
    if img.shape != (N_CHANNELS, *hr_shape):
        raise InputError(f"recon/{path.name}", f"shape {img.shape}", f"{(N_CHANNELS, *hr_shape)} (the gt.tiff grid)")
    return img


def evaluate_capture(capture_path, *, convention: str = "capssim", methods: list[str] | None = None,
                     min_s0: float | None = None, min_dolp: float | None = None, border: int | None = None,
                     lpips=None, with_mtf: bool = True, write: bool = True) -> dict:
    """Score ``recon/*.tiff`` of a capture folder; write ``metrics.json`` when ``write``.

    A reconstruction that cannot be scored (NaN, wrong shape, unreadable) gets
    ``{"error": ...}`` and the others are still scored. A missing ``gt.tiff`` or no
    reconstruction at all is a :class:`CaptureFormatError`.
    """
    path = Path(capture_path)
    capture = read_capture(path, require_gt=True)
    names = list_reconstructions(path)
    if methods:
        unknown = sorted(set(methods) - set(names))
        if unknown:
            raise InputError("methods", ", ".join(unknown), f"reconstructions present in {path}/recon: {names or 'none'}")
        names = [n for n in names if n in methods]
    if not names:
        raise CaptureFormatError(f"{path}: no reconstructions in recon/; run 'capssim reconstruct {path} --method NAME' first.")
    conv = M.get_convention(convention)
    result: dict[str, Any] = {"capture": str(path), "convention": conv.name, "convention_description": conv.description,
                              "methods": {}}
    estimates = {}
    for name in names:
        entry: dict[str, Any] = {}
        record_path = path / "recon" / f"{name}.json"
        if record_path.is_file():
            try:
                record = json.loads(record_path.read_text())
                entry["wall_time_s"] = record.get("wall_time_s")
                entry["stages_s"] = record.get("stages_s", {})
                if "registration" in record:
                    entry["registration"] = record["registration"]
            except json.JSONDecodeError as exc:
                entry["record_error"] = f"corrupt {record_path.name}: {exc}"
        try:
            est = read_estimate(path / "recon" / f"{name}.tiff", capture.hr_shape)
            scored = M.score(est, capture.gt, convention=conv, min_s0=min_s0, min_dolp=min_dolp, border=border,
                             lpips=lpips)
            entry["metrics"] = scored
            estimates[name] = est
        except CapssimError as exc:
            entry["error"] = str(exc)
        result["methods"][name] = entry
    if result["methods"]:
        first_ok = next((e for e in result["methods"].values() if "metrics" in e), None)
        if first_ok is not None:
            result["settings"] = first_ok["metrics"]["settings"]
    star = star_geometry(capture.meta)
    if with_mtf and star and estimates:
        try:
            gt_mtf, per_method = star_mtfs(capture.gt, estimates, star)
            result["star"] = star
            result["gt_mtf"] = gt_mtf
            for name, summary in per_method.items():
                result["methods"][name]["mtf"] = summary
        except CapssimError as exc:
            result["mtf_error"] = str(exc)
            log.warning("MTF of %s not measured: %s", path, exc)
    if write:
        atomic_write_json(path / "metrics.json", result)
    return result
