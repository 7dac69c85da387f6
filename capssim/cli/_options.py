"""Options shared by several commands (noise/sensor, devices, progress)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from capssim.sensor import Sensor, make_sensor


def sensor_from_options(noise: str, sigma: Optional[float], sensor_preset: Optional[str]) -> Sensor:
    if noise == "poisson-gaussian" and sensor_preset is None:
        sensor_preset = "imx250myr"
    return make_sensor(noise, sigma=sigma, preset=sensor_preset)


NoiseOption = typer.Option("none", "--noise", help="Sensor noise model: none | gaussian | poisson-gaussian.")
SigmaOption = typer.Option(None, "--sigma", help="Gaussian noise std on [0, 1] data (with --noise gaussian).")
SensorOption = typer.Option(None, "--sensor", help="Sensor preset for poisson-gaussian: python1300 | imx250myr.")
SeedOption = typer.Option(0, "--seed", help="Random seed (poses and noise).")
OverwriteOption = typer.Option(False, "--overwrite", help="Replace an existing output folder.")
DofpLayoutOption = typer.Option("sony", "--dofp-layout",
                                help="DoFP 2x2 polarizer cell: sony ([[90,45],[135,0]]) | 0-45-135-90.")


def echo_path(label: str, path: Path) -> None:
    typer.echo(f"{label}: {path}")
