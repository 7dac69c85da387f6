"""What a benchmark run writes for people: ``report.md`` next to its results, and a results page for the docs site.

``report.md`` (:func:`write_report`): tables per scene and noise level, plots, skips, the
regression verdict. The results page (:func:`write_results_page`, ``docs/results/SUITE.md``):
the same metric and timing tables without plots or links outside the site, written atomically
and listed in the folder's ``index.md``.
"""

from __future__ import annotations

import datetime as _dt
import logging
import re
from collections import defaultdict
from pathlib import Path

import numpy as np

from capssim.captures.capture import read_capture
from capssim.files.imageio import atomic_write_text, read_tiff
from capssim.reconstruct.registry import available_methods
from capssim.reconstruct.uncertainty.maps import read_uncertainty

from . import plots as P
from .benchmarks.compare import DEFAULT_METRICS, comparison_markdown, paired_rows, summarize
from .front import front_table
from .uncertainty_plots import polarization_uncertainty_plot
from .uncertainty_scores import NOMINAL_COVERAGE, uncertainty_table

log = logging.getLogger(__name__)

#: columns of the per-group tables: (metric key, header, digits)
TABLE_COLUMNS = [
    ("psnr_mean", "PSNR", 2), ("psnr_gt_peak_mean", "PSNR/GT peak", 2), ("ssim_mean", "SSIM", 4),
    ("ssim_gt_peak_mean", "SSIM/GT peak", 4), ("s0_psnr", "S0", 2), ("s1_psnr", "S1", 2),
    ("s2_psnr", "S2", 2), ("dolp_psnr", "DoLP", 2), ("dolp_ssim", "DoLP SSIM", 3), ("aop_rmse_deg", "AoP RMSE", 2),
    ("aop_mae_deg", "AoP MAE", 2), ("mtf_magnification_hv", "SR mag. hv", 2),
    ("mtf_magnification_diagonal", "SR mag. diag", 2),
]
#: what the tables' columns mean (the header paragraph of report.md and of the results page)
TABLE_LEGEND = (
    "Means over seeds. PSNR in dB (12-channel mean; S0/S1/S2/DoLP pooled over R, G, B) and SSIM with data range 1 "
    "(full scale); PSNR/GT peak and SSIM/GT peak: the same with the data range = the ground truth's peak, i.e. the "
    "scene exposed to full scale (they still rank methods on a dark scene, where the fixed-peak PSNR reaches its "
    "100 dB cap and SSIM rounds to 1). AoP errors in degrees over the masked pixels; SR magnification from the "
    "Siemens-star MTF (limit resolution in cycles per Bayer sub-image pixel / 0.5). Time: the method's wall time "
    "in seconds. Memory: the method's own peak, i.e. how far the process's resident memory (RSS, sampled every "
    "5 ms) rose above its level just before the method (`peak_rss_delta_mb` in results.jsonl), after the memory "
    "that earlier cases freed was handed back to the system; one-time costs (torch's first use, imports) fall on "
    "the first method that needs them. The process's whole RSS, everything loaded before included, is "
    "`peak_rss_mb` there. CUDA peak (on a GPU): torch's largest allocation during the method.")
#: a scene whose ground-truth peak is below this fraction of full scale gets a dark-scene line in the report
DARK_SCENE_PEAK = 0.1


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_")


def _mean(values):
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def _fmt(v, digits=2):
    return "-" if v is None else f"{v:.{digits}f}"


def group_records(records: list[dict]) -> dict[tuple[str, str], list[dict]]:
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in records:
        if r["status"] == "ok":
            groups[(r["scene"], r["noise"])].append(r)
    return dict(groups)


#: the mark of a method's score on a suite its defaults were tuned on (:func:`tuned_labels`)
TUNED_MARK = "‡"
TUNED_LEGEND = (f"{TUNED_MARK}: the method's defaults were chosen on this suite (its `tuned_on`, "
                "`capssim reconstruct --list`): its scores here are not evidence of what it is worth elsewhere.")


def tuned_labels(spec: dict) -> set[str]:
    """The method labels of ``spec`` whose method lists the suite's name in its ``tuned_on``."""
    methods = available_methods()
    return {m.get("label", m.get("name")) for m in spec.get("methods", []) if isinstance(m, dict)
            and m.get("name") in methods and spec.get("name") in methods[m["name"]].tuned_on}


def paired_section(spec: dict, recs: list[dict]) -> list[str]:
    """The "Paired comparison" lines of a suite whose ``paired:`` names a method label: that method against every
    other method of the suite, per-case differences with their mean and paired standard error
    (:mod:`capssim.eval.benchmarks.compare`); ``[]`` without ``paired:``."""
    reference = spec.get("paired")
    if not reference:
        return []
    ok = [r for r in recs if r["status"] == "ok"]
    labels = [m["label"] if isinstance(m, dict) else str(m) for m in spec.get("methods", [])]
    rows = [(reference, label, summarize(paired_rows(ok, ok, reference, label, metric), metric))
            for metric in DEFAULT_METRICS for label in labels if label != reference]
    return ["## Paired comparison", "",
            f"`{reference}` against every other method over the cases both scored: per-case differences (dB), their "
            "mean and its paired standard error, wins / losses / ties (a tie: within 0.001 dB), and the worst case "
            f"(`capssim bench compare OUTPUT -m {reference} --against LABEL` gives the same and every case).", "",
            comparison_markdown(rows), ""]


def results_table(recs: list[dict], methods: list[str], tuned: set[str] = frozenset()) -> str:
    have = [c for c in TABLE_COLUMNS if any(r["metrics"].get(c[0]) is not None for r in recs)]
    cuda = any(r.get("cuda_peak_mb") is not None for r in recs)
    header = ["method"] + [h for _, h, _ in have] + ["time (s)", "memory (MB)"] + (["CUDA peak (MB)"] if cuda else [])
    header.append("seeds")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    by_method = defaultdict(list)
    for r in recs:
        by_method[r["method"]].append(r)
    for m in methods:
        rs = by_method.get(m)
        if not rs:
            continue
        cells = [f"{m} {TUNED_MARK}" if m in tuned else m] + [_fmt(_mean(r["metrics"].get(k) for r in rs), d)
                                                                for k, _, d in have]
        cells += [_fmt(_mean(r.get("wall_time_s") for r in rs), 2), _fmt(_mean(r.get("peak_rss_delta_mb") for r in rs), 0)]
        cells += [_fmt(_mean(r.get("cuda_peak_mb") for r in rs), 0)] if cuda else []
        cells.append(str(len(rs)))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def dark_scene_line(recs: list[dict]) -> str:
    """A line for a group whose ground truth peaks below :data:`DARK_SCENE_PEAK` of full scale, else ``""``."""
    peaks = [(r.get("metric_settings") or {}).get("gt_peak") for r in recs]
    peaks = [p for p in peaks if p is not None]
    if not peaks or max(peaks) >= DARK_SCENE_PEAK:
        return ""
    return (f"Dark scene: the ground truth peaks at {max(peaks):.3g} of full scale, so the fixed-peak PSNR and SSIM "
            "barely move between methods (PSNR is capped at 100 dB); compare PSNR/GT peak and SSIM/GT peak.")


def stage_table(recs: list[dict], methods: list[str]) -> str:
    stages = []
    for r in recs:
        for s in (r.get("stages_s") or {}):
            if s not in stages:
                stages.append(s)
    if not stages:
        return ""
    lines = ["| method | " + " | ".join(stages) + " | total |", "|" + "---|" * (len(stages) + 2)]
    for m in methods:
        rs = [r for r in recs if r["method"] == m]
        if not rs:
            continue
        cells = [_fmt(_mean((r.get("stages_s") or {}).get(s) for r in rs), 2) for s in stages]
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {_fmt(_mean(r.get('wall_time_s') for r in rs), 2)} |")
    return "\n".join(lines)


def _report_header(run, verdict) -> list[str]:
    """The report's title, run summary, substitutions and regression verdict."""
    spec, env, recs = run.spec, run.environment, run.records
    ok = [r for r in recs if r["status"] == "ok"]
    git = env.get("git", {})
    lines = [f"# capssim benchmark: suite `{spec['name']}`", ""]
    if spec.get("description"):
        lines += [str(spec["description"]).strip(), ""]
    lines += [
        f"- suite file: `{spec['path']}` (sha256 {spec['sha256'][:12]})",
        f"- cases: {len(recs)} planned, {len(ok)} scored, "
        f"{sum(r['status'] == 'skipped' for r in recs)} skipped, {run.n_errors} failed; this invocation took "
        f"{run.wall_time_s:.1f} s (cached captures and completed cases are reused)",
        f"- metric convention: `{recs[0]['convention'] if recs else spec.get('convention')}` "
        "(definitions: the scoring guide)",
        f"- git {git.get('revision') or 'unknown'}{' (dirty)' if git.get('dirty') else ''}; "
        f"CPU {env.get('cpu')} x{env.get('cpu_count')} (torch threads {env.get('torch_threads')}); "
        f"GPU {env.get('gpu') or 'none'}; device {env.get('device')}",
        "- versions: " + ", ".join(f"{k} {v}" for k, v in env.get("versions", {}).items()),
        "- timings are wall-clock on a possibly shared machine: compare them within one run only.",
        "",
    ]
    if run.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in run.notes] + [""]
    if verdict is not None:
        lines += ["## Regression check", "", "```", verdict.text(), "```", ""]
    return lines


def _speed_plots(ok: list[dict], plot_dir: Path, methods: list[str]) -> list[tuple[str, Path]]:
    """``(label, png)`` of the speed-vs-error plots that could be drawn (a failed plot is logged, not raised)."""
    drawn = []
    for metric, label, hib, name in (("psnr_mean", "PSNR (dB, 12-ch mean)", True, "speed_vs_psnr.png"),
                                     ("dolp_psnr", "DoLP PSNR (dB)", True, "speed_vs_dolp.png"),
                                     ("aop_rmse_deg", "AoP RMSE (deg)", False, "speed_vs_aop.png")):
        try:
            p = P.speed_vs_error(ok, plot_dir / name, metric=metric, label=label, higher_is_better=hib,
                                 methods=methods)
            if p:
                drawn.append((label, p))
        except Exception as exc:  # a plot must never lose the results
            log.warning("plot %s failed: %s", name, exc)
    return drawn


def _group_plots(scene: str, noise: str, rs: list[dict], methods: list[str], plot_dir: Path) -> list[str]:
    """The crops (and MTF curves) of one scene and noise level, at its first seed, as report lines."""
    lines: list[str] = []
    first_seed = min(r["seed"] for r in rs)
    rs0 = [r for r in rs if r["seed"] == first_seed]
    try:
        capture = read_capture(rs0[0]["capture"], require_gt=True)
        estimates = {}
        for m in methods:
            r = next((x for x in rs0 if x["method"] == m), None)
            if r is not None and Path(r["recon"]).is_file():
                estimates[m] = read_tiff(r["recon"])
        star = rs0[0].get("star")
        centre = None
        if star and star.get("center_rowcol") is None and rs0[0].get("gt_mtf"):
            centre = rs0[0]["gt_mtf"]["center_rowcol"]
        elif star:
            centre = star["center_rowcol"]
        if star and centre is not None:  # frame the star's fine core, where SR matters
            radius = 4 * star["cycles"] / np.pi  # sub-image Nyquist radius in HR px
            centre = (centre[0], centre[1] + 0.9 * radius)
        p = P.crops(capture.gt, estimates, plot_dir / f"crops_{_slug(scene)}_{_slug(noise)}.png",
                    title=f"{scene} / {noise} / seed {first_seed}", center_rowcol=centre)
        lines += [f"![crops {scene} {noise}](plots/{p.name})", ""]
        lines += _uncertainty_crops(scene, noise, rs0, methods, estimates, plot_dir)
        if any(r.get("mtf") for r in rs0):
            p = P.mtf_curves(rs0[0].get("gt_mtf"), {r["method"]: r["mtf"] for r in rs0 if r.get("mtf")},
                             plot_dir / f"mtf_{_slug(scene)}_{_slug(noise)}.png", title=f"{scene} / {noise}",
                             methods=methods)
            if p:
                lines += [f"![MTF {scene} {noise}](plots/{p.name})", ""]
    except Exception as exc:  # a plot must never lose the results
        log.warning("plots of %s/%s failed: %s", scene, noise, exc)
        lines += [f"(plots of this group failed: {exc})", ""]
    return lines


def _uncertainty_crops(scene: str, noise: str, rs0: list[dict], methods: list[str], estimates: dict,
                       plot_dir: Path) -> list[str]:
    """DoLP and AoP with their error bars, for each method of the group whose case made them (``uncertainty``)."""
    lines = []
    for m in methods:
        r = next((x for x in rs0 if x["method"] == m and x.get("uncertainty")), None)
        maps = None if r is None or m not in estimates else read_uncertainty(Path(r["recon"]).parent.parent, m)
        if maps is not None:
            p = polarization_uncertainty_plot(estimates[m], maps, plot_dir / f"bars_{_slug(scene)}_{_slug(noise)}_"
                                              f"{_slug(m)}.png", title=f"{m}: {scene} / {noise}")
            lines += [f"![error bars {m} {scene} {noise}](plots/{p.name})", ""]
    return lines


def front_section(ok: list[dict]) -> list[str]:
    """"The front" (:mod:`capssim.eval.front`): per time budget, the best camera-array and DoFP methods; [] when the
    run lacks one of the kinds."""
    table = front_table(ok)
    return [] if table is None else [
        "## The front: the best method of each kind per time budget", "",
        "Median time per case (registration included), mean scores over the cases every method scored; oracles "
        "(true warps) left out.", "", table, ""]


def _report_tail(recs: list[dict], ok: list[dict]) -> list[str]:
    """The skipped cases, the failed cases with their tracebacks, and the metric notes."""
    lines: list[str] = []
    skipped = [r for r in recs if r["status"] == "skipped"]
    if skipped:
        lines += ["## Skipped cases", "", "| case | reason |", "|---|---|"]
        lines += [f"| {r['key']} | {r.get('reason')} |" for r in skipped] + [""]
    errors = [r for r in recs if r["status"] == "error"]
    if errors:
        lines += ["## Failed cases", ""]
        for r in errors:
            lines += [f"### {r['key']}", "", "```", (r.get("traceback") or r.get("reason") or "").strip(), "```", ""]
    notes = sorted({n for r in ok for n in r.get("notes", [])})
    if notes:
        lines += ["## Metric notes", ""] + [f"- {n}" for n in notes] + [""]
    return lines


def write_report(run, output, *, verdict=None, plots: bool = True) -> Path:
    """Write ``OUTPUT/report.md`` (and ``OUTPUT/plots/*.png`` when ``plots``) of a suite run.

    Parameters
    ----------
    run : BenchRun
        The result of :func:`capssim.eval.benchmarks.suite.run_suite`.
    output : str or pathlib.Path
        The run's folder.
    verdict : optional
        A baseline comparison to print at the top.
    plots : bool
        Draw the per-group and speed-vs-error plots (matplotlib).

    Returns
    -------
    pathlib.Path
        The ``report.md`` path.
    """
    output = Path(output)
    plot_dir = output / "plots"
    methods = [m["label"] for m in run.spec["methods"]]
    recs = run.records
    ok = [r for r in recs if r["status"] == "ok"]
    tuned = tuned_labels(run.spec)
    lines = _report_header(run, verdict)
    lines += paired_section(run.spec, recs)
    lines += ["## Results", "", TABLE_LEGEND, ""] + ([TUNED_LEGEND, ""] if tuned else [])
    speed_plots = _speed_plots(ok, plot_dir, methods) if plots and ok else []
    for (scene, noise), rs in sorted(group_records(recs).items()):
        lines += [f"### {scene} / {noise}", "", results_table(rs, methods, tuned), ""]
        lines += [dark_scene_line(rs), ""] if dark_scene_line(rs) else []
        st = stage_table(rs, methods)
        if st:
            lines += ["Time per stage (s):", "", st, ""]
        if plots:
            lines += _group_plots(scene, noise, rs, methods, plot_dir)
    if speed_plots:
        lines += ["## Speed vs error", "",
                  "One point per method (mean over seeds); the dashed step line is the Pareto front "
                  "(no other method is both faster and better).", ""]
        lines += [f"![{label}](plots/{p.name})" for label, p in speed_plots] + [""]
    lines += front_section(ok)
    errors = uncertainty_table(ok, methods)
    if errors:
        lines += ["## Error bars", "", f"Coverage of the calibrated {NOMINAL_COVERAGE:.0%} intervals (mean over the "
                  "cases; capssim evaluate's groups and scored pixels), width and AUSE of the 12 channels.", "",
                  errors, ""]
    lines += _report_tail(recs, ok)
    path = output / "report.md"
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


def _environment_lines(run) -> list[str]:
    env = run.environment
    git = env.get("git", {})
    return [f"- git {git.get('revision') or 'unknown'}{' (with uncommitted changes)' if git.get('dirty') else ''}",
            f"- CPU {env.get('cpu')} x{env.get('cpu_count')} (torch threads {env.get('torch_threads')}); "
            f"GPU {env.get('gpu') or 'none'}; device {env.get('device')}",
            "- versions: " + ", ".join(f"{k} {v}" for k, v in env.get("versions", {}).items())]


def results_page(run, *, verdict=None, written: str | None = None) -> str:
    """Markdown results page of a run: metric and timing tables per scene and noise level."""
    spec, recs = run.spec, run.records
    methods = [m["label"] for m in spec["methods"]]
    ok = [r for r in recs if r["status"] == "ok"]
    lines = [f"# Results: suite `{spec['name']}`", ""]
    if spec.get("description"):
        lines += [" ".join(str(spec["description"]).split()), ""]
    lines += [f"Written by `capssim bench suite {spec['name']} --results-page PATH` on "
              f"{written or _dt.datetime.now(_dt.timezone.utc).strftime('%Y-%m-%d')}; the same command regenerates it.",
              "",
              f"- cases: {len(recs)} planned, {len(ok)} scored, {sum(r['status'] == 'skipped' for r in recs)} skipped, "
              f"{run.n_errors} failed",
              f"- metric convention: `{recs[0]['convention'] if recs else spec.get('convention')}`",
              *_environment_lines(run),
              "- timings are wall-clock seconds on a possibly shared machine: compare them within one page only.",
              ""]
    if verdict is not None:
        lines += [f"Regression check against the stored baseline: **{'passed' if verdict.passed else 'FAILED'}** "
                  f"({len(verdict.compared)} case(s) compared, {len(verdict.failures)} failure(s)).", ""]
    if run.notes:  # substitutions, and where a page's cases come from earlier runs
        lines += ["## Notes", ""] + [f"- {n}" for n in run.notes] + [""]
    tuned = tuned_labels(spec)
    lines += paired_section(spec, recs)
    lines += front_section([r for r in recs if r["status"] == "ok"])
    lines += ["## Results", "", TABLE_LEGEND, ""] + ([TUNED_LEGEND, ""] if tuned else [])
    for (scene, noise), rs in sorted(group_records(recs).items()):
        lines += [f"### {scene} / {noise}", "", results_table(rs, methods, tuned), ""]
        lines += [dark_scene_line(rs), ""] if dark_scene_line(rs) else []
        stages = stage_table(rs, methods)
        if stages:
            lines += ["Time per stage (s):", "", stages, ""]
    skipped = [r for r in recs if r["status"] == "skipped"]
    if skipped:
        lines += ["## Skipped cases", "", "| case | reason |", "|---|---|"]
        lines += [f"| {r['key']} | {r.get('reason')} |" for r in skipped] + [""]
    return "\n".join(lines).rstrip() + "\n"


def write_results_page(run, path: str | Path, *, verdict=None) -> Path:
    """Write :func:`results_page` to ``path`` (temp file, then rename) and list it in the folder's ``index.md``."""
    path = Path(path)
    atomic_write_text(path, results_page(run, verdict=verdict))
    index = path.parent / "index.md"
    if index.is_file():
        text = index.read_text()
        if f"]({path.name})" not in text:
            entry = f"- [Suite `{run.spec['name']}`]({path.name})"
            atomic_write_text(index, text.rstrip("\n") + ("\n\n" if "](" not in text else "\n") + entry + "\n")
    return path
