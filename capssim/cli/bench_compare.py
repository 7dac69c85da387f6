"""``capssim bench compare``: paired differences of two methods over the cases both scored
(:mod:`capssim.eval.benchmarks.compare`; docs/guides/benchmarks.md, "Development and test data")."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from capssim.cli._options import DeviceOption, JsonOption, ThreadsOption, echo_json


def compare(
    run_a: Path = typer.Argument(..., metavar="RUN_A", help="A benchmark output folder (its results.jsonl)."),
    run_b: Optional[Path] = typer.Argument(None, metavar="[RUN_B]",
                                           help="Another benchmark output folder (default: RUN_A)."),
    methods: Optional[List[str]] = typer.Option(None, "--method", "-m", metavar="LABEL",
                                                help="Method label of RUN_A (repeatable; default: every label "
                                                     "RUN_A and RUN_B share)."),
    against: Optional[str] = typer.Option(None, "--against", metavar="LABEL",
                                          help="Method label of RUN_B that every -m is compared with (default: "
                                               "the same label)."),
    metrics: Optional[List[str]] = typer.Option(None, "--metric", metavar="KEY",
                                                help="Metric of results.jsonl (repeatable; default: psnr_mean, "
                                                     "dolp_psnr)."),
    scenes: Optional[List[str]] = typer.Option(None, "--scene", metavar="PATTERN",
                                               help="Only the scenes matching this shell pattern (repeatable; "
                                                    "e.g. 'qiu-*')."),
    exclude_scenes: Optional[List[str]] = typer.Option(None, "--exclude-scene", metavar="PATTERN",
                                                       help="Leave out the scenes matching this shell pattern "
                                                            "(repeatable), e.g. a learned method's training "
                                                            "scenes."),
    cases: bool = typer.Option(False, "--cases", help="Also print every case's difference."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
    as_json: bool = JsonOption,
) -> None:
    """Paired comparison: per-case differences A - B, their mean with its paired standard error, wins and losses.

    A default ships only if it beats its simpler alternative on development data by more than one paired
    standard error (the last column). Examples: `capssim bench compare runs/new runs/old` (every shared
    label), `capssim bench compare runs/test -m caps-plus --against caps` (two methods of one run),
    `--exclude-scene 'qiu-*'` (leave out scenes, e.g. those a network was trained on).
    """
    from capssim.eval.benchmarks.compare import (
        DEFAULT_METRICS,
        check_metrics,
        comparison_markdown,
        load_run_records,
        paired_rows,
        select_scenes,
        summarize,
    )

    chosen = {"scenes": list(scenes or []), "exclude": list(exclude_scenes or []),
              "argument": "--scene" if scenes else "--exclude-scene"}
    records_a = select_scenes(load_run_records(run_a, argument="RUN_A"), **chosen)
    records_b = records_a if run_b is None else select_scenes(load_run_records(run_b, argument="RUN_B"), **chosen)
    wanted = _labels_to_compare(records_a, records_b, methods, against, two_runs=run_b is not None)
    keys = check_metrics(records_a + records_b, metrics) if metrics else list(DEFAULT_METRICS)
    comparisons, details = [], []
    for label in wanted:
        other = against or label
        for metric in keys:
            rows = paired_rows(records_a, records_b, label, other, metric)
            summary = summarize(rows, metric)
            comparisons.append((label, other, summary))
            details.append({"a": label, "b": other, **summary.to_dict(),
                            "cases": [{"case": c, "a": a, "b": b, "difference": a - b} for c, a, b in rows]})
    if as_json:
        echo_json({"run_a": str(run_a), "run_b": str(run_b or run_a), "scenes": chosen["scenes"],
                   "exclude_scenes": chosen["exclude"], "comparisons": details})
        return
    typer.echo(comparison_markdown(comparisons))
    if cases:
        for d in details:
            typer.echo(f"\n{d['a']} - {d['b']}, {d['metric']}:")
            for row in d["cases"]:
                typer.echo(f"  {row['case']}: {row['a']:.3f} - {row['b']:.3f} = {row['difference']:+.3f}")


def _labels_to_compare(records_a: list[dict], records_b: list[dict], methods, against, *, two_runs: bool) -> list:
    """The labels of RUN_A to compare (``-m``, or every label both runs share, or every other label of one run
    against ``--against``), each checked; an :class:`InputError` naming the option otherwise."""
    from capssim.errors import InputError

    labels_a = sorted({r["method"] for r in records_a})
    labels_b = sorted({r["method"] for r in records_b})
    wanted = list(methods or [])
    if not wanted:
        wanted = [m for m in labels_a if m in labels_b and (two_runs or against is not None)]
        if against is not None:
            wanted = [m for m in labels_a if m != against]
    for label in wanted:
        if label not in labels_a:
            raise InputError("--method", label, f"a method label of RUN_A ({', '.join(labels_a)})",
                             "Give a label that RUN_A's results.jsonl holds.")
    if against is not None and against not in labels_b:
        raise InputError("--against", against, f"a method label of RUN_B ({', '.join(labels_b)})",
                         "Give a label that RUN_B's results.jsonl holds.")
    if not wanted:
        raise InputError("--method", "nothing to compare", "a second run, or --against LABEL for two methods of "
                         "one run", "Example: capssim bench compare RUN -m caps-plus --against caps.")
    return wanted


def add_compare_command(bench_app: typer.Typer) -> None:
    """Register `capssim bench compare` on the `bench` group (called by capssim.cli.bench)."""
    bench_app.command("compare")(compare)
