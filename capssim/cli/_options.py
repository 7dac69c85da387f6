"""Options shared by every command (docs: guides/cli.md): --threads, --device, --json, seeds, number checks;
the camera set-up options are in capssim.cli._setup_options."""

from __future__ import annotations

import math
from typing import Callable, Optional

import typer

from capssim.errors import InputError
from capssim.runtime.resources import check_scene_size

#: largest ``--seed`` (numpy's ``SeedSequence`` takes any integer >= 0; 63 bits keep it an int64 everywhere)
MAX_SEED = 2**63 - 1


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


def check_hr_size(option: str) -> Callable:
    """A callback refusing an HR ``size`` whose scene alone would pass the memory limit (the resource guard,
    :func:`capssim.runtime.resources.check_scene_size`, as suite scenes)."""
    def check(size):
        if size is not None:
            check_scene_size(option, size, fix=f"Use a smaller {option}.")
        return size

    return check


def check_iterations(iterations: Optional[int]) -> Optional[int]:
    """``--iterations`` in ``0 .. MAX_ITERATIONS`` (the solvers' sane range)."""
    from capssim.reconstruct.solvers.admm import MAX_ITERATIONS  # start-up time: pulls torch

    return number_in("--iterations", 0, MAX_ITERATIONS, what="the paper uses 25")(iterations)




def seed_in_range(seed: int, option: str) -> int:
    """``seed`` as given, or an :class:`InputError` naming ``option`` outside ``0 .. MAX_SEED``."""
    if not 0 <= seed <= MAX_SEED:
        raise InputError(option, seed, f"an integer in [0, {MAX_SEED}]", f"Try {option} 0.")
    return seed


def check_seed(seed: int) -> int:
    """``--seed`` as given, or an :class:`InputError` outside ``0 .. MAX_SEED``."""
    return seed_in_range(seed, "--seed")


SeedOption = typer.Option(0, "--seed", callback=check_seed, help="Random seed (poses and noise), 0 .. 2**63-1.")
OverwriteOption = typer.Option(False, "--overwrite", help="Replace an existing output folder.")
#: ``--threads``: at least 1 (a one-line error naming the option, as every numeric option; no click usage block)
ThreadsOption = typer.Option(None, "--threads", callback=number_in("--threads", 1, what="CPU threads",
                                                                  fix="Leave --threads out for the default."),
                             help="CPU threads for torch/OpenMP/OpenCV (default: $CAPSSIM_THREADS, else 'auto': one "
                                  "thread, and a reconstruction takes every core while no other process is busy).")


def apply_threads(threads: Optional[int], *, renderer: bool = False) -> int:
    """Set the compute threads from ``--threads`` (else ``$CAPSSIM_THREADS``, else the default);
    ``renderer``: Dr.Jit's (Mitsuba's) too."""
    from capssim.runtime.threads import set_threads  # start-up time: pulls torch

    return set_threads(threads, renderer=renderer)


#: the choices of ``--device`` on every command (``auto``: cuda when present), and its one default
DEVICES = ("auto", "cpu", "cuda")
DEFAULT_DEVICE = "cpu"


def check_device(value):
    """``--device`` in lower case, or a one-line :class:`InputError` naming the option outside
    :data:`DEVICES`; a list (a repeatable ``--device``) is checked value by value."""
    if isinstance(value, (list, tuple)):
        return [check_device(v) for v in value]
    key = str(value).strip().lower()
    if key not in DEVICES:
        raise InputError("--device", repr(value), " | ".join(DEVICES),
                         "Use --device cpu (or --device auto: cuda when present).")
    return key


DEVICE_HELP = "Torch device of the computation: auto (cuda when present) | cpu | cuda."
DeviceOption = typer.Option(DEFAULT_DEVICE, "--device", callback=check_device, metavar="|".join(DEVICES), help=DEVICE_HELP)
JsonOption = typer.Option(False, "--json", help="Print the result as JSON to stdout (instead of the text).")


def echo_json(obj) -> None:
    """Print ``obj`` as standard JSON to stdout (``--json``): NaN/inf as null, numpy values as Python's,
    paths as strings."""
    import json

    from capssim.eval.metric_records import json_safe  # start-up time

    typer.echo(json.dumps(json_safe(obj), indent=2, allow_nan=False, default=str))


def apply_compute(threads: Optional[int], device: str, *, renderer: bool = False):
    """Apply ``--threads`` (:func:`apply_threads`) and resolve ``--device`` to a ``torch.device``
    (``cuda`` without a GPU: an :class:`InputError` naming ``--device``)."""
    apply_threads(threads, renderer=renderer)
    from capssim.reconstruct import resolve_device  # start-up time: pulls torch

    try:
        return resolve_device(device)
    except InputError as exc:
        raise InputError("--device", exc.received, exc.valid, exc.fix) from None
