"""``capssim dataset``: generate (or finish) a synthetic dataset on Dask, or verify one."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from capssim.cli._options import DeviceOption, apply_compute, number_in
from capssim.errors import InputError
from capssim.files.output_paths import resolve_output


def _fmt_duration(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    seconds = int(round(seconds))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}"


def _verify(out: Path) -> int:
    from capssim.dataset.verify import verify_dataset  # pulls torch and Dask (start-up time)

    with Progress(TextColumn("verifying"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  transient=True, disable=not sys.stderr.isatty()) as bar:
        task = bar.add_task("verify", total=None)
        report = verify_dataset(out, progress=lambda done, total: bar.update(task, completed=done, total=total))
    typer.echo(report.summary())
    return 0 if report.ok else 1


def dataset(
    config: Optional[Path] = typer.Argument(None, help="Dataset config (YAML). With --verify and no -o: the dataset folder."),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Dataset folder to create or finish."),
    workers: Optional[int] = typer.Option(None, "--workers", "-w",
                                          help="Local Dask workers (processes, 1 thread each; default: one per core). "
                                               "0 runs in this process without Dask."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler",
                                            help="Address of an existing Dask scheduler, e.g. tcp://host:8786."),
    threads: Optional[int] = typer.Option(None, "--threads",
                                          callback=number_in("--threads", 1, what="CPU threads",
                                                             fix="Leave --threads out for the default."),
                                          help="torch/OpenMP/Mitsuba threads per worker, or of this process with "
                                               "--workers 0 (default: cores // workers locally, 1 on a cluster, "
                                               "$CAPSSIM_THREADS or 1 in this process)."),
    device: str = DeviceOption,
    verify: bool = typer.Option(False, "--verify", help="Check every sample against the manifest (after generating, "
                                                         "if CONFIG is given); exit 1 on corruption."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Check the config and print the first samples' parameters."),
) -> None:
    """Generate a synthetic dataset from a YAML config (resumable; rerun to finish), or verify one.

    \b
    capssim dataset CONFIG -o OUT [--workers N | --scheduler ADDRESS] [--verify]
    capssim dataset --verify OUT
    The samples are simulated or rendered on the CPU (Mitsuba picks its own variant); --device is checked like
    every command's.
    """
    apply_compute(threads, device)
    if verify and output is None:
        if config is None:
            raise InputError("dataset", "nothing", "a dataset folder", "Run: capssim dataset --verify OUT")
        raise typer.Exit(_verify(config))
    if config is None:
        raise InputError("CONFIG", "nothing", "a dataset config file (YAML)",
                         "Run: capssim dataset CONFIG -o OUT (see examples/dataset-small.yaml).")
    if workers is not None and scheduler is not None:
        raise InputError("--workers", workers, "no --workers with --scheduler (the cluster has its own workers)")
    if scheduler is not None:
        from capssim.dataset.generate import check_scheduler_address  # start-up time

        check_scheduler_address(scheduler)
    if output is not None:  # created, or finished if it exists; links followed
        output = resolve_output(output, kind="folder", overwrite=True)
    from capssim.dataset.config import load_config  # pulls torch, Dask and the scene library (start-up time)

    cfg = load_config(config)
    if workers and scheduler is None:
        from capssim.dataset.generate import check_local_workers  # start-up time

        check_local_workers(workers)
    _check_disk(cfg, output if output is not None else Path.cwd())
    if dry_run:
        return _dry_run(cfg, config)
    _check_first_samples(cfg)
    if output is None:
        raise InputError("-o/--output", "nothing", "the dataset folder to create or finish", "Add -o OUT.")
    status = _generate(cfg, output, workers=workers, scheduler=scheduler, threads=threads)
    if verify:
        status = max(status, _verify(output))
    raise typer.Exit(status)


def _dry_run(cfg, config: Path) -> None:
    """``--dry-run``: check every sample's parameters and print the first five."""
    from capssim.dataset.sample import check_sample  # pulls torch and the renderer (start-up time)

    typer.echo(f"config {config}: {cfg.samples} samples, {len(cfg.sources)} sources, seed {cfg.seed}, "
               f"fingerprint {cfg.fingerprint()[:12]}")
    for index in range(cfg.samples):
        spec = cfg.sample_spec(index)
        check_sample(spec)
        if index < 5:
            typer.echo(f"{spec['name']}: seed {spec['seed']} {json.dumps(spec['params'], sort_keys=True)}")
    typer.echo(f"all {cfg.samples} samples' parameters checked")


def _generate(cfg, output: Path, *, workers: Optional[int], scheduler: Optional[str], threads: Optional[int]) -> int:
    """Generate (or finish) the dataset under a progress bar; the exit status (1: some samples failed)."""
    if not logging.getLogger().isEnabledFor(logging.DEBUG):
        import distributed  # noqa: F401  (it configures its loggers on import; quieten them after)

        for name in ("distributed", "bokeh", "tornado"):
            logging.getLogger(name).setLevel(logging.WARNING)

    from capssim.dataset.generate import generate_dataset  # pulls torch and Dask (start-up time)

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[status]}"), transient=False) as bar:
        task = bar.add_task(f"dataset {cfg.name}", total=cfg.samples, status="starting workers...")

        def on_progress(p):
            rate = f"{p.rate_per_hour:.0f} samples/h" if p.rate_per_hour else "- samples/h"
            failed = f", {p.failed} failed" if p.failed else ""
            bar.update(task, completed=p.done, status=f"{rate}, ETA {_fmt_duration(p.eta_s)}{failed}")

        result = generate_dataset(cfg, output, workers=workers, scheduler=scheduler, compute_threads=threads,
                                  progress=on_progress)
    rate = result.samples_per_hour
    where = "in this process" if result.workers == 0 else f"on {result.workers} Dask workers"
    typer.echo(f"{output}: {result.already_done + result.generated}/{result.total} samples "
               f"({result.already_done} from earlier runs, {result.generated} made {where}"
               f"{f', {rate:.0f} samples/h' if rate else ''}), {len(result.removed)} leftovers removed, "
               f"{result.wall_s:.1f} s")
    if not result.failed:
        return 0
    for index, error in sorted(result.failed.items()):
        typer.echo(f"FAILED sample {index}: {error}", err=True)
    typer.echo(f"{len(result.failed)} samples failed; rerun the same command to retry them.", err=True)
    return 1


#: samples whose drawn sizes set the per-sample disk estimate (the largest of them, times ``samples``)
DISK_ESTIMATE_SAMPLES = 256


def _check_disk(cfg, where: Path) -> None:
    """Refuse a ``samples`` count whose files cannot fit on the disk that would hold them."""
    from capssim.dataset.sample import sample_bytes_estimate  # start-up time
    from capssim.runtime.resources import check_disk, format_bytes

    largest = max(sample_bytes_estimate(cfg.sample_spec(i)) for i in range(min(cfg.samples, DISK_ESTIMATE_SAMPLES)))
    check_disk("samples", float(cfg.samples) * largest, where, what=f"{cfg.samples} samples of up to {format_bytes(largest)} each",
               fix="Lower 'samples' in the config, or write the dataset where there is room (-o).")


def _check_first_samples(cfg) -> None:
    """Before the dataset folder is made: the first samples checked as ``--dry-run`` checks them all (a PSF wider
    than the samples, a crop larger than the ground truth, ...), so a config that cannot make them leaves nothing."""
    from capssim.dataset.sample import check_sample  # start-up time

    for index in range(min(cfg.samples, DISK_ESTIMATE_SAMPLES)):
        check_sample(cfg.sample_spec(index))


def register(app: typer.Typer) -> None:
    app.command("dataset")(dataset)
