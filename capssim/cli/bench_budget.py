"""``capssim bench budget``: the error budget of a suite's cases (docs/guides/benchmarks.md, "Error budget")."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from capssim.cli._options import DeviceOption, JsonOption, ThreadsOption, apply_compute, echo_json
from capssim.errors import InputError


def check_suite_names(specs: list[dict], suites: list[str]) -> None:
    """Several suites run each into OUTPUT/NAME: refuse two that share a ``name:`` (one would replace the other)."""
    seen: dict[str, str] = {}
    for given, spec in zip(suites, specs):
        if spec["name"] in seen:
            raise InputError("SUITE", f"{seen[spec['name']]} and {given} (both named {spec['name']!r})",
                             "suites with distinct names (each runs into OUTPUT/NAME)",
                             "Give one of them another 'name:', or run them in separate calls with different -o.")
        seen[spec["name"]] = given


def _checked_suites(suites: list[str], *, methods, scenes, workers, scheduler, cache,
                    report_only: bool) -> list[dict]:
    """Every suite loaded and checked (names, ``-m``, ``--scene``, ``--workers``, ``--scheduler``, ``--cache``)
    before any work."""
    from capssim.eval.benchmarks.executors import check_execution
    from capssim.eval.benchmarks.suite import load_suite  # start-up time: pulls torch and every method
    from capssim.eval.error_budget.runner import check_budget

    specs = [load_suite(name) for name in suites]
    check_suite_names(specs, suites)
    check_execution(workers=workers, scheduler=scheduler, cache=cache)
    if not report_only:
        for spec in specs:
            check_budget(spec, methods=methods or None, scenes=scenes or None, workers=workers, scheduler=scheduler)
    return specs


def _events(say):
    """The runner's ``events`` callback: a line per finished case, and its notes, skips and errors."""

    def events(kind: str, **info) -> None:
        if kind == "done":
            say(f"  {info['label']}: {info['status']}")
        elif kind in ("note", "skip", "error"):
            say(info["message"])

    return events


def _results_page(runs, results_page: Path, suites, output, methods, scenes, views: bool, no_plots: bool) -> Path:
    """Write ``--results-page`` from the runs, with the command that regenerates it."""
    from capssim.eval.error_budget.budget_report import write_results_page

    picked = "".join(f" -m {m}" for m in methods or ()) + "".join(f" --scene {x}" for x in scenes or ())
    command = ("capssim bench budget " + " ".join(suites) + f" -o {output}{picked}" + (" --views" if views else "")
               + f" --results-page {results_page}")
    notes_page = Path(results_page).parent.parent / "notes" / "error-budget.md"
    notes = ("What the budget finds, case by case, and what it rules out: the "
             "[error-budget notes](../notes/error-budget.md)." if notes_page.is_file() else None)
    return write_results_page(runs, results_page, command=command, plots=not no_plots, notes=notes)


def budget(
    suites: List[str] = typer.Argument(..., metavar="SUITE...",
                                       help="Suite name(s) (eval/suites/NAME.yaml) or YAML path(s); one suite runs "
                                            "into OUTPUT itself, several each into OUTPUT/NAME."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder (resumed if it exists)."),
    methods: Optional[List[str]] = typer.Option(None, "--method", "-m", metavar="METHOD",
                                                help="Method label or name (repeatable; default: the suite's "
                                                     "methods; a method not in the suite runs with its defaults)."),
    scenes: Optional[List[str]] = typer.Option(None, "--scene", metavar="SCENE",
                                               help="Only this scene of the suite (repeatable)."),
    results_page: Optional[Path] = typer.Option(None, "--results-page",
                                                help="(Re)write this Markdown results page, e.g. "
                                                     "docs/results/budget.md (plots beside it)."),
    views: bool = typer.Option(False, "--views", help="Add the second views at the ceiling: the solver "
                                                      "with 4x its iterations, NLSTR on the truth."),
    no_plots: bool = typer.Option(False, "--no-plots", help="Skip the waterfall plots."),
    report_only: bool = typer.Option(False, "--report-only", help="Run nothing: rewrite budget.md, the plots and "
                                                                   "the results page from the stored budget.jsonl."),
    cache: Optional[Path] = typer.Option(None, "--cache", help="Capture cache folder (default: cache/ in the suite's output folder; "
                                                               "a suite run's cache can be shared)."),
    fresh: bool = typer.Option(False, "--fresh", help="Redo the cases this run plans (all, or those of -m and "
                                                      "--scene) although OUTPUT has them; other cases' results stay."),
    allow_other_suite: bool = typer.Option(False, "--allow-other-suite",
                                           help="Run into an OUTPUT whose budget another suite owns (its results are "
                                                "moved to OUTPUT/budget.OTHER.jsonl)."),
    device: str = DeviceOption,
    threads: Optional[int] = ThreadsOption,
    workers: Optional[int] = typer.Option(None, "--workers", "-w", min=0, metavar="N",
                                          help="Run the cases on a local Dask cluster of N worker processes."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", metavar="ADDRESS",
                                            help="Run the cases on the Dask cluster at this address."),
    as_json: bool = JsonOption,
) -> None:
    """Error budget: each case's ladder of oracles (as captured -> true warps -> model-exact -> noise-free).

    Each step is what one imperfection costs; the steps sum to the gap between the method as run and
    its ceiling. Writes budget.jsonl (one line per case, as it finishes; run again to resume), budget.md
    and a waterfall plot per case into OUTPUT for one suite, into OUTPUT/NAME for each of several. A
    folder is one suite's, and one run's at a time (like bench suite's).
    """
    from capssim.eval.benchmarks.output_claim import BUDGET_OUTPUT, claim_output
    from capssim.eval.error_budget.budget_report import write_report
    from capssim.eval.error_budget.runner import load_budget, run_budget
    from capssim.files.output_paths import resolve_output
    from capssim.runtime.threads import resolve_threads

    specs = _checked_suites(suites, methods=methods, scenes=scenes, workers=workers, scheduler=scheduler,
                            cache=cache, report_only=report_only)  # before any work
    target = resolve_output(output, kind="folder", overwrite=True)  # resumed if it exists; links followed
    if results_page is not None:
        resolve_output(results_page, kind="file", overwrite=True, argument="--results-page")
    apply_compute(threads if threads is not None else resolve_threads(None), device)
    say = (lambda text: typer.echo(text, err=True)) if as_json else typer.echo
    events = _events(say)

    runs = []
    for spec in specs:
        out = target / spec["name"] if len(specs) > 1 else target
        if report_only:
            run = load_budget(spec, out, methods=methods or None, scenes=scenes or None)
            report = write_report(run, out, plots=not no_plots)
        else:
            with claim_output(out, spec, allow_other_suite=allow_other_suite, kind=BUDGET_OUTPUT) as claimed:
                for message in claimed:  # the folder is held through the report too
                    say(message)
                run = run_budget(spec, out, methods=methods or None, scenes=scenes or None, device=device,
                                 cache_dir=cache, fresh=fresh, workers=workers, scheduler=scheduler, threads=threads,
                                 views=views, events=events, allow_other_suite=allow_other_suite)
                run.notes[:0] = claimed
                report = write_report(run, out, plots=not no_plots)
        say(f"{spec['name']}: {len(run.records)} case(s), {run.n_errors} error(s), {run.wall_time_s:.1f} s; "
            f"report {report}")
        runs.append(run)
    if results_page is not None:
        say(f"results page: {_results_page(runs, results_page, suites, output, methods, scenes, views, no_plots)}")
    if as_json:
        echo_json([{"suite": r.spec["name"], "wall_time_s": r.wall_time_s, "records": r.records} for r in runs])
    if any(r.n_errors for r in runs):
        say("some cases failed; see the budget.jsonl files")
        raise typer.Exit(1)


def add_budget_command(bench_app: typer.Typer) -> None:
    """Register `capssim bench budget` on the `bench` group (called by capssim.cli.bench)."""
    bench_app.command("budget")(budget)
