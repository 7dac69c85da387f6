"""Options shared by several commands (noise/sensor, devices, progress)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from capssim.errors import InputError
from capssim.sensor import Sensor, make_sensor

#: largest ``--seed`` (numpy's ``SeedSequence`` takes any integer >= 0; 63 bits keep it an int64 everywhere)
MAX_SEED = 2**63 - 1


def sensor_from_options(noise: str, sigma: Optional[float], sensor_preset: Optional[str]) -> Sensor:
    if noise == "poisson-gaussian" and sensor_preset is None:
        sensor_preset = "imx250myr"
    return make_sensor(noise, sigma=sigma, preset=sensor_preset)


NoiseOption = typer.Option("none", "--noise", help="Sensor noise model: none | gaussian | poisson-gaussian.")
SigmaOption = typer.Option(None, "--sigma", help="Gaussian noise std on [0, 1] data (with --noise gaussian).")
SensorOption = typer.Option(None, "--sensor", help="Sensor preset for poisson-gaussian: python1300 | imx250myr.")


def check_seed(seed: int) -> int:
    """``--seed`` as given, or an :class:`InputError` outside ``0 .. MAX_SEED``."""
    if not 0 <= seed <= MAX_SEED:
        raise InputError("--seed", seed, f"an integer in [0, {MAX_SEED}]", "Try --seed 0.")
    return seed


SeedOption = typer.Option(0, "--seed", callback=check_seed, help="Random seed (poses and noise), 0 .. 2**63-1.")
OverwriteOption = typer.Option(False, "--overwrite", help="Replace an existing output folder.")
DofpLayoutOption = typer.Option("sony", "--dofp-layout",
                                help="DoFP 2x2 polarizer cell: sony ([[90,45],[135,0]]) | 0-45-135-90.")


def echo_path(label: str, path: Path) -> None:
    typer.echo(f"{label}: {path}")
