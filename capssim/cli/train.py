"""``capssim train``: train a learned baseline (CPDNet, the x2 EDSR of caps-sisr) on a capssim dataset."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from capssim.cli._options import DeviceOption, ThreadsOption, apply_compute


def train(
    config: Path = typer.Argument(..., help="Training config (YAML), e.g. examples/train-cpdnet-small.yaml."),
    output: Path = typer.Option(..., "-o", "--output", help="Run folder: checkpoint, model.pt, history, plot."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Start again in an existing run folder."),
    dataset_workers: int = typer.Option(0, "--dataset-workers", min=0,
                                        help="Dask workers that generate a missing dataset (0: in this process)."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Train the model of CONFIG into the run folder; the same command resumes after an interruption.

    Writes RUN/model.pt (use it with: capssim reconstruct CAP -m cpdnet -p weights=RUN/model.pt, or
    -m caps-sisr -p model=RUN/model.pt), RUN/history.jsonl and RUN/training.png. Train on a GPU with
    --device cuda (or auto).
    """
    dev = apply_compute(threads, device)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from capssim.files.output_paths import resolve_output
    from capssim.reconstruct.training.config import check_model_memory, load_train_config
    from capssim.reconstruct.training.trainer import check_run_folder
    from capssim.reconstruct.training.trainer import train as run_training

    output = resolve_output(output, kind="folder", overwrite=True)  # resumed if it exists; links followed
    cfg = load_train_config(config)
    check_model_memory(cfg, activations=dev.type == "cpu")  # on a GPU the batch's maps are the GPU's
    check_run_folder(cfg, output, overwrite=overwrite)  # before the progress bar: an unusable run folder, one line
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[status]}"), TimeRemainingColumn()) as bar:
        task = bar.add_task(f"train {cfg.name}", total=cfg.schedule["steps"], status="loading the dataset...")

        def on_progress(step, steps, loss, val):
            status = f"loss {loss:.4f}" + (f", val {val:.2f} dB" if val is not None else "")
            bar.update(task, completed=step, status=status)

        result = run_training(cfg, output, device=dev, overwrite=overwrite, dataset_workers=dataset_workers,
                              progress=on_progress, say=lambda msg: bar.console.print(msg))
    resumed = f", resumed at step {result.resumed_from}" if result.resumed_from else ""
    val = f", validation PSNR {result.validation_psnr:.2f} dB" if result.validation_psnr is not None else ""
    typer.echo(f"{output}: {result.steps} steps on {dev}{resumed}{val}, {result.wall_s:.0f} s")
    typer.echo(f"model: {result.model}")


def register(app: typer.Typer) -> None:
    app.command("train")(train)
