"""Regression baselines of a benchmark suite: write one, check a run against one.

:func:`check_against_baseline` compares every quality metric of every case present in both the
baseline and the run with its stored value: a higher-is-better metric fails when it falls more
than its tolerance below, a lower-is-better one when it rises more than its tolerance above
(:data:`DEFAULT_TOLERANCES`, stored in the baseline file and editable there). Timings are never a
failure (shared CI machines are too noisy); they are printed with their ratio to the baseline.
Baseline cases skipped for missing data (``../shared`` absent, renderer unavailable) are listed
and not compared; a case that errors, a method that is no longer registered, a run that scored
nothing, or a run that compares nothing fails.

A baseline file is checked against :data:`BASELINE_SPEC` when it is loaded (:func:`load_baseline`),
before the run: tolerances must be finite numbers >= 0, metrics numbers, unknown keys are refused
(one :class:`~capssim.files.schema.ConfigError` line). :func:`write_baseline` merges this run's cases into
an existing baseline of the same suite (the cases this run did not score are kept, and so are the
file's tolerances) unless ``replace`` (``--replace-baseline``) is given.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from pathlib import Path

from capssim.errors import InputError
from capssim.files.imageio import atomic_write_json, check_output_file
from capssim.files.schema import (
    AnyMapping,
    ConfigError,
    Integer,
    Mapping,
    Nullable,
    Number,
    String,
    load_json_file,
    validate,
)

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


class JsonNumber(Number):
    """A finite JSON number (a string such as ``"0.1"`` is refused: JSON has numbers)."""

    def check(self, value, path):
        if isinstance(value, str):
            raise ConfigError(path, repr(value), f"{self.description} (not a string)", "Remove the quotes.")
        return super().check(value, path)


BASELINE_SPEC = Mapping({
    "schema": String(choices=[BASELINE_SCHEMA]),
    "version": Integer(minimum=1, maximum=1),
    "suite": String(),
    "suite_sha256": Nullable(String()),
    "created": Nullable(String()),
    "environment": Nullable(AnyMapping("the environment of the run")),
    "tolerances": Mapping({k: JsonNumber(minimum=0) for k in DEFAULT_TOLERANCES},
                          what="tolerances (" + ", ".join(DEFAULT_TOLERANCES) + ": finite numbers >= 0)"),
    "notes": Nullable(String()),
    "cases": Mapping(extra=Mapping({
        "metrics": Mapping(extra=Nullable(JsonNumber()), what="metrics (name: number)"),
        "wall_time_s": Nullable(JsonNumber(minimum=0)),
        "render_variant": Nullable(String()),
    }, required=("metrics",), what="a case {metrics, wall_time_s, render_variant}"),
        what="cases (scene/noise/seedN/method: {metrics, ...})"),
}, required=("schema", "suite", "cases"), what="a baseline written by --update-baseline")


def load_baseline(path: str | Path, *, argument: str = "--check") -> dict:
    """Read and validate a baseline file (:data:`BASELINE_SPEC`); one :class:`ConfigError` line if it is
    missing or invalid. Returns the file's content as written."""
    path = Path(path)
    if not path.is_file():
        raise InputError(argument, f"{str(path)!r} ({'a folder' if path.is_dir() else 'no such file'})",
                         "an existing baseline JSON", "Create it with: capssim bench suite NAME -o OUT "
                                                      "--update-baseline PATH")
    base = load_json_file(path, kind="baseline", example="eval/baselines/quick.json")
    validate(BASELINE_SPEC, base, config_file=path, kind="baseline")
    return base


def baseline_to_update(path: str | Path, spec: dict, *, replace: bool = False) -> dict | None:
    """Check, before the run, that ``--update-baseline PATH`` can be written: the existing baseline of the
    same suite to merge into (None: none, or ``replace``). Another suite's or an invalid file is refused
    unless ``replace``."""
    check_output_file(path, argument="--update-baseline")
    path = Path(path)
    if replace or not path.exists():
        return None
    try:
        base = load_baseline(path, argument="--update-baseline")
    except ConfigError as exc:
        raise ConfigError(exc.key_path, exc.received, exc.valid, (exc.fix + " " if exc.fix else "")
                          + "Or add --replace-baseline to overwrite it.", config_file=exc.config_file,
                          kind=exc.kind) from None
    if base["suite"] != spec["name"]:
        raise InputError("--update-baseline", f"{str(path)!r} (the baseline of suite {base['suite']!r})",
                         f"a baseline of suite {spec['name']!r} to merge into, or a new file",
                         "Choose another path, or add --replace-baseline to overwrite it.")
    return base


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


def write_baseline(run: BenchRun, path: str | Path, *, previous: dict | None = None) -> tuple[int, int]:
    """Store this run's metrics as the regression baseline (atomic), merged into ``previous`` (the existing
    baseline of :func:`baseline_to_update`: its other cases and its tolerances are kept).

    Returns ``(cases written, cases kept from previous)``.
    """
    cases = {}
    for r in run.ok_records():
        cases[r["key"]] = {"metrics": {k: v for k, v in r["metrics"].items() if v is not None},
                           "wall_time_s": r.get("wall_time_s"),
                           "render_variant": (r.get("capture_info") or {}).get("render_variant")}
    if not cases:
        raise InputError("--update-baseline", "a run without any successful case", "at least one scored case")
    kept = {k: v for k, v in (previous or {}).get("cases", {}).items() if k not in cases}
    merged = {k: cases.get(k, v) for k, v in (previous or {}).get("cases", {}).items()}
    merged.update(cases)
    tolerances = {**DEFAULT_TOLERANCES, **(previous or {}).get("tolerances", {})}
    baseline = {"schema": BASELINE_SCHEMA, "version": 1, "suite": run.spec["name"], "suite_sha256": run.spec["sha256"],
                "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "environment": run.environment, "tolerances": tolerances,
                "notes": "Regenerate with: capssim bench suite NAME -o OUT --update-baseline PATH (merges; "
                         "--replace-baseline starts afresh). Tolerances may be edited here (finite, >= 0); "
                         "timings are informational only.",
                "cases": merged}
    atomic_write_json(path, baseline)
    return len(merged), len(kept)


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


def check_against_baseline(run: BenchRun, baseline: str | Path | dict) -> Verdict:
    """Compare a run with a stored baseline (a path, or :func:`load_baseline`'s result; module docstring
    for the rules)."""
    base = baseline if isinstance(baseline, dict) else load_baseline(baseline)
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
    if not run.ok_records():
        failures.append("nothing scored: every case of this run was skipped or failed")
    if not compared:
        failures.append("no case could be compared with the baseline (all skipped or missing)")
    return Verdict(passed=not failures, failures=failures, compared=compared, not_compared=not_compared,
                   new_cases=new_cases, improvements=improvements, timings=timings, notes=notes)
