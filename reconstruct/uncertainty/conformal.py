"""Split conformal calibration of the bootstrap's intervals: one scale per method, noise level and channel group.

A bootstrap measures the estimator's spread ``s`` around the estimate ``x_hat``, not the prior's bias, so
``x_hat +- 1.645 s`` covers less than 90 % of the truth. Split conformal prediction (Vovk et al. 2005; Angelopoulos
and Bates, "A gentle introduction to conformal prediction", 2021, section 2.3, with a normalized score) fixes the
scale on *calibration* captures where the truth ``x`` is known: with the score ``r = |x - x_hat| / max(s, floor)``
over the calibration pixels, ``q`` is its ``ceil((n + 1) 0.9) / n`` empirical quantile, and ``x_hat +- q s`` covers
90 % of new pixels that are exchangeable with them. Pixels of one image are not independent, so the promise holds
for development scenes like the calibration's, and is checked on development scenes that were not used to fit
it (docs: results/uncertainty.md).

The groups: the 12 channels, S0, DoLP and AoP (the AoP's score is its wrapped angle error over its circular
spread). The shipped file ``calibration.json`` (beside this module) is written by
``capssim bench uncertainty eval/uncertainty/calibration.yaml -o DIR --install`` and read here; a run names the
entry it used in its record, or ``none`` (the uncalibrated ``1.645 s``) when the file has no entry for its
method and noise level.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from pathlib import Path

import numpy as np

from capssim.camera.sensor import GaussianSensor, PoissonGaussianSensor, Sensor
from capssim.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["CALIBRATION_FILE", "CALIBRATION_FORMAT", "FLOORS", "GROUPS", "Z90", "calibration_scales",
           "conformal_quantile", "load_calibration", "noise_key"]

#: the shipped calibration
CALIBRATION_FILE = Path(__file__).with_name("calibration.json")
#: the file's format name and version
CALIBRATION_FORMAT, CALIBRATION_VERSION = "capssim-uncertainty-calibration", 1
#: the channel groups with a scale of their own
GROUPS = ("12ch", "S0", "DoLP", "AoP")
#: the smallest spread a score divides by, per group (intensity on [0, 1], S0 on [0, 2], DoLP, AoP in degrees)
FLOORS = {"12ch": 1e-4, "S0": 2e-4, "DoLP": 1e-3, "AoP": 0.1}
#: the standard normal's 95th percentile: the half-width of a 90 % interval in standard deviations
Z90 = 1.6448536269514722
#: the nominal coverage of the intervals
NOMINAL = 0.90


def noise_key(sensor: Sensor) -> str | None:
    """The calibration's name of a sensor's noise level: ``gaussian-0.01``, ``poisson-gaussian-imx250myr``; None
    for a sensor without noise."""
    if isinstance(sensor, GaussianSensor):
        return f"gaussian-{sensor.sigma:.4g}"
    if isinstance(sensor, PoissonGaussianSensor):
        exposure = "" if sensor.exposure == 1.0 else f"-x{sensor.exposure:g}"
        return f"poisson-gaussian-{sensor.preset or 'custom'}{exposure}"
    return None


def conformal_quantile(scores, *, nominal: float = NOMINAL) -> float:
    """The split-conformal quantile of ``scores``: the ``ceil((n + 1) nominal)``-th smallest (inf when that
    exceeds ``n``)."""
    scores = np.asarray(scores, dtype=np.float64).ravel()
    scores = scores[np.isfinite(scores)]
    n = scores.size
    rank = math.ceil((n + 1) * nominal)
    if n == 0 or rank > n:
        return math.inf
    return float(np.partition(scores, rank - 1)[rank - 1])


def _check_calibration(data, where: str) -> dict:
    if not isinstance(data, dict) or data.get("format") != CALIBRATION_FORMAT:
        raise InputError("uncertainty calibration", where, f"a {CALIBRATION_FORMAT} JSON file",
                         "Regenerate it with capssim bench uncertainty ... --install.")
    if data.get("version") != CALIBRATION_VERSION:
        raise InputError("uncertainty calibration", f"{where} (version {data.get('version')!r})",
                         f"version {CALIBRATION_VERSION}", "Regenerate it with capssim bench uncertainty ... --install.")
    for method, levels in (data.get("entries") or {}).items():
        for level, scales in levels.items():
            bad = [g for g in GROUPS if not (isinstance(scales.get(g), (int, float)) and scales[g] > 0)]
            if bad:
                raise InputError("uncertainty calibration", f"{where}: entries.{method}.{level} lacks {bad}",
                                 f"a positive scale for each of {', '.join(GROUPS)}")
    return data


def load_calibration(path: str | Path | None = None) -> dict:
    """The calibration file at ``path`` (None: the shipped one), checked; its ``sha256`` and ``path`` added."""
    file = CALIBRATION_FILE if path is None else Path(path)
    if not file.is_file():
        if path is None:  # a checkout before the first calibration: every run is uncalibrated
            return {"format": CALIBRATION_FORMAT, "version": CALIBRATION_VERSION, "entries": {}, "path": None,
                    "sha256": None}
        raise InputError("uncertainty calibration", str(file), "an existing calibration JSON file",
                         "Use the shipped calibration (leave the option out) or 'none'.")
    raw = file.read_bytes()
    try:
        data = json.loads(raw)
    except ValueError as exc:
        raise InputError("uncertainty calibration", f"{file} ({exc})", "a JSON file") from None
    data = _check_calibration(data, str(file))
    return {**data, "path": str(file), "sha256": hashlib.sha256(raw).hexdigest()}


def calibration_scales(method: str, sensor: Sensor, *, calibration: str | Path | None = None) -> tuple[dict, dict]:
    """The scale ``q`` of each group for ``method`` at ``sensor``'s noise level, and the record naming it.

    ``calibration``: None (the shipped file), ``"none"`` (uncalibrated: ``q = 1.645`` everywhere) or a file. A
    method or noise level the file lacks runs uncalibrated, with a warning and the reason in the record.
    """
    raw = {group: Z90 for group in GROUPS}
    if calibration is not None and str(calibration) == "none":
        return raw, {"name": "none", "reason": "asked for (--uncertainty-calibration none)", "scales": raw}
    data = load_calibration(calibration)
    key = noise_key(sensor)
    entry = (data.get("entries") or {}).get(method, {}).get(key)
    if entry is None:
        known = sorted((data.get("entries") or {}).get(method, {}))
        reason = (f"the calibration has no entry for {method} at noise {key} (it has: {', '.join(known) or 'none'})")
        log.warning("%s: uncalibrated 90 %% intervals (1.645 bootstrap std): %s", method, reason)
        return raw, {"name": "none", "reason": reason, "file": data.get("path"), "scales": raw}
    scales = {group: float(entry[group]) for group in GROUPS}
    return scales, {"name": f"{method}/{key}", "file": data.get("path"), "sha256": data.get("sha256"),
                    "created": data.get("created"), "scales": scales}
