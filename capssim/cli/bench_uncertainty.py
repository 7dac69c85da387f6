"""``capssim bench uncertainty``: fit the calibration of ``--uncertainty``'s intervals on development captures and
check their coverage on others (docs/guides/reconstruction.md, "Error bars"; docs/results/uncertainty.md)."""

from __future__ import annotations

import datetime as _dt
import shlex
import sys
from pathlib import Path
from typing import Optional

import typer

from capssim.cli._options import DeviceOption, ThreadsOption, apply_compute


def bench_uncertainty(
    spec_name: str = typer.Argument(..., metavar="SPEC", help="Calibration spec name (eval/uncertainty/NAME.yaml, "
                                                              "e.g. calibration) or a YAML path."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder: calibration.json, report.md, cases/ "
                                                            "(resumed if it exists)."),
    install: bool = typer.Option(False, "--install", help="Also write the calibration to the file capssim ships "
                                                          "and --uncertainty reads (capssim/reconstruct/uncertainty/"
                                                          "calibration.json)."),
    cache: Optional[Path] = typer.Option(None, "--cache", help="Capture cache folder (default: OUTPUT/cache)."),
    device: str = DeviceOption,
    threads: Optional[int] = ThreadsOption,
) -> None:
    """Fit the conformal scales of --uncertainty on the spec's calibration scenes; report coverage on its check scenes.

    Every (scene, noise, seed, method) is reconstructed with an uncalibrated bootstrap; per method and noise level,
    each group's scale (12 channels, S0, DoLP, AoP) is the split-conformal 90 % quantile of |error| / spread over
    the calibration scenes' pixels. report.md gives the coverage, width and AUSE on the check scenes.
    """
    from rich.console import Console  # start-up time

    from capssim.eval.uncertainty.calibrate import run_uncertainty_calibration
    from capssim.eval.uncertainty.report import write_uncertainty_report
    from capssim.eval.uncertainty.spec import load_uncertainty_spec
    from capssim.runtime.threads import resolve_threads

    spec = load_uncertainty_spec(spec_name)
    if output.exists() and not output.is_dir():
        from capssim.errors import InputError

        raise InputError("-o/--output", str(output), "a folder (new, or one this command wrote)",
                         "Choose another -o path.")
    apply_compute(threads if threads is not None else resolve_threads(None), device)
    console = Console(stderr=True)

    def events(kind, **fields):
        if kind == "case":
            console.print(f"[{fields['index'] + 1}/{fields['total']}] {fields['name']}")
        elif kind == "note":
            console.print(fields.get("message", ""))

    result = run_uncertainty_calibration(spec, output, device=device, cache_dir=cache, install=install,
                                         events=events)
    command = "capssim bench uncertainty " + " ".join(shlex.quote(a) for a in sys.argv[3:])
    report = write_uncertainty_report(output, result, spec, command=command, date=_dt.date.today().isoformat())
    typer.echo(f"{len(result['cases'])} cases; calibration: {output / 'calibration.json'}"
               + (" (installed)" if install else ""))
    typer.echo(f"report: {report}")


def add_uncertainty_command(bench_app: typer.Typer) -> None:
    """Register `capssim bench uncertainty` on the `bench` group (called by capssim.cli.bench)."""
    bench_app.command("uncertainty")(bench_uncertainty)
