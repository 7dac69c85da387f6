"""Regression baselines of a benchmark suite: write one, check a run against one.

:func:`check_against_baseline` compares every quality metric of every case present in both the
baseline and the run with its stored value: a higher-is-better metric fails when it falls more
than its tolerance below, a lower-is-better one when it rises more than its tolerance above
(:data:`DEFAULT_TOLERANCES`, stored in the baseline file and editable there). Timings are never a
failure (shared CI machines are too noisy); they are printed with their ratio to the baseline.
Baseline cases skipped for missing data (``../shared`` absent, renderer unavailable) are listed
and not compared; a case that errors, a method that is no longer registered, or a run that
compares nothing fails.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field
from pathlib import Path

from capssim.errors import InputError
from capssim.imageio import atomic_write_json

from ..metric_records import metric_direction
from .suite import BenchRun

BASELINE_SCHEMA = "capssim.bench-baseline"

#: Allowed drop (or rise, for lower-is-better metrics) before a metric counts as a regression.
DEFAULT_TOLERANCES: dict[str, float] = {
    "psnr_db": 0.10,  # every PSNR-type metric, dB
    "ssim": 0.005,  # SSIM, DoLP SSIM
    "aop_deg": 0.25,  # AoP RMSE / MAE, degrees
    "mtf_magnification": 0.05,  # SR magnification (absolute)
    "mtf_limit": 0.0125,  # limit resolution, cycles per sub-image pixel (= 0.05 / 4)
    "lpips": 0.005,
}


def tolerance_for(metric: str, tolerances: dict[str, float]) -> float | None:
    """Tolerance of a metric, or None when it is not a checked quality metric."""
    head = metric.split(".", 1)[0]
    if head.startswith("mtf_magnification"):
        return tolerances["mtf_magnification"]
    if head.startswith("mtf_limit"):
        return tolerances["mtf_limit"]
    if metric_direction(metric) == 0:
        return None
    if "ssim" in head:
        return tolerances["ssim"]
    if "psnr" in head:
        return tolerances["psnr_db"]
    if head.startswith("aop_") and head.endswith("_deg"):
        return tolerances["aop_deg"]
    if head.startswith("lpips"):
        return tolerances["lpips"]
    return None


def write_baseline(run: BenchRun, path: str | Path) -> int:
    """Store this run's metrics as the regression baseline (atomic). Returns the number of cases."""
    cases = {}
    for r in run.ok_records():
        cases[r["key"]] = {"metrics": {k: v for k, v in r["metrics"].items() if v is not None},
                           "wall_time_s": r.get("wall_time_s"),
                           "render_variant": (r.get("capture_info") or {}).get("render_variant")}
    if not cases:
        raise InputError("update-baseline", "a run without any successful case", "at least one scored case")
    baseline = {"schema": BASELINE_SCHEMA, "version": 1, "suite": run.spec["name"], "suite_sha256": run.spec["sha256"],
                "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "environment": run.environment, "tolerances": dict(DEFAULT_TOLERANCES),
                "notes": "Regenerate with: capssim bench suite NAME -o OUT --update-baseline PATH. "
                         "Tolerances may be edited here; timings are informational only.",
                "cases": cases}
    atomic_write_json(path, baseline)
    return len(cases)


@dataclass
class Verdict:
    passed: bool
    failures: list[str]
    compared: list[str]
    not_compared: list[str]
    new_cases: list[str]
    improvements: list[str]
    timings: list[str]
    notes: list[str] = field(default_factory=list)

    def text(self) -> str:
        lines = [f"regression check: {'PASSED' if self.passed else 'FAILED'} "
                 f"({len(self.compared)} case(s) compared, {len(self.failures)} failure(s))"]
        lines += [f"  FAIL {f}" for f in self.failures]
        lines += [f"  note: {n}" for n in self.notes]
        lines += [f"  not compared: {n}" for n in self.not_compared]
        lines += [f"  new (not in baseline): {n}" for n in self.new_cases]
        if self.improvements:
            lines.append(f"  {len(self.improvements)} metric(s) improved beyond tolerance (consider --update-baseline):")
            lines += [f"    {i}" for i in self.improvements[:20]]
        lines += [f"  time {t}" for t in self.timings]
        return "\n".join(lines)


def check_against_baseline(run: BenchRun, baseline_path: str | Path) -> Verdict:
    """Compare a run with a stored baseline (module docstring for the rules)."""
    path = Path(baseline_path)
    if not path.is_file():
        raise InputError("check", str(path), "an existing baseline JSON",
                         "Create it with: capssim bench suite NAME -o OUT --update-baseline PATH")
    try:
        base = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError("check", f"corrupt JSON in {path} ({exc})", "a baseline written by --update-baseline") from exc
    if base.get("schema") != BASELINE_SCHEMA:
        raise InputError("check", f"{path} (schema {base.get('schema')!r})", f"a {BASELINE_SCHEMA} file")
    tolerances = {**DEFAULT_TOLERANCES, **base.get("tolerances", {})}
    current = {r["key"]: r for r in run.records}
    failures, compared, not_compared, improvements, timings = [], [], [], [], []
    notes = []
    if base.get("suite") != run.spec["name"]:
        failures.append(f"baseline is for suite {base.get('suite')!r}, this run is {run.spec['name']!r}")
    elif base.get("suite_sha256") != run.spec.get("sha256"):
        notes.append("the suite file changed since the baseline was written; only cases present in both are compared")
    base_git = (base.get("environment") or {}).get("git", {}).get("revision")
    if base_git:
        notes.append(f"baseline written at git {base_git[:12]} on {base.get('created', '?')}")
    for key, stored in sorted(base.get("cases", {}).items()):
        rec = current.get(key)
        if rec is None:
            not_compared.append(f"{key} (not in this run)")
            continue
        if rec["status"] == "skipped":
            if rec.get("skip_kind") == "data":
                not_compared.append(f"{key} (skipped: {rec.get('reason')})")
            else:
                failures.append(f"{key}: skipped ({rec.get('reason')})")
            continue
        if rec["status"] == "error":
            failures.append(f"{key}: error ({rec.get('reason')})")
            continue
        base_variant = stored.get("render_variant")
        run_variant = (rec.get("capture_info") or {}).get("render_variant")
        if base_variant and run_variant and base_variant != run_variant:
            # another Mitsuba variant draws other Monte-Carlo samples: not the same capture
            not_compared.append(f"{key} (rendered with {run_variant}, baseline with {base_variant})")
            continue
        compared.append(key)
        cur = rec["metrics"]
        for metric, ref in sorted(stored["metrics"].items()):
            tol = tolerance_for(metric, tolerances)
            direction = metric_direction(metric)
            if tol is None or direction == 0 or ref is None:
                continue
            value = cur.get(metric)
            if value is None:
                failures.append(f"{key} {metric}: was {ref:.4g}, now undefined/missing")
                continue
            change = (value - ref) * direction  # > 0 is better
            if change < -tol:
                failures.append(f"{key} {metric}: {ref:.4f} -> {value:.4f} "
                                f"({'fell' if direction > 0 else 'rose'} by {abs(value - ref):.4f}, tolerance {tol})")
            elif change > tol:
                improvements.append(f"{key} {metric}: {ref:.4f} -> {value:.4f}")
        t_ref, t_now = stored.get("wall_time_s"), rec.get("wall_time_s")
        if t_ref and t_now:
            timings.append(f"{key}: {t_now:.2f} s vs {t_ref:.2f} s baseline (x{t_now / t_ref:.2f}, not checked)")
    new_cases = sorted(k for k, r in current.items() if r["status"] == "ok" and k not in base.get("cases", {}))
    if not compared:
        failures.append("no case could be compared with the baseline (all skipped or missing)")
    return Verdict(passed=not failures, failures=failures, compared=compared, not_compared=not_compared,
                   new_cases=new_cases, improvements=improvements, timings=timings, notes=notes)
