"""``capssim calibration-captures``: simulate or render one calibration set of a rig (docs: guides/calibration.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

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

#: keyword of make_calibration_captures -> the flag that sets it
_FLAGS = {"polarizer_angles": "--polarizer-angles", "size": "--size", "spp": "--spp", "frames": "--frames",
          "renderer": "--renderer"}


def calibration_captures(
    output: Path = typer.Argument(..., help="Folder to create: one capture folder per calibration target."),
    size: int = typer.Option(256, "--size", help="HR size in pixels (the size of the captures to calibrate)."),
    polarizer_angles: int = typer.Option(12, "--polarizer-angles", help="Angles of the polarizer sweep (>= 3)."),
    frames: int = typer.Option(1, "--frames", help="Captures of each uniform target (flat, sweep angles), 1..5."),
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
    as_json: bool = typer.Option(False, "--json", help="Print the set's index (index.json) as JSON."),
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
            polarizer_angles=polarizer_angles, seed=seed, spp=spp, frames=frames, overwrite=overwrite,
            aperture_homographies=None if geometry is None else geometry.aperture_homographies)
    except InputError as exc:
        flag = _FLAGS.get(exc.argument)
        if flag is None:
            raise
        raise InputError(flag, exc.received, exc.valid, exc.fix) from None
    if as_json:
        typer.echo(json.dumps(index, indent=1))
        return
    targets = [c["target"] for c in index["captures"]]
    typer.echo(f"wrote {output}: {len(targets)} calibration captures ({polarizer_angles} polarizer angles x "
               f"{frames} frame(s), flat, geometry, star), {size} px, {renderer}; next: capssim calibrate "
               f"{output} -o calibration.json")


def register(app: typer.Typer) -> None:
    app.command("calibration-captures")(calibration_captures)
