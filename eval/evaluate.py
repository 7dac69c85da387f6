"""The one scoring path of capssim: :class:`CaptureScorer`, used by ``capssim evaluate`` and the benchmarks.

An estimate is scored by the metrics of :func:`capssim.eval.metrics.score` against the
capture's ground truth and, for Siemens-star scenes, by the MTF / SR magnification of
:mod:`capssim.eval.mtf` (paper section 5.3). :func:`evaluate_capture` scores every
``recon/NAME.tiff`` of a capture folder, adds the wall time and stage times from
``recon/NAME.json``, scores its error bars when it has them (:mod:`capssim.eval.uncertainty_scores`) and
writes ``CAPTURE/metrics.json`` (atomic write).

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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capssim.captures.capture import list_reconstructions, read_capture
from capssim.conventions import CHANNEL_NAMES, N_CHANNELS
from capssim.errors import CapssimError, CaptureFormatError, InputError
from capssim.files.imageio import atomic_write_json, read_tiff
from capssim.reconstruct.uncertainty.maps import read_uncertainty
from capssim.runtime.data_range import warn_out_of_range

from . import metrics as M
from .metric_records import flatten, json_safe
from .mtf import StarMTF, measure_star
from .uncertainty_plots import write_uncertainty_plots
from .uncertainty_scores import UncertaintyScores, score_uncertainty

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


@dataclass
class EstimateScore:
    """The scores of one estimate: :func:`capssim.eval.metrics.score`'s result and, for a star scene, its MTF."""

    metrics: dict[str, Any]
    mtf: dict | None = None  # :func:`mtf_summary` of the estimate; None when not measured
    mtf_error: str | None = None  # why the estimate's MTF could not be measured

    def flat(self) -> dict[str, float | None]:
        """Scalar metrics for results.jsonl and baselines: the metrics' and the MTF's."""
        return {**flatten(self.metrics), **flat_mtf(self.mtf)}


class CaptureScorer:
    """Scores estimates of one capture against its ground truth: the one scoring path of capssim.

    ``capssim evaluate`` (:func:`evaluate_capture`) and the benchmark suites both score through
    it. Options are those of :func:`capssim.eval.metrics.score`. For a Siemens-star scene
    (:func:`star_geometry`) and ``with_mtf``, the ground truth's MTF is measured once (on first
    use, or by :meth:`measure_ground_truth`) and every estimate's MTF is measured at its centre
    and radius, normalized by its per-channel modulation; when the ground truth cannot be
    measured, :attr:`mtf_error` says why and no MTF is reported.
    """

    def __init__(self, capture, *, convention: str | M.Convention = "capssim", min_s0: float | None = None,
                 min_dolp: float | None = None, border: int | None = None, lpips=None, with_mtf: bool = True):
        self.gt = capture.gt
        self.convention = M.get_convention(convention)
        self.score_options = {"min_s0": min_s0, "min_dolp": min_dolp, "border": border, "lpips": lpips}
        crop = self.convention.border if border is None else int(border)
        if self.gt is not None and crop >= 0:  # a crop the ground truth cannot take fails every method: say it once
            M._check_size(np.asarray(self.gt), self.convention, crop)
        self.star = star_geometry(capture.meta) if with_mtf else None
        self.gt_mtf: StarMTF | None = None
        self.mtf_error: str | None = None

    def measure_ground_truth(self) -> StarMTF | None:
        """The ground truth's MTF (measured once); None for a scene without a star or when it failed."""
        if self.star is None or self.gt_mtf is not None:
            return self.gt_mtf
        star = self.star
        try:
            self.gt_mtf = measure_star(self.gt, star["cycles"], names=list(CHANNEL_NAMES),
                                       center_rowcol=star.get("center_rowcol"), radius=star.get("radius_px"),
                                       reference_modulation=star.get("contrast"), reference_pitch=SUB_IMAGE_PITCH_HR)
        except CapssimError as exc:
            self.mtf_error = str(exc)
            self.star = None
        return self.gt_mtf

    def score_uncertainty(self, estimate: np.ndarray, maps) -> UncertaintyScores:
        """Coverage, width and AUSE of the error bars ``maps`` of a ``(12, 2H, 2W)`` estimate, under this scorer's
        convention, border and thresholds (:func:`~capssim.eval.uncertainty_scores.score_uncertainty`)."""
        options = {k: v for k, v in self.score_options.items() if k != "lpips"}
        return score_uncertainty(estimate, self.gt, maps, convention=self.convention, **options)

    def score(self, estimate: np.ndarray) -> EstimateScore:
        """Scores of a ``(12, 2H, 2W)`` estimate; a metric error (NaN, wrong shape) raises :class:`InputError`."""
        result = EstimateScore(M.score(estimate, self.gt, convention=self.convention, **self.score_options))
        gt_mtf = self.measure_ground_truth()
        if gt_mtf is not None:
            head = gt_mtf.results["mean"]
            refs = [gt_mtf.results[n].reference_modulation for n in CHANNEL_NAMES]
            try:
                measured = measure_star(estimate, self.star["cycles"], names=list(CHANNEL_NAMES),
                                        center_rowcol=head.center_rowcol, radius=head.radius_px,
                                        reference_modulation=refs, reference_pitch=SUB_IMAGE_PITCH_HR)
                result.mtf = mtf_summary(measured)
            except CapssimError as exc:
                result.mtf_error = str(exc)
        return result


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


def _record_entry(record_path: Path) -> tuple[dict[str, Any], dict]:
    """Wall time, stage times and registration of a reconstruction's ``recon/NAME.json``, and the record itself
    (``{}`` when absent or corrupt)."""
    entry: dict[str, Any] = {}
    record: dict = {}
    if record_path.is_file():
        try:
            record = json.loads(record_path.read_text())
            entry["wall_time_s"] = record.get("wall_time_s")
            entry["stages_s"] = record.get("stages_s", {})
            if "registration" in record:
                entry["registration"] = record["registration"]
        except json.JSONDecodeError as exc:
            entry["record_error"] = f"corrupt {record_path.name}: {exc}"
    return entry, record if isinstance(record, dict) else {}


def uncertainty_entry(scores: UncertaintyScores, record: dict) -> dict[str, Any]:
    """The ``"uncertainty"`` block of a method in ``metrics.json``: :meth:`UncertaintyScores.to_dict` with the
    ``calibration`` name and ``replicates`` of the record's ``"uncertainty"`` block (None when absent), and a
    note when the record has no such block (the files may be left from an earlier run)."""
    made = record.get("uncertainty") if isinstance(record.get("uncertainty"), dict) else None
    calibration = (made or {}).get("calibration")
    if isinstance(calibration, dict):
        calibration = calibration.get("name")
    block = {**scores.to_dict(), "calibration": calibration, "replicates": (made or {}).get("replicates"),
             "notes": []}
    if made is None:
        block["notes"].append("the record (recon/METHOD.json) has no 'uncertainty' block: the error-bar files "
                              "may be left from an earlier reconstruction")
    return block


def _score_uncertainty(path: Path, name: str, estimate: np.ndarray, gt: np.ndarray, scorer: CaptureScorer,
                       record: dict, plot_dir: Path | None) -> dict[str, Any] | None:
    """The ``"uncertainty"`` block of ``recon/NAME`` (None without error-bar files; ``{"error": ...}`` when they
    cannot be read or scored), with the paths of its plots when ``plot_dir`` is given."""
    try:
        maps = read_uncertainty(path, name)
        if maps is None:
            return None
        scores = scorer.score_uncertainty(estimate, maps)
    except CapssimError as exc:
        return {"error": str(exc)}
    block = uncertainty_entry(scores, record)
    if plot_dir is not None:
        try:
            block["plots"] = [str(p) for p in write_uncertainty_plots(estimate, gt, maps, scores, plot_dir,
                                                                      method=name)]
        except Exception as exc:  # a plot must never lose the scores
            log.warning("uncertainty plots of %s failed: %s", name, exc)
            block["plots_error"] = f"{type(exc).__name__}: {exc}"
    return block


def _score_reconstruction(path: Path, name: str, capture, scorer: CaptureScorer,
                          plot_dir: Path | None) -> dict[str, Any]:
    """The ``metrics.json`` entry of ``recon/NAME``: record times, metrics, MTF, error bars, or ``error``."""
    entry, record = _record_entry(path / "recon" / f"{name}.json")
    try:
        estimate = read_estimate(path / "recon" / f"{name}.tiff", capture.hr_shape)
        scored = scorer.score(estimate)
        entry["metrics"] = scored.metrics
        if scored.mtf is not None or scored.mtf_error is not None:
            entry["mtf"] = scored.mtf if scored.mtf is not None else {"error": scored.mtf_error}
    except CapssimError as exc:
        entry["error"] = str(exc)
        return entry
    block = _score_uncertainty(path, name, estimate, capture.gt, scorer, record, plot_dir)
    if block is not None:
        entry["uncertainty"] = block
    return entry


#: a ground truth above this many times full scale gets a warning: PSNR and SSIM assume a peak of 1
GT_WARN_ABOVE = 2.0


def evaluate_capture(capture_path, *, convention: str = "capssim", methods: list[str] | None = None,
                     min_s0: float | None = None, min_dolp: float | None = None, border: int | None = None,
                     lpips=None, with_mtf: bool = True, write: bool = True, plot_dir=None) -> dict:
    """Score ``recon/*.tiff`` of a capture folder against its ``gt.tiff``; write ``metrics.json`` when ``write``.

    A reconstruction that cannot be scored (NaN, wrong shape, unreadable) gets ``{"error": ...}`` and
    the others are still scored.

    Parameters
    ----------
    capture_path : str or pathlib.Path
        The capture folder.
    convention : str
        ``capssim``, ``tokyotech`` or ``qiu`` (as in :func:`capssim.eval.metrics.score`).
    min_s0, min_dolp : float, optional
        AoP mask thresholds (default: the convention's).
    border : int, optional
        Pixels cropped on each side (default: the convention's).
    lpips : optional
        An :class:`capssim.eval.lpips.LPIPS` model, or None.
    methods : list of str, optional
        Only these reconstructions (default: all).
    with_mtf : bool
        Also measure the MTF on a star scene (``meta.json["scene"]["star"]``).
    write : bool
        Write ``metrics.json`` into the folder.
    plot_dir : str or pathlib.Path, optional
        Draw the error-bar plots (:func:`~capssim.eval.uncertainty_plots.write_uncertainty_plots`) of each
        reconstruction with error bars into this folder.

    Returns
    -------
    dict
        ``methods``: per method, ``metrics`` (the :func:`~capssim.eval.metrics.score` result) or ``error``,
        and ``uncertainty`` (:func:`uncertainty_entry`) when ``recon/NAME.std.tiff`` and its companions exist.

    Raises
    ------
    CaptureFormatError
        A missing ``gt.tiff``, or no reconstruction at all.
    """
    path = Path(capture_path)
    capture = read_capture(path, require_gt=True)
    warn_out_of_range(f"{path.name}/gt.tiff", capture.gt, low=0.0, high=None, below_means="negative",
                      consequence="scored as they are (a ground truth is an intensity >= 0: check how it was made)")
    warn_out_of_range(f"{path.name}/gt.tiff", capture.gt, low=-np.inf, high=GT_WARN_ABOVE,
                      above_means="above twice full scale",
                      consequence="scored as they are, but PSNR and SSIM take a peak of 1 (full scale), so their "
                                  "numbers say nothing there: rescale the ground truth to [0, 1]")
    names = list_reconstructions(path)
    if methods:
        unknown = sorted(set(methods) - set(names))
        if unknown:
            raise InputError("methods", ", ".join(unknown), f"reconstructions present in {path}/recon: {names or 'none'}")
        names = [n for n in names if n in methods]
    if not names:
        raise CaptureFormatError(f"{path}: no reconstructions in recon/; run 'capssim reconstruct {path} --method NAME' first.")
    scorer = CaptureScorer(capture, convention=convention, min_s0=min_s0, min_dolp=min_dolp, border=border,
                           lpips=lpips, with_mtf=with_mtf)
    conv = scorer.convention
    result: dict[str, Any] = {"capture": str(path), "convention": conv.name, "convention_description": conv.description,
                              "methods": {}}
    for name in names:
        result["methods"][name] = _score_reconstruction(path, name, capture, scorer,
                                                        None if plot_dir is None else Path(plot_dir))
    first_ok = next((e for e in result["methods"].values() if "metrics" in e), None)
    if first_ok is not None:
        result["settings"] = first_ok["metrics"]["settings"]
    if scorer.gt_mtf is not None:
        result["star"] = scorer.star
        result["gt_mtf"] = mtf_summary(scorer.gt_mtf)
    elif scorer.mtf_error is not None:
        result["mtf_error"] = scorer.mtf_error
        log.warning("MTF of %s not measured: %s", path, scorer.mtf_error)
    if write:
        atomic_write_json(path / "metrics.json", json_safe(result))
    return result
