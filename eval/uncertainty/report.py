"""The coverage report of an uncertainty calibration (``OUTPUT/report.md``): per method and noise level, on the check
scenes only (never fitted on), the coverage of the calibrated 90 % intervals per group, pooled over the scored
pixels and per scene (its range), their mean width and the AUSE of the 12 channels (mean over the check cases;
:func:`capssim.eval.uncertainty_scores.sparsification`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capssim.files.imageio import atomic_write_text
from capssim.reconstruct.uncertainty.conformal import GROUPS, NOMINAL

from ..uncertainty_scores import sparsification
from .calibrate import load_case_scores

__all__ = ["check_rows", "write_uncertainty_report"]

def check_rows(result: dict, spec: dict, cases_dir: Path) -> list[dict]:
    """One row per (method, noise key) with the calibration's scales: ``coverage``, ``coverage_range`` (per scene),
    ``width`` per group and ``scenes``, over the check scenes' cases."""
    check = {s["name"] for s in spec["check_scenes"]}
    rows = []
    for method, levels in result["calibration"]["entries"].items():
        for level, entry in levels.items():
            cases = [c for c in result["cases"] if c["method"] == method and c["noise_key"] == level
                     and c["scene"] in check]
            if not cases:
                continue
            loaded = [load_case_scores(cases_dir, c["key"]) for c in cases]
            row = {"method": method, "noise": level, "scenes": sorted({c["scene"] for c in cases}), "coverage": {},
                   "coverage_range": {}, "width": {}, "scales": {g: entry[g] for g in GROUPS}}
            for group in GROUPS:
                q = entry[group]
                scores = [s[group][0] for s in loaded]
                pooled = np.concatenate(scores)
                row["coverage"][group] = float(np.mean(pooled <= q)) if pooled.size else None
                per = [float(np.mean(s <= q)) for s in scores if s.size]
                row["coverage_range"][group] = [min(per), max(per)] if per else None
                spreads = np.concatenate([s[group][1] for s in loaded])
                half = q * spreads.astype(np.float64)
                row["width"][group] = float(np.mean(np.minimum(2 * half, 180.0) if group == "AoP" else 2 * half))
            curves = [sparsification(s["12ch"][0].astype(np.float64) * s["12ch"][1], s["12ch"][1]) for s in loaded]
            row["ause_12ch"] = float(np.mean([c.ause for c in curves if c is not None])) if any(curves) else None
            rows.append(row)
    return rows


def write_uncertainty_report(output: Path, result: dict, spec: dict, *, command: str | None = None,
                             date: str | None = None) -> Path:
    """``OUTPUT/report.md``: the check scenes' coverage table (module docstring), with the run's date and command."""
    rows = check_rows(result, spec, Path(output) / "cases")
    lines = [f"# Uncertainty calibration `{spec['name']}`", ""]
    if date or command:
        lines += [f"Run on {date or 'an unknown date'} with `{command or 'capssim bench uncertainty'}`.", ""]
    calibration_scenes = ", ".join(s["name"] for s in spec["calibration_scenes"])
    check_scenes = ", ".join(s["name"] for s in spec["check_scenes"])
    lines += [f"Fitted on: {calibration_scenes}. Checked on (never fitted on): {check_scenes}. "
              f"{spec['replicates']} replicates; nominal coverage {NOMINAL:.0%}.", "",
              "| method | noise | " + " | ".join(f"{g} coverage (per scene)" for g in GROUPS) + " | "
              + " | ".join(f"{g} width" for g in GROUPS) + " | 12ch AUSE |",
              "|---|---|" + "---:|" * (2 * len(GROUPS) + 1)]
    for row in rows:
        cover = [f"{row['coverage'][g]:.3f} ({row['coverage_range'][g][0]:.2f}-{row['coverage_range'][g][1]:.2f})"
                 if row["coverage"][g] is not None else "n/a" for g in GROUPS]
        width = [f"{row['width'][g]:.4g}" + (" deg" if g == "AoP" else "") for g in GROUPS]
        ause = "n/a" if row["ause_12ch"] is None else f"{row['ause_12ch']:.3f}"
        lines.append(f"| {row['method']} | {row['noise']} | " + " | ".join(cover + width) + f" | {ause} |")
    path = Path(output) / "report.md"
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
