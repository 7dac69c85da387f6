"""``capssim bench map``: a design map, a sweep of camera and scene conditions (docs/guides/benchmarks.md,
"Design maps").

Everything a user can get wrong is checked before the first cell runs: the map file (its schema, every key and
value, :mod:`capssim.eval.maps.spec`), the scene's size against the memory limit, ``--workers``/``--scheduler``,
``--cache`` and the output folder (its lock, and the map that owns it).
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Optional

import typer

from capssim.cli._options import DeviceOption, ThreadsOption, apply_compute
from capssim.cli.bench_suite import _progress_events


def bench_map(
    spec_name: str = typer.Argument(..., metavar="SPEC", help="Map name (eval/maps/NAME.yaml, e.g. phase-noise) or "
                                                              "a YAML path."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder: map.jsonl, report.md, *.png (resumed if "
                                                            "it exists; one map and one run at a time)."),
    device: str = DeviceOption,
    threads: Optional[int] = ThreadsOption,
    cache: Optional[Path] = typer.Option(None, "--cache", help="Capture cache folder (default: OUTPUT/cache)."),
    fresh: bool = typer.Option(False, "--fresh", help="Redo every case although map.jsonl has it."),
    no_plots: bool = typer.Option(False, "--no-plots", help="Skip the pictures (map.jsonl and report.md only)."),
    workers: Optional[int] = typer.Option(None, "--workers", "-w", min=0, metavar="N",
                                          help="Run the cases on a local Dask cluster of N worker processes "
                                               "(default: in this process)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", metavar="ADDRESS",
                                            help="Run the cases on the Dask cluster at this address, e.g. "
                                                 "tcp://host:8786 (workers must see OUTPUT and the data)."),
) -> None:
    """Run a design map: every cell of the axes x seeds x methods; map.jsonl, report.md, heatmaps.

    The margin (best camera-array method - best DoFP method) of every metric per cell, with the zero
    contour, each cell's winner and the undecided cells (within one standard error over the seeds).
    Run the same command again to finish an interrupted map (only the missing cases run); -w N /
    --scheduler ADDRESS give the same map.jsonl as a run in this process.
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    # start-up time: the runner pulls torch and every method
    from capssim.eval.benchmarks.executors import check_execution
    from capssim.eval.benchmarks.output_claim import claim_output
    from capssim.eval.maps.report import write_map_report
    from capssim.eval.maps.spec import load_map
    from capssim.eval.maps.sweep import MAP_OUTPUT, plan_map, run_map
    from capssim.runtime.threads import resolve_threads

    spec = load_map(spec_name)
    plan_map(spec)  # the scene's size against the memory limit
    check_execution(workers=workers, scheduler=scheduler, cache=cache)
    apply_compute(threads if threads is not None else resolve_threads(None), device)
    with claim_output(output, spec, kind=MAP_OUTPUT) as claim_notes:
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      TextColumn("{task.fields[case]}"), console=Console(stderr=True), transient=False) as progress:
            task = progress.add_task(f"map {spec['name']}", total=None, case="")
            for message in claim_notes:
                progress.console.print(f"[yellow]{message}")
            run = run_map(spec, output, device=device, cache_dir=cache, fresh=fresh, workers=workers,
                          scheduler=scheduler, threads=threads, events=_progress_events(progress, task))
        command = "capssim bench map " + " ".join(shlex.quote(a) for a in sys.argv[3:]) if len(sys.argv) > 3 else None
        report = write_map_report(output, spec, command=command, plots=not no_plots)
    where = f" on {run.execution['workers']} Dask worker(s)" if run.execution.get("kind") == "dask" else ""
    typer.echo(f"{len(run.records)} cases{where} in {run.wall_time_s:.1f} s")
    typer.echo(f"results: {run.results_path}")
    typer.echo(f"report:  {report}")
    if run.n_errors:
        typer.echo(f"{run.n_errors} case(s) failed; see {run.results_path}", err=True)
        raise typer.Exit(1)


def add_map_command(bench_app: typer.Typer) -> None:
    """Register `capssim bench map` on the `bench` group (called by capssim.cli.bench)."""
    bench_app.command("map")(bench_map)
