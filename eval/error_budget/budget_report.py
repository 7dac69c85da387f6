"""The error budget as a reader sees it: tables, a waterfall plot per case, the losses explained.

A loss of method A to method B (both as captured, same capture) decomposes exactly into the
difference of their ceilings and, per imperfection, the difference of what it costs each of them:

``B - A = (ceiling_B - ceiling_A) + sum over causes of (step_A(cause) - step_B(cause))``

(a rung a method does not have costs it 0). :func:`explain_loss` names the largest term: the rung
that explains the loss.
"""

from __future__ import annotations

import datetime
import io
from pathlib import Path

from capssim.files.imageio import atomic_write_bytes, atomic_write_text

from .findings import findings_section
from .ladder import STEP_CAUSE

LOSS_THRESHOLD_DB = 0.3
REFERENCE_METHOD = "caps"


def _fmt(value, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:+.{digits}f}" if digits < 0 else f"{value:.{digits}f}"


def _step(record: dict, to: str, key: str = "psnr_mean"):
    for s in record["steps"]:
        if s["to"] == to:
            return s[f"d_{key}"]
    return None


def ok(records: list[dict]) -> list[dict]:
    return [r for r in records if r.get("status") == "ok"]


def budget_table(records: list[dict], key: str = "psnr_mean", unit: str = "dB") -> str:
    """One row per case: as captured, each step, the ceiling and the second views, in ``key``."""
    head = ["scene", "method", f"as captured ({unit})", "registration", "model mismatch", "noise",
            f"ceiling ({unit})", "converged", "prior on truth"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in ok(records):
        steps = [_step(r, to, key) for to in ("true-warps", "model-exact", "noise-free")]
        views = r.get("views") or {}
        row = [r["scene"], r["method"], _fmt(r["rungs"][0]["scores"][key]),
               *("-" if s is None else f"{s:+.2f}" for s in steps), _fmt(r["ceiling"][key]),
               _fmt((views.get("converged") or {}).get("scores", {}).get(key)),
               _fmt((views.get("prior-on-truth") or {}).get("scores", {}).get(key))]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def loss_terms(loser: dict, winner: dict, key: str = "psnr_mean") -> dict:
    """``{term: dB}`` whose sum is ``winner - loser`` as captured (module docstring)."""
    terms = {"ceiling (the method's own prior and solver)": winner["ceiling"][key] - loser["ceiling"][key]}
    for to, cause in STEP_CAUSE.items():
        a, b = _step(loser, to, key), _step(winner, to, key)
        if a is None and b is None:
            continue
        terms[cause] = (a or 0.0) - (b or 0.0)
    return terms


def explain_loss(loser: dict, winner: dict, key: str = "psnr_mean") -> dict:
    """The loss of ``loser`` to ``winner`` as captured, its terms and the one that explains it."""
    loss = winner["rungs"][0]["scores"][key] - loser["rungs"][0]["scores"][key]
    terms = loss_terms(loser, winner, key)
    culprit = max(terms, key=lambda t: terms[t])
    return {"loss": loss, "terms": terms, "rung": culprit, "rung_db": terms[culprit],
            "residual": loss - sum(terms.values())}


def losses(records: list[dict], *, method: str = REFERENCE_METHOD, threshold: float = LOSS_THRESHOLD_DB) -> list[dict]:
    """Every case where ``method`` loses to another method of the same capture by more than ``threshold`` dB."""
    by_capture: dict[tuple, dict[str, dict]] = {}
    for r in ok(records):
        by_capture.setdefault((r["scene"], r["noise"], r["seed"]), {})[r["method"]] = r
    found = []
    for (scene, noise, seed), cases in by_capture.items():
        if method not in cases:
            continue
        for other, rec in cases.items():
            if other == method:
                continue
            explained = explain_loss(cases[method], rec)
            if explained["loss"] > threshold:
                found.append({"scene": scene, "noise": noise, "seed": seed, "winner": other, **explained})
    return found


def losses_text(records: list[dict]) -> str:
    rows = losses(records)
    if not rows:
        return f"`{REFERENCE_METHOD}` loses to no other method by more than {LOSS_THRESHOLD_DB} dB."
    lines = ["| scene | wins over caps | loss (dB) | explained by | its dB | the other terms (dB) |",
             "|---|---|---|---|---|---|"]
    for x in rows:
        others = "; ".join(f"{t}: {v:+.2f}" for t, v in x["terms"].items() if t != x["rung"])
        lines.append(f"| {x['scene']} | {x['winner']} | {x['loss']:.2f} | {x['rung']} | {x['rung_db']:+.2f} | "
                     f"{others} |")
    return "\n".join(lines)


def plot_name(record: dict) -> str:
    safe = lambda s: "".join(c if c.isalnum() or c in "-_" else "-" for c in str(s))  # noqa: E731
    return f"waterfall-{safe(record['scene'])}-{safe(record['noise'])}-s{record['seed']}-{safe(record['method'])}.png"


def waterfall_plot(record: dict, path: Path, key: str = "psnr_mean") -> Path:
    """The ladder of one case as a waterfall: the as-captured bar, one step per rung (labelled with its
    dB), the ceiling bar; PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    start, ceiling = record["rungs"][0]["scores"][key], record["ceiling"][key]
    labels, bottoms, heights, colours, texts = ["as captured"], [0.0], [start], ["#4c72b0"], [f"{start:.2f}"]
    level = start
    for s in record["steps"]:
        d = s[f"d_{key}"] or 0.0
        labels.append(s["cause"].split(" (")[0])
        bottoms.append(min(level, level + d))
        heights.append(abs(d))
        colours.append("#55a868" if d >= 0 else "#c44e52")
        texts.append(f"{d:+.2f}")
        level += d
    labels.append("ceiling")
    bottoms.append(0.0)
    heights.append(ceiling)
    colours.append("#8172b2")
    texts.append(f"{ceiling:.2f}")
    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    ax.bar(range(len(labels)), heights, bottom=bottoms, color=colours)
    for i, (b, h, t) in enumerate(zip(bottoms, heights, texts)):
        ax.text(i, b + h, t, ha="center", va="bottom", fontsize=8)
    low = min(b for b, h in zip(bottoms, heights) if b > 0) if any(b > 0 for b in bottoms) else 0.0
    ax.set_ylim(max(0.0, min(low, start, ceiling) - 3.0), max(start, ceiling, level) + 2.0)
    ax.set_xticks(range(len(labels)), labels, fontsize=8)
    ax.set_ylabel("12-channel mean PSNR (dB)")
    ax.set_title(f"{record['scene']} / {record['noise']}: {record['method']}", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    buffer = io.BytesIO()  # written whole or not at all: a full disk leaves no half-written plot nor temporary
    fig.savefig(buffer, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
    return path


INTRO = ("Rungs, in order: as captured -> true warps (registration) -> model-exact capture (model "
         "mismatch) -> noise-free (noise) -> ceiling. Each step is the score gained by replacing that "
         "one imperfection with the truth; the steps sum to ceiling - as captured. 'converged': the "
         "ceiling case with 4x the iterations; 'prior on truth': NLSTR's estimate of the true image.")


def suite_section(run, *, plots: dict[str, str], level: str = "##") -> str:
    """The tables, the explained losses and the waterfalls of one suite's run."""
    recs = run.records
    failed = [r for r in recs if r.get("status") != "ok"]
    parts = [f"{level} 12-channel mean PSNR (dB)", "", budget_table(recs), "",
             f"{level} Intensity (S0) PSNR (dB)", "", budget_table(recs, "s0_psnr"), "",
             f"{level} DoLP PSNR (dB)", "", budget_table(recs, "dolp_psnr"), "",
             f"{level} AoP mean absolute error (deg; lower is better)", "", budget_table(recs, "aop_mae_deg", "deg"), "",
             f"{level} Where `{REFERENCE_METHOD}` loses by more than {LOSS_THRESHOLD_DB} dB", "", losses_text(recs), ""]
    if plots:
        parts += [f"{level} Waterfalls", ""] + [f"![{label}]({src})" for label, src in plots.items()] + [""]
    if failed:
        parts += [f"{level} Cases not scored", ""]
        parts += [f"- {r['key']}: {r['status']}: {r.get('reason', '')}" for r in failed] + [""]
    notes = getattr(run, "notes", None)
    if notes:  # a fallback scene used, a handed-over folder (the case runner's notes)
        parts += [f"{level} Notes", ""] + [f"- {n}" for n in notes] + [""]
    return "\n".join(parts)


def write_report(run, output: Path, *, plots: bool = True) -> Path:
    """``output/budget.md`` and, with ``plots``, ``output/waterfall-*.png``; returns the report's path."""
    output = Path(output)
    made = {}
    if plots:
        for r in ok(run.records):
            made[r["key"]] = waterfall_plot(r, output / plot_name(r)).name
    path = output / "budget.md"
    atomic_write_text(path, f"# Error budget: suite {run.spec['name']}\n\n{INTRO}\n\n" + suite_section(run, plots=made))
    return path


def write_results_page(runs, page: Path, *, command: str, plots: bool = True, notes: str | None = None) -> Path:
    """The docs results page ``page`` of one or more suites' runs, plots beside it in ``<page stem>/``."""
    page = Path(page)
    folder = page.with_suffix("")
    dates = [str(r["finished"])[:10] for run in runs for r in run.records if r.get("finished")]
    run_date = max(dates) if dates else datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d")
    parts = ["# Error budget", "", f"Run on {run_date}. Regenerated by `{command}` (it resumes: only missing or "
             "changed cases run; add "
             "`--report-only` to rewrite this page from the stored `budget.jsonl` files without running anything).",
             "", INTRO, ""]
    if notes:
        parts += [notes, ""]
    parts += [findings_section(runs)]
    for run in runs:
        made = {}
        if plots:
            folder.mkdir(parents=True, exist_ok=True)
            for r in ok(run.records):
                name = f"{run.spec['name']}-{plot_name(r)}"
                source = run.output / plot_name(r)
                if not source.is_file():
                    waterfall_plot(r, source)
                atomic_write_bytes(folder / name, source.read_bytes())  # a full disk leaves no half a copy
                made[r["key"]] = f"{folder.name}/{name}"
        parts += [f"## Suite `{run.spec['name']}`", "", suite_section(run, plots=made, level="###")]
    atomic_write_text(page, "\n".join(parts) + "\n")
    return page


__all__ = ["budget_table", "explain_loss", "loss_terms", "losses", "waterfall_plot", "write_report",
           "write_results_page"]
