"""``capssim demosaic``: DoFP colour-polarization demosaicking of a real raw mosaic from a camera."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from capssim.cli._options import DeviceOption, OverwriteOption, ThreadsOption, apply_compute
from capssim.conventions import DEFAULT_DOFP_LAYOUT, dofp_layout, dofp_layout_name
from capssim.errors import InputError, UnknownNameError
from capssim.files.imageio import atomic_directory, atomic_write_json, check_output_free, read_image, write_tiff
from capssim.runtime.data_range import warn_out_of_range
from capssim.runtime.resources import MEMORY_LIMIT_ENV, check_image_memory

DOFP_METHODS = ("dofp-eari", "dofp-bilinear", "dofp-igri2", "dofp-jcpd", "cpdnet", "dofp-nafnet")
#: peak bytes per raw mosaic pixel of ``capssim demosaic`` (the float copies of the mosaic, the (12, H, W)
#: output, the method's working arrays and the previews; measured 1.05-1.15 KiB with dofp-eari and dofp-igri2)
DEMOSAIC_BYTES_PER_PIXEL = 1280


def read_raw_mosaic(path: Path, *, white_level: Optional[float] = None, black_level: float = 0.0,
                    trim_odd: bool = False):
    """Read a raw DoFP mosaic (8/16-bit PNG or TIFF, or float TIFF) as float on [0, 1] of full scale.

    Returns ``(mosaic float32 (H, W), saturated bool (H, W), info dict)``. Integer data map
    ``(DN - black_level) / (white_level - black_level)`` with ``white_level`` defaulting to the
    container maximum (255 or 65535; give e.g. 4095 for 12-bit data in a 16-bit file). Pixels at
    or above ``white_level`` are reported as saturated. An image with three identical channels
    (a grey mosaic saved as RGB) is accepted as one channel; any other channel count is an error.
    Odd sides are an error unless ``trim_odd``, which drops the last row and/or column (the
    2x2 polarizer cell is anchored at the top-left pixel, so the layout is unchanged).
    """
    raw, bits = read_image(path, argument="RAW")
    info: dict = {"path": str(path), "bit_depth": bits, "stored_shape": list(raw.shape)}
    if raw.ndim == 3:
        if raw.shape[2] in (3, 4) and np.array_equal(raw[..., 0], raw[..., 1]) and np.array_equal(raw[..., 0], raw[..., 2]):
            raw = raw[..., 0]
            info["note"] = "three identical channels read as one"
        else:
            raise InputError("RAW", f"{path} with shape {raw.shape}",
                             "a single-channel raw mosaic (H, W) straight from the sensor",
                             "A demosaicked colour image cannot be demosaicked again; export the raw frame.")
    if raw.ndim != 2:
        raise InputError("RAW", f"{path} with shape {raw.shape}", "a single-channel raw mosaic (H, W)")
    h, w = raw.shape
    if h % 2 or w % 2:
        if not trim_odd:
            raise InputError("RAW", f"{path} of odd size {h}x{w}",
                             "an even height and width (whole 2x2 polarizer cells)",
                             "Pass --trim-odd to drop the last row/column.")
        raw = raw[: h - h % 2, : w - w % 2]
        info["trimmed_to"] = list(raw.shape)
    if bits == 0:
        if white_level is not None or black_level:
            raise InputError("--white-level/--black-level", "given for a float image",
                             "levels only for 8- or 16-bit integer data")
        mosaic = raw.astype(np.float32)
        if not np.all(np.isfinite(mosaic)):
            raise InputError("RAW", f"{int(np.sum(~np.isfinite(mosaic)))} NaN/inf values in {path}", "finite values")
        saturated = mosaic >= 1.0
        warn_out_of_range(f"RAW {path.name}", mosaic, low=0.0, high=1.0,
                          consequence="negative values are used as they are, values >= 1 count as saturated")
        info.update(white_level=1.0, black_level=0.0)
    else:
        top = float(2 ** bits - 1)
        white = top if white_level is None else float(white_level)
        if not (0 <= black_level < white <= top):
            raise InputError("--white-level/--black-level", f"black {black_level}, white {white}",
                             f"0 <= black < white <= {int(top)} for {bits}-bit data")
        check_black_level(raw, black_level, path)
        saturated = raw.astype(np.float64) >= white
        mosaic = ((raw.astype(np.float64) - black_level) / (white - black_level)).astype(np.float32)
        info.update(white_level=white, black_level=float(black_level))
    info["shape"] = list(mosaic.shape)
    info["saturated_pixels"] = int(saturated.sum())
    return mosaic, saturated, info


def check_black_level(raw: np.ndarray, black_level: float, path: Path) -> None:
    """Refuse a ``--black-level`` at or above every pixel of ``raw`` (an all-black result); warn, with the
    count, when some pixels lie below it (they map to negative values)."""
    if not black_level:
        return
    top = int(raw.max()) if raw.size else 0
    if black_level >= top:
        raise InputError("--black-level", black_level, f"a DN below the brightest pixel of {path.name} ({top})",
                         "Use the sensor's black level (its datasheet, or a dark frame's mean), e.g. --black-level 0.")
    warn_out_of_range(f"RAW {path.name}", raw, low=black_level, high=None, below_means="below --black-level",
                      consequence="they map to negative values")


def demosaic(
    raw: Path = typer.Argument(..., help="Raw DoFP mosaic: 8/16-bit PNG or TIFF (or float TIFF), one channel."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder to create."),
    layout: str = typer.Option(DEFAULT_DOFP_LAYOUT, "--dofp-layout", help="2x2 polarizer cell: sony ([[90,45],[135,0]]) | "
                                                              "0-45-135-90 | four angles row-major like 90-45-135-0."),
    method: str = typer.Option("dofp-eari", "--method", "-m", help=f"Demosaicking method: {' | '.join(DOFP_METHODS)}."),
    white_level: Optional[float] = typer.Option(None, "--white-level",
                                                help="DN of full scale (default: 255 or 65535 by container)."),
    black_level: float = typer.Option(0.0, "--black-level", help="DN of black (subtracted)."),
    trim_odd: bool = typer.Option(False, "--trim-odd", help="Drop the last row/column of an odd-sized mosaic."),
    dolp_max: float = typer.Option(0.5, "--dolp-max", help="DoLP shown fully saturated in the AoP preview."),
    physical_projection: bool = typer.Option(
        True, "--physical-projection/--no-physical-projection",
        help="Project the output onto physically valid intensities (>= 0, I0 + I90 = I45 + I135, DoLP <= 1)."),
    overwrite: bool = OverwriteOption,
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Demosaick a real colour-polarization DoFP raw mosaic.

    Writes OUTPUT/demosaicked.tiff (12, H, W) float32 (channel c = 3*p + k, p over 0/45/90/135 deg,
    k over R/G/B), previews intensity.png, dolp.png, aop.png, panel.png (the three with titles, the
    intensity and DoLP scales and the AoP colour key), and demosaic.json (with each preview's scale).
    """
    # start-up time: the previews and the methods pull torch
    from capssim.reconstruct.registry import StageTimer, dofp_array_function
    from capssim.visualize import preview_scales, write_previews

    dev = apply_compute(threads, device)
    if method not in DOFP_METHODS:
        raise UnknownNameError("DoFP method", method, list(DOFP_METHODS))
    if not (math.isfinite(dolp_max) and 0.0 < dolp_max <= 1.0):
        raise InputError("--dolp-max", dolp_max, "a DoLP in (0, 1] (shown fully saturated in the AoP preview)",
                         "Try --dolp-max 0.5.")
    cell = dofp_layout(layout)
    check_output_free(output, overwrite=overwrite)
    check_image_memory("RAW", raw, DEMOSAIC_BYTES_PER_PIXEL, what="demosaicking",
                       fix=f"Crop the mosaic, or raise {MEMORY_LIMIT_ENV} if the machine has the memory.")
    t0 = time.perf_counter()
    mosaic, saturated, info = read_raw_mosaic(raw, white_level=white_level, black_level=black_level, trim_odd=trim_odd)
    timer = StageTimer(dev)
    image = dofp_array_function(method)(mosaic, layout=cell, device=dev, timer=timer)
    image = np.asarray(image, dtype=np.float32)
    projection = None
    if physical_projection:
        from capssim.stokes.physical_validity import project_to_physical  # torch: imported when used

        with timer.stage("physical_projection"):
            image, projection = project_to_physical(image)
    record = {
        "command": "capssim demosaic", "method": method, "layout": [list(r) for r in cell],
        "layout_name": dofp_layout_name(cell), "input": info, "output_shape": list(image.shape),
        "channel_order": "c = 3*p + k, p over (0,45,90,135) deg, k over (R,G,B)", "device": str(dev),
        "stages_s": dict(timer.stages), "wall_time_s": time.perf_counter() - t0,
        "physical_projection": None if projection is None else projection.to_dict(),
        "previews": preview_scales(image, dolp_max=dolp_max),
    }
    with atomic_directory(output, overwrite=overwrite) as tmp:
        write_tiff(tmp / "demosaicked.tiff", image)
        write_previews(image, tmp, dolp_max=dolp_max, title=f"{raw.name}: {method}, layout "
                       f"{dofp_layout_name(cell)}, {image.shape[2]}x{image.shape[1]} px")
        atomic_write_json(tmp / "demosaic.json", record)
    h, w = image.shape[1:]
    typer.echo(f"wrote {output}: {method}, layout {dofp_layout_name(cell)}, {h}x{w} x 12 channels, "
               f"{info['saturated_pixels']} saturated input pixels ({record['wall_time_s']:.2f} s)")


def register(app: typer.Typer) -> None:
    app.command("demosaic")(demosaic)
