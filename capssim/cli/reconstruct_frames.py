"""``capssim reconstruct``'s full-frame options: ``--tile``, ``--memory-gb``, ``--workers``, ``--scheduler`` and a
folder of captures (docs: guides/reconstruction.md, "Full frames and tiles")."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import typer

from capssim.cli._options import number_in
from capssim.errors import InputError

TileOption = typer.Option(None, "--tile", metavar="PIXELS",
                          help="Reconstruct CAPS methods in tiles of at most PIXELS x PIXELS HR pixels (>= 64; a "
                               "margin is added and blended). Default: untiled unless the frame needs more than "
                               "--memory-gb.")
MemoryOption = typer.Option(None, "--memory-gb", metavar="GB",
                            callback=number_in("--memory-gb", 0, low_open=True, what="GiB of memory for the run"),
                            help="Memory budget (GiB) that picks the tile size (all --workers together). Default: "
                                 "80 % of the free memory, or $CAPSSIM_MEMORY_LIMIT_GB.")
WorkersOption = typer.Option(None, "--workers", "-w", metavar="N",
                             help="Local Dask workers (processes of 1 thread): the tiles of one capture, or the "
                                  "captures of a folder, run side by side.")
SchedulerOption = typer.Option(None, "--scheduler", metavar="ADDR",
                               help="Address of a running Dask scheduler (e.g. tcp://host:8786) to run tiles or "
                                    "frames on; its workers must see the capture folders.")


def check_full_frame_options(tile: Optional[int], workers: Optional[int], scheduler: Optional[str]) -> None:
    """One-line :class:`InputError` for a bad ``--tile``, ``--workers``, ``--scheduler`` address or ``--workers``
    with ``--scheduler``."""
    from capssim.reconstruct.tiles import MIN_TILE  # start-up time

    if tile is not None and tile < MIN_TILE:
        raise InputError("--tile", tile, f"an integer >= {MIN_TILE} (HR pixels)", f"Use --tile {MIN_TILE} or more.")
    if workers is not None and scheduler is not None:
        raise InputError("--workers", workers, "no --workers with --scheduler (the cluster has its own workers)")
    if scheduler is not None:
        from capssim.dataset.generate import check_scheduler_address  # start-up time

        check_scheduler_address(scheduler)
    if workers is not None:
        if workers < 1:
            raise InputError("--workers", workers, "an integer >= 1 (local Dask worker processes)")
        from capssim.dataset.generate import check_local_workers  # start-up time

        check_local_workers(workers)


def uses_full_frames(capture: Path, workers: Optional[int], scheduler: Optional[str]) -> bool:
    """True when the run needs the full-frame driver (a folder of captures, or Dask)."""
    from capssim.reconstruct.tiles.frames import capture_folders  # start-up time

    return workers is not None or scheduler is not None or capture_folders(capture) is not None


def first_capture(capture: Path) -> Path:
    """``capture``, or the first capture folder inside it (a folder of captures)."""
    from capssim.reconstruct.tiles.frames import capture_folders  # start-up time

    folders = capture_folders(capture)
    return capture if folders is None else folders[0]


def frame_runner(tile: Optional[int], memory_gb: Optional[float]) -> Callable:
    """``run(capture, name, progress=..., **flags_and_options)`` of one capture: untiled, or tiled when asked."""
    from capssim.reconstruct.tiles.frames import reconstruct_frame  # start-up time

    def run(capture, name, **kwargs):
        return reconstruct_frame(capture, name, tile=tile, memory_gb=memory_gb, **kwargs)

    return run


def run_full_frames(capture: Path, methods: list[str], *, tile: Optional[int], memory_gb: Optional[float],
                    workers: Optional[int], scheduler: Optional[str], echo: Callable, options_of: Callable,
                    **flags) -> None:
    """Reconstruct one capture's tiles, or a folder's captures, on Dask (or here); ``echo(folder, name, record)``.

    ``options_of(name)``: the method's options; ``**flags``: the options of :func:`capssim.reconstruct.reconstruct`.

    Each finished frame is written at once; frames already finished with the same settings are skipped.
    """
    from capssim.reconstruct.tiles.distributed import DaskSession, reconstruct_frames  # start-up time
    from capssim.reconstruct.tiles.frames import capture_folders, reconstruct_frame

    folders = capture_folders(capture)
    check_frames_before_work(capture, folders, methods, tile=tile, memory_gb=memory_gb, workers=workers,
                             options_of=options_of)
    dask = workers is not None or scheduler is not None
    session = DaskSession(workers=workers, scheduler=scheduler) if dask else None
    try:
        if session is not None:
            session.__enter__()
        for name in methods:
            kwargs = {**flags, **options_of(name)}
            if folders is None:  # one capture: its tiles on the cluster
                record = reconstruct_frame(capture, name, tile=tile, memory_gb=memory_gb, workers=workers or 1,
                                           runner=session.runner, **kwargs)
                echo(capture, name, record)
                if "tiles" not in record:
                    typer.echo(f"note: {name} ran untiled (the frame fits the memory budget), so --workers/--scheduler "
                               "had nothing to share; give --tile PIXELS to split it", err=True)
                continue
            client = None if session is None else session.client
            side_by_side = workers or 1  # local frames share --memory-gb (a cluster's workers have their own)
            frame_gb = None if memory_gb is None else memory_gb / side_by_side
            for folder, record in reconstruct_frames(folders, name, client=client, tile=tile, memory_gb=frame_gb,
                                                     **kwargs):
                if record is None:
                    typer.echo(f"{folder.name}: {name} already finished (same settings); skipped")
                else:
                    echo(folder, name, record)
    finally:
        if session is not None:
            session.__exit__(None, None, None)


def check_frames_before_work(capture: Path, folders: Optional[list[Path]], methods: list[str], *,
                             tile: Optional[int], memory_gb: Optional[float], workers: Optional[int],
                             options_of: Callable) -> None:
    """Every refusal of the tiling that needs only ``meta.json`` (:func:`capssim.reconstruct.tiles.run.check_tiling`:
    the margin's options, ``--tile`` against its margin, ``--memory-gb`` against ``--workers`` tiles), for each CAPS
    method and capture, before a Dask cluster starts. One capture: its ``--workers`` tiles share ``--memory-gb``; a
    folder of captures (``folders``): its frames do, as :func:`run_full_frames` shares it."""
    from capssim.captures.capture import Capture, read_meta
    from capssim.reconstruct import get_method  # start-up time
    from capssim.reconstruct.tiles.run import check_tiling

    caps = [name for name in methods if get_method(name).input_kind == "caps"]
    if folders is None:
        frames, frame_gb, tiles_at_once = [capture], memory_gb, workers or 1
    else:
        frames, tiles_at_once = folders, 1
        frame_gb = None if memory_gb is None else memory_gb / (workers or 1)
    for folder in frames if caps else []:
        frame = Capture(meta=read_meta(folder), caps_raw=None, path=folder)  # the geometry and PSF only
        for name in caps:
            check_tiling(frame, options_of(name), tile=tile, memory_gb=frame_gb, workers=tiles_at_once)
