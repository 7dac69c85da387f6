"""Options shared by several commands (noise/sensor, devices, progress)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Optional

import typer

from capssim.errors import InputError
from capssim.resources import check_memory
from capssim.sensor import Sensor, make_sensor

#: largest ``--seed`` (numpy's ``SeedSequence`` takes any integer >= 0; 63 bits keep it an int64 everywhere)
MAX_SEED = 2**63 - 1


def sensor_from_options(noise: str, sigma: Optional[float], sensor_preset: Optional[str]) -> Sensor:
    if noise == "poisson-gaussian" and sensor_preset is None:
        sensor_preset = "imx250myr"
    return make_sensor(noise, sigma=sigma, preset=sensor_preset)


def number_in(option: str, low: float = -math.inf, high: float = math.inf, *, low_open: bool = False,
              high_open: bool = False, what: str = "", fix: str | None = None) -> Callable:
    """A typer callback refusing a value of ``option`` that is not finite or lies outside ``low .. high``
    (``*_open``: that end excluded) with an :class:`InputError`; ``None`` (the option not given) passes."""
    if math.isinf(high):
        valid = f"a finite number {'>' if low_open else '>='} {low:g}"
    else:
        valid = f"a finite number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    valid += f" ({what})" if what else ""

    def check(value):
        if value is None:
            return value
        above = value > low if low_open else value >= low
        below = value < high if high_open else value <= high
        if not (math.isfinite(value) and above and below):
            raise InputError(option, value, valid, fix)
        return value

    return check


def each(check: Callable) -> Callable:
    """``check`` applied to every value of a repeatable option."""
    return lambda values: values if values is None else [check(v) for v in values]


#: bytes per HR pixel a benchmark's scene holds at least (12 float64 channels, several copies)
SCENE_BYTES_PER_HR_PIXEL = 768


def check_hr_size(option: str) -> Callable:
    """A callback refusing an HR ``size`` whose scene alone would pass the memory limit (the resource guard)."""
    def check(size):
        if size is not None:
            check_memory(option, float(size) ** 2 * SCENE_BYTES_PER_HR_PIXEL, what=f"a {size}x{size} scene",
                         fix=f"Use a smaller {option}.")
        return size

    return check


def check_iterations(iterations: Optional[int]) -> Optional[int]:
    """``--iterations`` in ``0 .. MAX_ITERATIONS`` (the solvers' sane range)."""
    from capssim.reconstruct.admm import MAX_ITERATIONS  # start-up time: pulls torch

    return number_in("--iterations", 0, MAX_ITERATIONS, what="the paper uses 25")(iterations)


NoiseOption = typer.Option("none", "--noise", help="Sensor noise model: none | gaussian | poisson-gaussian.")
SigmaOption = typer.Option(None, "--sigma", help="Gaussian noise std on [0, 1] data (with --noise gaussian).",
                           callback=number_in("--sigma", 0.0, 1.0, what="noise std on [0, 1] data",
                                              fix="Try --sigma 0.01."))
SensorOption = typer.Option(None, "--sensor", help="Sensor preset for poisson-gaussian: python1300 | imx250myr.")


def _seed_in_range(seed: int, option: str) -> int:
    if not 0 <= seed <= MAX_SEED:
        raise InputError(option, seed, f"an integer in [0, {MAX_SEED}]", f"Try {option} 0.")
    return seed


def check_seed(seed: int) -> int:
    """``--seed`` as given, or an :class:`InputError` outside ``0 .. MAX_SEED``."""
    return _seed_in_range(seed, "--seed")


SeedOption = typer.Option(0, "--seed", callback=check_seed, help="Random seed (poses and noise), 0 .. 2**63-1.")
OverwriteOption = typer.Option(False, "--overwrite", help="Replace an existing output folder.")
DofpLayoutOption = typer.Option("sony", "--dofp-layout",
                                help="DoFP 2x2 polarizer cell: sony ([[90,45],[135,0]]) | 0-45-135-90.")

ThreadsOption = typer.Option(None, "--threads", min=1,
                             help="CPU threads for torch/OpenMP/OpenCV (default: $CAPSSIM_THREADS, else 'auto': one "
                                  "thread, and a reconstruction takes every core while no other process is busy).")


def apply_threads(threads: Optional[int], *, renderer: bool = False) -> int:
    """Set the compute threads from ``--threads`` (else ``$CAPSSIM_THREADS``, else the default);
    ``renderer``: Dr.Jit's (Mitsuba's) too."""
    from capssim.threads import set_threads  # start-up time: pulls torch

    return set_threads(threads, renderer=renderer)


def echo_path(label: str, path: Path) -> None:
    typer.echo(f"{label}: {path}")


# -- imperfect rigs (capssim simulate / render / calibration-captures) ------------------------------
RigOption = typer.Option(None, "--rig", help="Imperfect camera array: a preset (ideal, realistic) or a capssim-rig "
                                             "JSON file (capssim calibrate's output; its geometry, if any, gives "
                                             "the aperture homographies). Default: the ideal array.")
def _check_rig_seed(seed: int) -> int:
    return _seed_in_range(seed, "--rig-seed")


RigSeedOption = typer.Option(0, "--rig-seed", callback=_check_rig_seed, help="Draw of the --rig preset, 0 .. 2**63-1.")
AngleOffsetsOption = typer.Option(None, "--angle-offsets",
                                  help="Polarizer angle errors of the 4 apertures, degrees (|x| <= 20): a,b,c,d.")
ExtinctionRatiosOption = typer.Option(None, "--extinction-ratios",
                                      help="Polarizer extinction ratios of the rig (> 1, inf = ideal): 1 value, 3 "
                                           "(per colour R,G,B) or 12 (per aperture and colour). With a rig they "
                                           "replace --extinction-ratio for the CAPS frames; the DoFP camera keeps "
                                           "--extinction-ratio.")
GainsOption = typer.Option(None, "--gains", help="Gains of the 4 cameras (1 = nominal): a,b,c,d.")
VignettingOption = typer.Option(None, "--vignetting",
                                help="Corner fall-off of a centred radial vignetting, 0..0.9 (0.2 = corners at 80 %).",
                                callback=number_in("--vignetting", 0.0, 0.9, what="the corner fall-off fraction",
                                                   fix="For example --vignetting 0.2 (corners at 80 %)."))
AperturePsfOption = typer.Option(None, "--aperture-psf-sigmas",
                                 help="Gaussian PSF std of each aperture, HR pixels (>= 0): a,b,c,d.")

#: rig flag -> (RigModel.with_overrides keyword, value counts, valid range, example)
_RIG_FLAGS = {
    "--angle-offsets": ("angle_offsets_deg", (4,), (-20.0, 20.0, False), "1.5,-0.8,0.3,-2"),
    "--extinction-ratios": ("extinction_ratio", (1, 3, 12), (1.0, math.inf, True), "200,150,60"),
    "--gains": ("gain", (4,), (1e-3, math.inf, False), "1.03,0.97,1,1.01"),
    "--aperture-psf-sigmas": ("psf_sigmas_hr_px", (4,), (0.0, math.inf, False), "0.45,0.5,0.55,0.5"),
}


def _rig_numbers(flag: str, text: str) -> list[float]:
    """The comma-separated values of rig option ``flag``, checked against :data:`_RIG_FLAGS`."""
    _, counts, (low, high, low_open), example = _RIG_FLAGS[flag]
    allow_inf = flag == "--extinction-ratios"
    count_text = " or ".join(map(str, counts))
    valid = (f"{count_text} comma-separated numbers, each {'>' if low_open else '>='} {low:g}"
             + (" (inf: ideal)" if allow_inf else f" and <= {high:g}" if math.isfinite(high) else ""))
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise InputError(flag, repr(text), valid, f"For example {flag} {example}.") from None
    if len(values) not in counts or not all(
            (math.isfinite(v) or (allow_inf and v == math.inf)) and (v > low if low_open else v >= low) and v <= high
            for v in values):
        raise InputError(flag, repr(text), valid, f"For example {flag} {example}.")
    return values


def rig_from_options(rig: Optional[str], rig_seed: int = 0, *, angle_offsets: Optional[str] = None,
                     extinction_ratios: Optional[str] = None, gains: Optional[str] = None,
                     vignetting: Optional[float] = None, aperture_psf_sigmas: Optional[str] = None,
                     extinction_ratio: Optional[float] = None):
    """``(RigModel | None, ArrayGeometry | None)`` of the rig options; ``(None, None)`` when none is given.

    ``rig``: ``ideal``, ``realistic`` (drawn with ``rig_seed``) or a capssim-rig JSON file (its
    geometry, if any, is returned); the other options replace the rig's quantities. On the ideal
    array (``--rig`` absent or ``ideal``) without ``--extinction-ratios``, the one
    ``extinction_ratio`` (``--extinction-ratio``) stays the CAPS polarizers' too.
    """
    from capssim.rig import RigModel, read_rig_json

    texts = {"--angle-offsets": angle_offsets, "--extinction-ratios": extinction_ratios, "--gains": gains,
             "--aperture-psf-sigmas": aperture_psf_sigmas}
    overrides = {_RIG_FLAGS[flag][0]: _rig_numbers(flag, text) for flag, text in texts.items() if text is not None}
    if vignetting is not None:
        overrides["vignetting_corner"] = vignetting
    if rig is None and not overrides:
        return None, None
    geometry = None
    if rig in (None, "ideal") and extinction_ratio is not None and "extinction_ratio" not in overrides:
        overrides["extinction_ratio"] = [extinction_ratio]
    if rig is None or rig in ("ideal", "realistic"):
        model = RigModel.preset(rig or "ideal", seed=rig_seed)
    elif Path(rig).suffix.lower() == ".json" or Path(rig).exists():
        loaded = read_rig_json(rig, argument="--rig")
        model, geometry = loaded.rig, loaded.geometry
    else:
        raise InputError("--rig", repr(rig), "ideal, realistic, or a capssim-rig JSON file",
                         "Write one with `capssim calibrate`, or use --rig realistic.")
    try:
        return model.with_overrides(**overrides), geometry
    except InputError as exc:
        flag = {"rig angle_offsets_deg": "--angle-offsets", "rig extinction_ratio": "--extinction-ratios",
                "rig gain": "--gains", "rig vignetting": "--vignetting", "extinction_ratio": "--extinction-ratios",
                "vignetting": "--vignetting", "aperture PSF sigmas": "--aperture-psf-sigmas"}.get(exc.argument,
                                                                                                   exc.argument)
        raise InputError(flag, exc.received, exc.valid, exc.fix) from None


def check_rig_psfs(rig, hr_shape, *, aperture_psf_sigmas: Optional[str]) -> None:
    """Refuse rig PSFs wider than the ``hr_shape`` image, naming the flag that set them."""
    flag = "--aperture-psf-sigmas" if aperture_psf_sigmas is not None else "--rig"
    for aperture_psf in (rig.psf_objects() if rig is not None else None) or []:
        aperture_psf.check_extent(tuple(hr_shape), option=flag, memory=False)


def rig_homographies(geometry, hr_shape, *, fix: str):
    """``(4, 3, 3)`` aperture homographies of a ``--rig`` file's geometry (``None`` without one),
    refused unless made for ``hr_shape``."""
    if geometry is None:
        return None
    if tuple(geometry.hr_shape) != tuple(int(v) for v in hr_shape):
        raise InputError("--rig", f"geometry for {geometry.hr_shape[0]}x{geometry.hr_shape[1]} HR px",
                         f"the capture's size {hr_shape[0]}x{hr_shape[1]}",
                         f"Calibrate at the capture's size, or {fix}.")
    return geometry.aperture_homographies
