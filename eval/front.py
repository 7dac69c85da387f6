"""The speed-against-error front of a suite run, in words: for each time budget, the best camera-array method and the
best DoFP method that fit in it, and the margin between them (the suites' results pages, issue 58).

Oracles (methods run on the true warps) are left out. A method's time is the median of its cases' ``wall_time_s`` (registration included); its score the mean over the
cases that every method of the run scored (so that the means compare like with like). The budgets are the
methods' own times, from the fastest: at a budget, a method counts when its time is at most the budget.
"""

from __future__ import annotations

import numpy as np

from capssim.reconstruct.registry import available_methods

__all__ = ["FRONT_METRICS", "front_rows", "front_table"]

#: the scores the front is stated in: (record metric, column label)
FRONT_METRICS = (("psnr_mean", "PSNR"), ("dolp_psnr", "DoLP PSNR"))


def _oracle(record: dict) -> bool:
    """A case run on the capture's true warps (an oracle no user has, e.g. ``caps-true-warps``): not on the front."""
    return str((record.get("registration") or {}).get("source", "")).startswith("true")


def _summaries(records: list[dict]) -> dict[str, dict]:
    """``{method: {"kind", "time_s", metric: mean}}`` over the (scene, noise, seed) cases every method scored."""
    ok = [r for r in records if r.get("status") == "ok" and r.get("metrics") and not _oracle(r)]
    methods = sorted({r["method"] for r in ok})
    cases = {m: {(r["scene"], r["noise"], r["seed"]): r for r in ok if r["method"] == m} for m in methods}
    common = set.intersection(*(set(c) for c in cases.values())) if cases else set()
    kinds = {name: spec.input_kind for name, spec in available_methods().items()}
    out = {}
    for m in methods:
        chosen = [cases[m][key] for key in sorted(common)]
        name = chosen[0].get("method_name", m) if chosen else m
        if not chosen or name not in kinds:
            continue
        out[m] = {"kind": kinds[name], "time_s": float(np.median([r["wall_time_s"] for r in chosen])),
                  "cases": len(chosen)}
        for metric, _ in FRONT_METRICS:
            values = [r["metrics"].get(metric) for r in chosen if r["metrics"].get(metric) is not None]
            out[m][metric] = float(np.mean(values)) if values else None
    return out


def front_rows(records: list[dict], *, metric: str = "psnr_mean") -> list[dict]:
    """One row per time budget at which the leader of either kind changes: ``budget_s``, ``array`` and ``dofp``
    (the best method of each kind within the budget by ``metric``, or None) with their scores, and ``margin``
    (array - DoFP in ``metric``, None when one kind has no method yet)."""
    summary = _summaries(records)
    rows, last = [], None
    for budget in sorted({s["time_s"] for s in summary.values()}):
        best = {}
        for kind in ("caps", "dofp"):
            inside = [(s[metric], m) for m, s in summary.items() if s["kind"] == kind and s["time_s"] <= budget
                      and s[metric] is not None]
            best[kind] = max(inside)[1] if inside else None
        if (best["caps"], best["dofp"]) == last:
            continue
        last = (best["caps"], best["dofp"])
        row = {"budget_s": budget, "array": best["caps"], "dofp": best["dofp"], "margin": None,
               "scores": {m: {k: summary[m][k] for k, _ in FRONT_METRICS} for m in last if m is not None}}
        if best["caps"] and best["dofp"]:
            row["margin"] = {k: summary[best["caps"]][k] - summary[best["dofp"]][k] for k, _ in FRONT_METRICS
                             if summary[best["caps"]][k] is not None and summary[best["dofp"]][k] is not None}
        rows.append(row)
    return rows


def front_table(records: list[dict]) -> str | None:
    """The front as a Markdown table (leaders by 12-channel PSNR; DoLP PSNR beside), or None when the run lacks a
    camera-array or a DoFP method."""
    rows = front_rows(records)
    if not rows or not any(r["margin"] for r in rows):
        return None

    def cell(method, row):
        if method is None:
            return "none fits"
        scores = row["scores"][method]
        return f"`{method}` ({scores['psnr_mean']:.2f} / {scores['dolp_psnr']:.2f} dB)"

    lines = ["| time budget | best camera-array method (PSNR / DoLP) | best DoFP method (PSNR / DoLP) | "
             "array - DoFP (PSNR / DoLP) |", "|---:|---|---|---:|"]
    for r in rows:
        margin = r["margin"] or {}
        text = " / ".join(f"{margin[k]:+.2f}" for k, _ in FRONT_METRICS if k in margin)
        lines.append(f"| <= {r['budget_s']:.2f} s | {cell(r['array'], r)} | {cell(r['dofp'], r)} | "
                     f"{text + ' dB' if text else '-'} |")
    return "\n".join(lines)
