"""``capssim calibration-captures``: simulate or render one calibration set of a rig (docs: guides/calibration.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from capssim.cli._options import (
    DeviceOption,
    OverwriteOption,
    SeedOption,
    ThreadsOption,
    apply_compute,
)
from capssim.cli._setup_options import SetupOptions, with_setup_options
from capssim.errors import InputError

#: keyword of make_calibration_captures -> the flag that sets it
_FLAGS = {"polarizer_angles": "--polarizer-angles", "size": "--size", "spp": "--spp", "frames": "--frames",
          "renderer": "--renderer"}


@with_setup_options
def calibration_captures(
    output: Path = typer.Option(..., "-o", "--output", help="Folder to create: one capture folder per calibration "
                                                           "target."),
    size: int = typer.Option(256, "--size", help="HR size in pixels (the size of the captures to calibrate)."),
    polarizer_angles: int = typer.Option(12, "--polarizer-angles", help="Angles of the polarizer sweep (>= 3)."),
    frames: int = typer.Option(1, "--frames", help="Captures of each uniform target (flat, sweep angles), 1..5."),
    renderer: str = typer.Option("simulate", "--renderer", help="simulate | mitsuba."),
    spp: Optional[int] = typer.Option(64, "--spp", help="Samples per HR pixel (--renderer mitsuba)."),
    seed: int = SeedOption,
    setup_options: SetupOptions = SetupOptions(),
    overwrite: bool = OverwriteOption,
    as_json: bool = typer.Option(False, "--json", help="Print the set's index (index.json) as JSON to stdout."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Simulate or render a rig's calibration captures: flat field, polarizer sweep, geometry target, star.

    The simulation computes on the CPU (Mitsuba picks its own variant); --device is checked like every command's.
    """
    if renderer not in ("simulate", "mitsuba"):
        raise InputError("--renderer", repr(renderer), "simulate or mitsuba")
    apply_compute(threads, device, renderer=renderer == "mitsuba")
    model, geometry = setup_options.rig_model(default="ideal")
    setup = setup_options.camera_setup(model)
    if geometry is not None and tuple(geometry.hr_shape) != (size, size):
        raise InputError("--size", size, f"the rig file's geometry size {geometry.hr_shape[0]}",
                         f"Use --size {geometry.hr_shape[0]}, or a rig file without geometry.")
    from capssim.dataset.calibration_captures import make_calibration_captures  # pulls torch and the renderer

    try:
        index = make_calibration_captures(
            output, setup=setup, size=size, renderer=renderer,
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
