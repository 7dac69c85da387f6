"""``capssim calibrate`` (measure a rig from calibration captures; ``capssim calibration-captures``
makes a set: capssim.cli.calibration_captures)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from capssim.cli._options import DeviceOption, ThreadsOption, apply_compute
from capssim.errors import InputError
from capssim.files.imageio import check_output_file


def calibrate(
    captures: List[Path] = typer.Argument(..., help="Calibration capture folders, or folders holding them."),
    output: Path = typer.Option(..., "-o", "--output", help="The capssim-rig JSON file to write."),
    report: Optional[Path] = typer.Option(None, "--report", help="Also write plots and a summary to this folder."),
    as_json: bool = typer.Option(False, "--json", help="Print the calibration as JSON to stdout."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --output."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Measure an imperfect array (angles, extinction, gain, vignetting, homographies, PSF) from calibration captures.

    The measurement computes on the CPU; --device is checked like every command's.
    """
    apply_compute(threads, device)
    output = check_output_file(output, argument="-o/--output")  # links followed; a folder in the way refused
    if output.exists() and not overwrite:  # after: --overwrite would not replace a folder, so it is not suggested
        raise InputError("-o/--output", str(output), "a file that does not exist yet", "Pass --overwrite to replace it.")
    if report is not None:
        from capssim.files.output_paths import resolve_output

        report = resolve_output(report, kind="folder", overwrite=True, argument="--report")
    from capssim.reconstruct.calibration import calibrate_captures  # pulls torch
    from capssim.reconstruct.calibration.report import summary_lines, write_report

    result = calibrate_captures(captures, output)
    if as_json:
        typer.echo(json.dumps(result.to_dict(), indent=1))
    else:
        for line in summary_lines(result):
            typer.echo(line)
        typer.echo(f"wrote {output}")
    if report is not None:
        written = write_report(result, report)
        typer.echo(f"report: {written}", err=as_json)


def register(app: typer.Typer) -> None:
    app.command("calibrate")(calibrate)
