"""``capssim calibration-captures`` (make a set) and ``capssim calibrate`` (measure a rig from one)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from capssim.cli._options import (
    AngleOffsetsOption,
    AperturePsfOption,
    ExtinctionRatiosOption,
    GainsOption,
    NoiseOption,
    OverwriteOption,
    RigOption,
    RigSeedOption,
    SeedOption,
    SensorOption,
    SigmaOption,
    ThreadsOption,
    VignettingOption,
    apply_threads,
    rig_from_options,
    sensor_from_options,
)
from capssim.errors import InputError
from capssim.imageio import check_output_file


def calibration_captures(
    output: Path = typer.Argument(..., help="Folder to create: one capture folder per calibration target."),
    size: int = typer.Option(256, "--size", help="HR size in pixels (the size of the captures to calibrate)."),
    polarizer_angles: int = typer.Option(12, "--polarizer-angles", help="Angles of the polarizer sweep (>= 3)."),
    renderer: str = typer.Option("simulate", "--renderer", help="simulate | mitsuba."),
    spp: Optional[int] = typer.Option(64, "--spp", help="Samples per HR pixel (--renderer mitsuba)."),
    seed: int = SeedOption,
    noise: str = NoiseOption,
    sigma: Optional[float] = SigmaOption,
    sensor: Optional[str] = SensorOption,
    rig: Optional[str] = RigOption,
    rig_seed: int = RigSeedOption,
    angle_offsets: Optional[str] = AngleOffsetsOption,
    extinction_ratios: Optional[str] = ExtinctionRatiosOption,
    gains: Optional[str] = GainsOption,
    vignetting: Optional[float] = VignettingOption,
    aperture_psf_sigmas: Optional[str] = AperturePsfOption,
    overwrite: bool = OverwriteOption,
    threads: Optional[int] = ThreadsOption,
) -> None:
    """Simulate or render a rig's calibration captures: flat field, polarizer sweep, geometry target, star."""
    apply_threads(threads, renderer=renderer == "mitsuba")
    if renderer not in ("simulate", "mitsuba"):
        raise InputError("--renderer", repr(renderer), "simulate or mitsuba")
    model, geometry = rig_from_options(rig or "ideal", rig_seed, angle_offsets=angle_offsets,
                                       extinction_ratios=extinction_ratios, gains=gains, vignetting=vignetting,
                                       aperture_psf_sigmas=aperture_psf_sigmas)
    if geometry is not None and tuple(geometry.hr_shape) != (size, size):
        raise InputError("--size", size, f"the rig file's geometry size {geometry.hr_shape[0]}",
                         f"Use --size {geometry.hr_shape[0]}, or a rig file without geometry.")
    from capssim.dataset.calibration_captures import make_calibration_captures  # pulls torch and the renderer

    try:
        index = make_calibration_captures(
            output, rig=model, size=size, sensor=sensor_from_options(noise, sigma, sensor), renderer=renderer,
            polarizer_angles=polarizer_angles, seed=seed, spp=spp, overwrite=overwrite,
            aperture_homographies=None if geometry is None else geometry.aperture_homographies)
    except InputError as exc:
        flag = {"polarizer_angles": "--polarizer-angles", "size": "--size", "spp": "--spp"}.get(exc.argument)
        if flag is None:
            raise
        raise InputError(flag, exc.received, exc.valid, exc.fix) from None
    targets = [c["target"] for c in index["captures"]]
    typer.echo(f"wrote {output}: {len(targets)} calibration captures ({targets.count('polarizer')} polarizer "
               f"angles, flat, geometry, star), {size} px, {renderer}; next: capssim calibrate {output} "
               f"-o calibration.json")


def calibrate(
    captures: List[Path] = typer.Argument(..., help="Calibration capture folders, or folders holding them."),
    output: Path = typer.Option(..., "-o", "--output", help="The capssim-rig JSON file to write."),
    report: Optional[Path] = typer.Option(None, "--report", help="Also write plots and a summary to this folder."),
    as_json: bool = typer.Option(False, "--json", help="Print the calibration as JSON."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --output."),
    threads: Optional[int] = ThreadsOption,
) -> None:
    """Measure an imperfect array (angles, extinction, gain, vignetting, homographies, PSF) from calibration captures."""
    apply_threads(threads)
    check_output_file(output, argument="-o/--output")
    if output.exists() and not overwrite:
        raise InputError("-o/--output", str(output), "a file that does not exist yet", "Pass --overwrite to replace it.")
    from capssim.eval.calibration import calibrate_captures  # pulls torch
    from capssim.eval.calibration.report import summary_lines, write_report

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
    app.command("calibration-captures")(calibration_captures)
    app.command("calibrate")(calibrate)
