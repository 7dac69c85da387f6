"""Paired comparison of two methods over the same cases: the protocol by which a default ships.

Two benchmark runs (or two methods of one run) scored the same cases ``(scene, noise, seed)``. For a metric
``q`` (e.g. ``psnr_mean``, dB) the per-case differences ``d_i = q_A,i - q_B,i`` over the ``n`` cases both scored
give

    mean  d = (1/n) sum_i d_i,        paired standard error  se = std(d_i, ddof=1) / sqrt(n),

and the wins, losses and ties of A (a tie: ``|d_i| <= tie``). A is said to beat B when ``mean - se > 0``: the
rule of the project for a default (docs: guides/benchmarks.md, "Development and test data"): it ships only if
it beats its simpler alternative on development data by more than its paired standard error. The pairing
removes what the cases share (a hard scene is hard for both), which is why it is far tighter than comparing the
two means (Student, "The probable error of a mean", Biometrika 6(1) 1908; the paired t statistic is
``mean / se``).

:func:`paired_rows` pairs the records, :func:`summarize` computes the statistics, :func:`comparison_markdown`
writes a table (``capssim bench compare``, and the results pages' "Paired comparison" section).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from capssim.errors import InputError

from .results import read_results

__all__ = ["DEFAULT_METRICS", "PairedSummary", "check_metrics", "comparison_markdown", "load_run_records",
           "paired_rows", "summarize"]

#: the metrics compared by default: the 12-channel PSNR and the DoLP PSNR (dB; higher is better)
DEFAULT_METRICS = ("psnr_mean", "dolp_psnr")
#: metrics where lower is better (the sign of a win flips)
LOWER_IS_BETTER = frozenset({"aop_rmse_deg", "aop_mae_deg"})
#: a difference at most this large (the metric's units) is a tie
TIE = 1e-3


@dataclass(frozen=True)
class PairedSummary:
    """The statistics of paired differences ``A - B`` of one metric (module docstring)."""

    metric: str
    n: int
    mean: float
    se: float
    wins: int
    losses: int
    ties: int
    worst: float
    worst_case: str

    @property
    def beats(self) -> bool:
        """A is better than B by more than one paired standard error (in the metric's better direction)."""
        sign = -1.0 if self.metric in LOWER_IS_BETTER else 1.0
        return self.n >= 2 and sign * self.mean - self.se > 0

    def to_dict(self) -> dict:
        return {"metric": self.metric, "n": self.n, "mean": self.mean, "se": self.se, "wins": self.wins,
                "losses": self.losses, "ties": self.ties, "worst": self.worst, "worst_case": self.worst_case,
                "beats": self.beats}


def load_run_records(run: str | Path, *, argument: str = "RUN") -> list[dict]:
    """The scored records of a benchmark run folder (its ``results.jsonl``) or of a results file itself."""
    path = Path(run)
    results = path / "results.jsonl" if path.is_dir() else path
    if not results.is_file():
        raise InputError(argument, str(run), "a benchmark output folder holding results.jsonl (or that file)",
                         "Give the -o folder of a finished 'capssim bench suite' run.")
    records = [r for r in read_results(results).values() if r.get("status") == "ok"]
    if not records:
        raise InputError(argument, str(run), "a run with at least one scored case", "Run the suite first.")
    return records


def select_scenes(records: list[dict], *, scenes: list[str] | tuple = (), exclude: list[str] | tuple = (),
                  argument: str = "--scene") -> list[dict]:
    """The records whose scene matches one of ``scenes`` (shell patterns, e.g. ``qiu-*``; none: every scene) and
    none of ``exclude``. Leaving out the scenes a learned method was trained on gives a development comparison
    of two weight files that is not a memory test. An :class:`InputError` when nothing is left."""
    from fnmatch import fnmatchcase

    kept = [r for r in records
            if (not scenes or any(fnmatchcase(str(r["scene"]), p) for p in scenes))
            and not any(fnmatchcase(str(r["scene"]), p) for p in exclude)]
    if records and not kept:
        names = sorted({str(r["scene"]) for r in records})
        shown = ", ".join(names[:12]) + (f", ... ({len(names)} in all)" if len(names) > 12 else "")
        given = " ".join([*(f"--scene {p}" for p in scenes), *(f"--exclude-scene {p}" for p in exclude)])
        raise InputError(argument, given, f"patterns that keep at least one scene of the run ({shown})",
                         "Match a scene name above, e.g. --scene 'qiu-*', or exclude fewer.")
    return kept


def check_metrics(records: list[dict], metrics, *, argument: str = "--metric") -> list[str]:
    """``metrics`` as a list, each checked to be a numeric metric of at least one of ``records``; an
    :class:`InputError` naming ``argument`` (and listing the run's metrics) otherwise."""
    known = sorted({k for r in records for k, v in (r.get("metrics") or {}).items() if isinstance(v, (int, float))})
    for metric in metrics:
        if metric not in known:
            shown = ", ".join(known[:16]) + (f", ... ({len(known)} in all)" if len(known) > 16 else "")
            raise InputError(argument, metric, f"a metric of the runs' records ({shown})",
                             "Give a key of a record's 'metrics', e.g. --metric psnr_mean.")
    return list(metrics)


def _case(record: dict) -> tuple:
    return (str(record["scene"]), str(record["noise"]), int(record.get("seed", 0)))


def paired_rows(records_a: list[dict], records_b: list[dict], method_a: str, method_b: str,
                metric: str) -> list[tuple[str, float, float]]:
    """``[(case, value of A, value of B)]`` for every case both methods scored with a finite ``metric``, in case
    order; ``case`` reads ``scene / noise / seed``."""
    def values(records, method):
        out = {}
        for r in records:
            value = (r.get("metrics") or {}).get(metric)
            if r.get("method") == method and isinstance(value, (int, float)) and math.isfinite(value):
                out[_case(r)] = float(value)
        return out

    a, b = values(records_a, method_a), values(records_b, method_b)
    return [(f"{c[0]} / {c[1]} / {c[2]}", a[c], b[c]) for c in sorted(set(a) & set(b))]


def summarize(rows: list[tuple[str, float, float]], metric: str, *, tie: float = TIE) -> PairedSummary:
    """:class:`PairedSummary` of ``rows`` (:func:`paired_rows`); ``se`` is NaN for fewer than two cases."""
    diffs = [a - b for _, a, b in rows]
    n = len(diffs)
    if n == 0:
        return PairedSummary(metric, 0, math.nan, math.nan, 0, 0, 0, math.nan, "")
    mean = sum(diffs) / n
    se = math.sqrt(sum((d - mean) ** 2 for d in diffs) / (n - 1) / n) if n > 1 else math.nan
    sign = -1.0 if metric in LOWER_IS_BETTER else 1.0
    wins = sum(sign * d > tie for d in diffs)
    losses = sum(sign * d < -tie for d in diffs)
    worst_index = min(range(n), key=lambda i: sign * diffs[i])
    return PairedSummary(metric, n, mean, se, wins, losses, n - wins - losses, diffs[worst_index],
                         rows[worst_index][0])


def comparison_markdown(comparisons: list[tuple[str, str, PairedSummary]]) -> str:
    """A Markdown table of ``[(A label, B label, summary)]``: one row each."""
    lines = ["| A | B | metric | cases | mean A - B | paired SE | A wins / losses / ties | worst case (A - B) | "
             "A beats B by > 1 SE |", "|---|---|---|---|---|---|---|---|---|"]
    for a, b, s in comparisons:
        if s.n == 0:
            lines.append(f"| {a} | {b} | {s.metric} | 0 | - | - | - | - | - |")
            continue
        se = "-" if math.isnan(s.se) else f"{s.se:.3f}"
        lines.append(f"| {a} | {b} | {s.metric} | {s.n} | {s.mean:+.3f} | {se} | {s.wins} / {s.losses} / {s.ties} "
                     f"| {s.worst:+.3f} ({s.worst_case}) | {'yes' if s.beats else 'no'} |")
    return "\n".join(lines)
