"""``capssim bench suite``: a benchmark suite (docs/guides/benchmarks.md, "Suites"; limits: docs/guides/limits.md).

Everything a user can get wrong is checked before the first case runs, so that no finished work is
thrown away: the suite file (its schema), ``-m``/``--scene``, the scene sizes against the memory
limit, ``--workers``/``--scheduler``, the ``--check`` baseline (its schema: finite tolerances >= 0),
the ``--update-baseline`` and ``--results-page`` targets, and the output folder (its lock, and the
suite that owns it: ``--allow-other-suite`` hands it over).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from capssim.cli._options import DeviceOption, ThreadsOption, apply_compute
from capssim.cli.evaluate import format_table, format_value
from capssim.errors import InputError


def _progress_events(progress, task):
    """The suite runner's ``events`` callback drawing on a rich progress bar."""

    def on_event(kind: str, **info):
        if kind == "start":
            progress.update(task, total=info["total"])
        elif kind == "case":
            progress.update(task, case=info["label"])
        elif kind == "done":
            progress.advance(task)
        elif kind in ("skip", "note"):
            progress.console.print(f"[yellow]{info['message']}")
        elif kind == "error":
            progress.console.print(f"[red]{info['message']}")

    return on_event


def _check_inputs(spec: dict, *, methods, scenes, workers, scheduler, check, update_baseline, replace_baseline,
                  results_page, cache=None) -> tuple[dict | None, dict | None]:
    """Every check of the command line that needs no work, before the output folder is touched:
    ``(the --check baseline, the baseline --update-baseline merges into)``."""
    from capssim.eval.benchmarks.baseline import baseline_to_update, load_baseline
    from capssim.eval.benchmarks.executors import check_cache_folder, check_execution
    from capssim.eval.benchmarks.suite import plan
    from capssim.files.imageio import check_output_file

    plan(spec, methods=methods, scenes=scenes, emit=lambda kind, **info: None)  # -m, --scene, scene memory
    check_execution(workers=workers, scheduler=scheduler)
    check_cache_folder(cache)
    if replace_baseline and update_baseline is None:
        raise InputError("--replace-baseline", "no --update-baseline", "--replace-baseline with --update-baseline PATH",
                         "Add --update-baseline PATH, or drop --replace-baseline.")
    baseline = load_baseline(check) if check is not None else None
    previous = None
    if update_baseline is not None:
        previous = baseline_to_update(update_baseline, spec, replace=replace_baseline)
    if results_page is not None:
        check_output_file(results_page, argument="--results-page")
    return baseline, previous


def _finish(run, output: Path, *, verdict, no_plots: bool, results_page, update_baseline, previous,
            partial: bool = False) -> None:
    """The report, summary, results page and baseline of a finished run (the output folder still held). After a
    ``partial`` run (``-m``/``--scene``) the report and the results page show the whole suite: this run's cases
    and the other cases' latest records in the folder
    (:func:`~capssim.eval.benchmarks.whole_suite.whole_suite_run`); the summary shows this run's cases."""
    from capssim.eval.benchmarks.baseline import write_baseline
    from capssim.eval.suite_report import write_report, write_results_page

    shown = run
    if partial:
        from capssim.eval.benchmarks.captures import expand_render_scenes
        from capssim.eval.benchmarks.whole_suite import whole_suite_run

        scene_names = {s["name"] for s in expand_render_scenes(run.spec["scenes"], lambda *a, **k: None)}
        shown = whole_suite_run(run, scene_names=scene_names)
    report = write_report(shown, output, verdict=verdict, plots=not no_plots)
    typer.echo(render_bench_summary(run))
    if run.execution.get("kind") == "dask":
        typer.echo(f"ran on {run.execution['workers']} Dask worker(s), {run.execution['compute_threads']} compute "
                   f"thread(s) each, in {run.wall_time_s:.1f} s")
    typer.echo(f"results: {run.results_path}")
    for note in shown.notes[len(run.notes):]:
        typer.echo(f"report: {note}")
    typer.echo(f"report:  {report}")
    if results_page is not None:
        typer.echo(f"results page: {write_results_page(shown, results_page, verdict=verdict)}")
    if update_baseline is not None:
        n, kept = write_baseline(run, update_baseline, previous=previous)
        more = f", {kept} kept from the existing baseline (--replace-baseline drops them)" if kept else ""
        typer.echo(f"wrote baseline {update_baseline} ({n} cases{more})")


def suite(
    name: str = typer.Argument(..., help="Suite name (eval/suites/NAME.yaml: quick, ablation, paper, full) "
                                         "or a YAML path."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder (resumed if it exists; one suite and one "
                                                            "run at a time)."),
    check: Optional[Path] = typer.Option(None, "--check", help="Baseline JSON: exit 1 if a metric fell beyond tolerance."),
    update_baseline: Optional[Path] = typer.Option(None, "--update-baseline",
                                                   help="Write this run's metrics as the baseline (merged into an "
                                                        "existing baseline of the suite)."),
    replace_baseline: bool = typer.Option(False, "--replace-baseline",
                                          help="With --update-baseline: write only this run's cases, dropping the "
                                               "others of the existing baseline."),
    results_page: Optional[Path] = typer.Option(None, "--results-page",
                                                help="(Re)write this Markdown results page, e.g. docs/results/quick.md. "
                                                     "With -m or --scene it, like report.md, still shows the whole "
                                                     "suite: the other cases' latest results in OUTPUT (its notes "
                                                     "say so)."),
    methods: Optional[List[str]] = typer.Option(None, "--method", "-m", metavar="METHOD",
                                                help="Run only this method of the suite (repeatable)."),
    scenes: Optional[List[str]] = typer.Option(None, "--scene", metavar="SCENE",
                                               help="Run only this scene of the suite (repeatable)."),
    device: str = DeviceOption,
    threads: Optional[int] = ThreadsOption,
    cache: Optional[Path] = typer.Option(None, "--cache", help="Capture cache folder (default: OUTPUT/cache)."),
    fresh: bool = typer.Option(False, "--fresh", help="Redo the cases this run plans (all, or those of -m and "
                                                      "--scene) although OUTPUT has them; other cases' results stay."),
    no_plots: bool = typer.Option(False, "--no-plots", help="Skip the plots (report and results only)."),
    allow_other_suite: bool = typer.Option(False, "--allow-other-suite",
                                           help="Run into an OUTPUT that another suite owns (its results are moved "
                                                "to OUTPUT/results.OTHER.jsonl)."),
    workers: Optional[int] = typer.Option(None, "--workers", "-w", min=0, metavar="N",
                                          help="Run the cases on a local Dask cluster of N worker processes (1 task "
                                               "and --threads compute threads each; default: in this process)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", metavar="ADDRESS",
                                            help="Run the cases on the Dask cluster at this address, "
                                                 "e.g. tcp://host:8786 (workers must see OUTPUT and the data)."),
) -> None:
    """Run a benchmark suite: scenes x methods x noise levels (x seeds); results.jsonl, report.md, plots.

    Each case's line is appended to results.jsonl as it finishes; run the same command again to
    finish an interrupted run (only the missing cases run). --workers N / --scheduler ADDRESS
    run the cases in parallel on Dask, with the same results as a run in this process.
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    # start-up time: the runner pulls torch, the renderer and every method
    from capssim.eval.benchmarks.baseline import check_against_baseline
    from capssim.eval.benchmarks.output_claim import claim_output
    from capssim.eval.benchmarks.suite import load_suite, run_suite
    from capssim.runtime.threads import resolve_threads

    spec = load_suite(name)
    baseline, previous = _check_inputs(spec, methods=methods or None, scenes=scenes or None, workers=workers,
                                       scheduler=scheduler, check=check, update_baseline=update_baseline,
                                       replace_baseline=replace_baseline, results_page=results_page, cache=cache)
    apply_compute(threads if threads is not None else resolve_threads(None), device)
    with claim_output(output, spec, allow_other_suite=allow_other_suite) as claim_notes:
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      TextColumn("{task.fields[case]}"), console=Console(stderr=True), transient=False) as progress:
            task = progress.add_task(f"bench {spec['name']}", total=None, case="")
            for message in claim_notes:
                progress.console.print(f"[yellow]{message}")
            run = run_suite(spec, output, methods=methods or None, scenes=scenes or None, device=device,
                            cache_dir=cache, fresh=fresh, workers=workers, scheduler=scheduler, threads=threads,
                            events=_progress_events(progress, task), allow_other_suite=allow_other_suite)
        run.notes[:0] = claim_notes
        verdict = check_against_baseline(run, baseline) if baseline is not None else None
        _finish(run, output, verdict=verdict, no_plots=no_plots, results_page=results_page,
                update_baseline=update_baseline, previous=previous, partial=bool(methods or scenes))
    if verdict is not None:
        typer.echo(verdict.text())
        if not verdict.passed:
            raise typer.Exit(1)
    if run.n_errors:
        typer.echo(f"{run.n_errors} case(s) failed; see {run.results_path}", err=True)
        raise typer.Exit(1)


def _mean_metric(records: list[dict], key: str) -> float | None:
    values = [r["metrics"][key] for r in records if r["metrics"].get(key) is not None]
    return sum(values) / len(values) if values else None


def render_bench_summary(run) -> str:
    """One compact table per scene / noise level (the full tables are in report.md)."""
    from capssim.eval.suite_report import group_records

    lines = []
    methods = [m["label"] for m in run.spec["methods"]]
    for (scene, noise), recs in sorted(group_records(run.records).items()):
        rows = []
        for m in methods:
            rs = [r for r in recs if r["method"] == m]
            if not rs:
                continue
            t = sum(r["wall_time_s"] for r in rs) / len(rs)
            rows.append([m, format_value(_mean_metric(rs, "psnr_mean")), format_value(_mean_metric(rs, "ssim_mean"), 4),
                         format_value(_mean_metric(rs, "dolp_psnr")), format_value(_mean_metric(rs, "aop_rmse_deg")),
                         format_value(_mean_metric(rs, "mtf_magnification_hv")), format_value(t, 2)])
        lines += ["", f"{scene} / {noise}:",
                  format_table(["method", "PSNR", "SSIM", "DoLP", "AoP-RMSE", "SR-mag", "time-s"], rows)]
    skipped = [r for r in run.records if r["status"] == "skipped"]
    if skipped:
        lines.append(f"\n{len(skipped)} case(s) skipped (reasons in report.md)")
    return "\n".join(lines)


def add_suite_command(bench_app: typer.Typer) -> None:
    """Register `capssim bench suite` on the `bench` group (called by capssim.cli.bench)."""
    bench_app.command("suite")(suite)
