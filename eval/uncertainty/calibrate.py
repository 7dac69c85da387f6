"""``capssim bench uncertainty``: fit the conformal scales on calibration captures, check coverage on others.

For every (scene, noise level, seed, method) of an uncertainty spec (:mod:`.spec`) the capture is made as a suite
makes it (:class:`~capssim.eval.benchmarks.captures.CaptureFactory`, cached), reconstructed with ``--uncertainty
N`` *uncalibrated*, and the normalized score ``|error| / max(spread, floor)`` of every scored pixel is kept per
group (12 channels, S0, DoLP, AoP), with the spread (``OUTPUT/cases/KEY.npz``; a rerun skips the cases it has).
The scored pixels are the metrics' (:mod:`capssim.eval.metrics`, ``capssim`` convention): an 8 px border crop; DoLP
where the truth's S0 > 0.02; AoP also where its DoLP > 0.05.

Then, per method and noise level, the scale of each group is the split-conformal quantile
(:func:`~capssim.reconstruct.uncertainty.conformal.conformal_quantile`) of the calibration scenes' pooled scores,
written to ``OUTPUT/calibration.json`` (``--install``: also to the shipped file the reconstruction reads), and the
check scenes' coverage ``P(score <= scale)``, mean interval width and AUSE are the report (``OUTPUT/report.md``).
"""

from __future__ import annotations

import datetime as _dt
import io
import json
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from capssim.captures.capture import read_capture
from capssim.files.imageio import atomic_write_bytes, atomic_write_json
from capssim.reconstruct.registry import reconstruct
from capssim.reconstruct.uncertainty.conformal import (
    CALIBRATION_FILE,
    CALIBRATION_FORMAT,
    CALIBRATION_VERSION,
    FLOORS,
    GROUPS,
    NOMINAL,
    conformal_quantile,
    noise_key,
)

from ..benchmarks.captures import CaptureFactory, Unavailable
from ..benchmarks.provenance import code_fingerprint, content_hash
from ..uncertainty_scores import scored_values

log = logging.getLogger(__name__)

#: what a case's result depends on besides its spec: the project's code, scoring included (a change runs every case again)
CODE = code_fingerprint("capssim", "reconstruct", "eval")

__all__ = ["case_scores", "fit_calibration", "load_case_scores", "run_uncertainty_calibration"]


def case_scores(estimate: np.ndarray, truth: np.ndarray, maps) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{group: (scores, spreads)}`` over the scored pixels of one uncalibrated reconstruction (the metrics' and
    :func:`~capssim.eval.uncertainty_scores.scored_values`'s): ``spreads`` the floored bootstrap spread (the std
    of a ``calibration="none"`` run) and ``scores`` the absolute error over it (AoP: the wrapped angle error)."""
    values, _ = scored_values(estimate, truth, maps)
    out = {}
    for group, v in values.items():
        spread = np.maximum(v.std.astype(np.float64), FLOORS[group])
        out[group] = ((np.abs(v.error) / spread).astype(np.float32), spread.astype(np.float32))
    return out


def _case_key(spec: dict, scene: dict, noise: dict, seed: int, method: dict) -> str:
    return content_hash({"scene": scene, "noise": noise, "seed": seed, "method": method, "code": CODE,
                         "replicates": spec["replicates"], "options": spec.get("options") or {}})[:20]


def _run_case(factory, spec, scene, noise, seed, method, *, device, cases_dir: Path) -> dict | None:
    key = _case_key(spec, scene, noise, seed, method)
    path = cases_dir / f"{key}.npz"
    info_path = cases_dir / f"{key}.json"
    if path.is_file() and info_path.is_file():
        return json.loads(info_path.read_text())
    entry = factory.get(scene, noise, seed)
    capture = read_capture(entry.path, require_gt=True)
    t0 = time.perf_counter()
    out, record = reconstruct(capture, method["name"], device=device, true_warps=method["true_warps"],
                              registration=method["registration"], uncertainty=spec["replicates"],
                              uncertainty_options={**(spec.get("options") or {}), "calibration": "none"},
                              **method["options"])
    scores = case_scores(out.image, capture.gt, out.uncertainty)
    arrays = {f"{g}_{part}": a for g, (s, w) in scores.items() for part, a in (("scores", s), ("spreads", w))}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    atomic_write_bytes(path, buffer.getvalue())
    info = {"key": key, "scene": scene["name"], "noise": noise["name"], "noise_key": noise_key(capture.sensor),
            "seed": seed, "method": method["name"], "wall_time_s": record["wall_time_s"],
            "uncertainty_time_s": record["uncertainty"]["time_s"], "total_time_s": time.perf_counter() - t0}
    atomic_write_json(info_path, info)
    return info


def load_case_scores(cases_dir: Path, key: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    with np.load(cases_dir / f"{key}.npz") as data:
        return {g: (data[f"{g}_scores"], data[f"{g}_spreads"]) for g in GROUPS}


def fit_calibration(cases: list[dict], cases_dir: Path, calibration_scenes: set[str], *, spec: dict) -> dict:
    """The calibration file's content: per method and noise key, the conformal scale of each group over the pooled
    scores of the calibration scenes' cases."""
    entries: dict[str, dict] = {}
    for method, level in sorted({(c["method"], c["noise_key"]) for c in cases}):
        chosen = [c for c in cases if c["method"] == method and c["noise_key"] == level
                  and c["scene"] in calibration_scenes]
        if not chosen:
            continue
        loaded = [load_case_scores(cases_dir, c["key"]) for c in chosen]
        scales = {g: conformal_quantile(np.concatenate([s[g][0] for s in loaded]), nominal=NOMINAL) for g in GROUPS}
        pixels = {g: int(sum(s[g][0].size for s in loaded)) for g in GROUPS}
        entries.setdefault(method, {})[level] = {**scales, "pixels": pixels,
                                                 "scenes": sorted({c["scene"] for c in chosen})}
    return {"format": CALIBRATION_FORMAT, "version": CALIBRATION_VERSION, "nominal": NOMINAL,
            "created": _dt.date.today().isoformat(), "spec": spec.get("name"), "spec_sha256": spec.get("sha256"),
            "replicates": spec["replicates"], "options": spec.get("options") or {}, "floors": FLOORS,
            "entries": entries}


def run_uncertainty_calibration(spec: dict, output: str | Path, *, device: str = "cpu", cache_dir: Path | None = None,
                                install: bool = False, events: Callable[..., None] | None = None) -> dict:
    """Run every case of ``spec`` (resumed), fit and write ``OUTPUT/calibration.json`` (and the shipped file with
    ``install``), and return ``{"cases": [...], "calibration": {...}}``."""
    output = Path(output)
    cases_dir = output / "cases"
    cases_dir.mkdir(parents=True, exist_ok=True)
    emit = events or (lambda *a, **k: None)
    factory = CaptureFactory(Path(cache_dir) if cache_dir else output / "cache", emit)
    cases = []
    scenes = [*spec["calibration_scenes"], *spec["check_scenes"]]
    plan = [(sc, nz, sd, m) for sc in scenes for nz in spec["noise"] for sd in spec["seeds"] for m in spec["methods"]]
    for index, (scene, noise, seed, method) in enumerate(plan):
        emit("case", index=index, total=len(plan), name=f"{scene['name']}/{noise['name']}/{seed}/{method['name']}")
        try:
            info = _run_case(factory, spec, scene, noise, seed, method, device=device, cases_dir=cases_dir)
        except Unavailable as exc:
            log.warning("skipped %s: %s", scene["name"], exc)
            continue
        cases.append(info)
    calibration = fit_calibration(cases, cases_dir, {s["name"] for s in spec["calibration_scenes"]}, spec=spec)
    atomic_write_json(output / "calibration.json", calibration)
    if install:
        atomic_write_json(CALIBRATION_FILE, calibration)
    atomic_write_json(output / "cases.json", cases)
    return {"cases": cases, "calibration": calibration}
