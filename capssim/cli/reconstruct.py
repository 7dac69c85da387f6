"""``capssim reconstruct``: run reconstruction methods on a capture (their speed: ``capssim bench reconstruct``)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from capssim.cli._options import DeviceOption, ThreadsOption, apply_compute, check_iterations
from capssim.cli.reconstruct_frames import (
    MemoryOption,
    SchedulerOption,
    TileOption,
    WorkersOption,
    check_frames_before_work,
    check_full_frame_options,
    first_capture,
    frame_runner,
    run_full_frames,
    uses_full_frames,
)
from capssim.errors import InputError

#: keywords of ``run_method`` that come from the command's flags, never from ``-p/--param``
COMMAND_FLAGS = {"device": "--device", "true_warps": "--true-warps", "registration": "--registration",
                 "progress": "--progress/--no-progress",
                 "physical_projection": "--physical-projection/--no-physical-projection",
                 "reuse_registration": "--reuse-registration/--no-reuse-registration",
                 "calibration": "--calibration", "uncertainty": "--uncertainty",
                 "uncertainty_options": "--uncertainty-calibration",
                 "start": "the Python API, reconstruct(..., start=IMAGE) (a warm start; no command flag)"}


RegistrationOption = typer.Option(
    None, "--registration", show_default=False,
    help="Registration mode when warps are estimated (default: the method's own, local-correlation for every method "
         "but array-kr, which uses fast): local-correlation (of the binomial and the demosaicked luminance, keeps the "
         "one whose registered images are more Stokes-consistent) | binomial-luminance | ri-luminance (one of the "
         "two only: faster) | stokes-subspace (Stokes-consistent data whose polarization texture biases the default) "
         "| fast (binomial, fitted at half resolution on frames of 512 HR px and more); see the docs, "
         "guides/reconstruction.md.")
UncertaintyOption = typer.Option(
    None, "--uncertainty", metavar="N",
    help="Also write error bars from an N-replicate bootstrap (e.g. 8): recon/METHOD.std.tiff, .interval90.tiff and "
         ".stokes-uncertainty.tiff, calibrated 90 %% intervals (guides/reconstruction.md, 'Error bars').")
UncertaintyCalibrationOption = typer.Option(
    None, "--uncertainty-calibration", metavar="FILE|none",
    help="With --uncertainty: the calibration of the intervals (default: the shipped one; 'none': the raw "
         "bootstrap's 1.645 std).")


def parse_options(pairs: List[str]) -> dict:
    """``KEY=VALUE`` strings -> dict (values stay strings; each method converts its own)."""
    options = {}
    for pair in pairs or []:
        if "=" not in pair:
            raise InputError("--param", repr(pair), "KEY=VALUE (e.g. --param c1=0.002)")
        key, value = pair.split("=", 1)
        key = key.strip()
        if not key:
            raise InputError("--param", repr(pair), "a non-empty KEY before '='")
        if key in COMMAND_FLAGS:
            raise InputError("--param", repr(pair), "a method option (capssim reconstruct --list shows the methods)",
                             f"'{key}' is set by the command's own flag: use {COMMAND_FLAGS[key]}.")
        options[key] = value.strip()
    return options


def expand_methods(names: List[str], capture_path: Path) -> list[str]:
    """Resolve ``all`` (every method the capture has input for) and check each name."""
    # start-up time: the capture format and the registry pull torch
    from capssim.captures.capture import read_meta
    from capssim.reconstruct import available_methods, get_method

    meta = read_meta(capture_path)
    has_dofp = "dofp_raw" in meta.get("files", {})
    out: list[str] = []
    for name in names:
        if name == "all":
            out.extend(n for n, spec in available_methods().items()
                       if spec.input_kind == "caps" or (spec.input_kind == "dofp" and has_dofp))
        else:
            get_method(name)  # UnknownNameError lists the valid names
            out.append(name)
    return list(dict.fromkeys(out))


def reconstruct(
    capture: Optional[Path] = typer.Argument(None, help="Capture folder (from 'capssim simulate' or "
                                                        "'capssim render'), or a folder of capture folders (each "
                                                        "written as it finishes; finished ones are skipped); not "
                                                        "needed with --list."),
    method: List[str] = typer.Option(["caps"], "--method", "-m", metavar="METHOD",
                                     help="Method name; repeat for several, or 'all'. "
                                          "'capssim reconstruct --list' shows them."),
    iterations: Optional[int] = typer.Option(None, "--iterations", help="ADMM iterations (paper: 25).",
                                             callback=check_iterations),
    true_warps: bool = typer.Option(False, "--true-warps",
                                    help="Use the homographies stored in meta.json instead of estimating them."),
    registration: Optional[str] = RegistrationOption,
    param: List[str] = typer.Option([], "--param", "-p", metavar="KEY=VALUE",
                                    help="Method option KEY=VALUE (repeatable), e.g. -p c1=0.002."),
    list_methods: bool = typer.Option(False, "--list", help="List the registered methods and exit."),
    show_options: Optional[str] = typer.Option(None, "--options", metavar="METHOD",
                                               help="List every -p option of METHOD (name, default, valid values, "
                                                    "meaning) and exit."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
    reuse_registration: bool = typer.Option(
        True, "--reuse-registration/--no-reuse-registration",
        help="Reuse the warps stored in CAPTURE/registration/ for the same input and mode (estimated once per "
             "capture); --no-reuse-registration registers again and replaces them."),
    threads: Optional[int] = ThreadsOption,
    calibration: Optional[str] = typer.Option(
        None, "--calibration",
        help="Model of the array for CAPS methods: a capssim-rig file (capssim calibrate), 'truth' (the capture's "
             "true rig, simulated/rendered), or 'ideal'. Default: the capture's meta.json calibration_file if it "
             "names one, else the ideal array."),
    physical_projection: bool = typer.Option(
        True, "--physical-projection/--no-physical-projection",
        help="Project the output onto physically valid intensities (>= 0, I0 + I90 = I45 + I135, DoLP <= 1) "
             "where all four angles are observed."),
    uncertainty: Optional[int] = UncertaintyOption,
    uncertainty_calibration: Optional[str] = UncertaintyCalibrationOption,
    tile: Optional[int] = TileOption,
    memory_gb: Optional[float] = MemoryOption,
    workers: Optional[int] = WorkersOption,
    scheduler: Optional[str] = SchedulerOption,
    device: str = DeviceOption,
) -> None:
    """Reconstruct a capture; writes recon/METHOD.tiff (12, 2H, 2W) and recon/METHOD.json."""
    apply_compute(threads, device)
    if list_methods or show_options is not None:
        typer.echo(method_list_lines() if list_methods else method_option_lines(show_options))
        return
    if capture is None:
        raise typer.BadParameter("missing the CAPTURE folder (e.g. 'capssim reconstruct runs/cap -m caps'); "
                                 "only --list runs without one", param_hint="CAPTURE")
    options = parse_options(param)
    check_full_frame_options(tile, workers, scheduler)
    check_iterations_agree(options, iterations)
    flags = dict(device=device, true_warps=true_warps, registration=registration,
                 physical_projection=physical_projection, reuse_registration=reuse_registration, calibration=calibration,
                 **check_uncertainty_flags(capture, uncertainty, uncertainty_calibration,
                                           tiled=tile is not None or uses_full_frames(capture, workers, scheduler)))
    if uses_full_frames(capture, workers, scheduler):  # a folder of captures, or tiles/frames on Dask
        names = expand_methods(method, first_capture(capture))
        check_recon_outputs(capture, names)
        check_before_work(capture, names, options, iterations, tiled=True, calibration=calibration)
        run_full_frames(capture, names, tile=tile, memory_gb=memory_gb, workers=workers, scheduler=scheduler,
                        echo=lambda folder, name, record: _echo_record(folder, name, record),
                        options_of=lambda name: _method_options(name, options, iterations), **flags)
        return
    rows = []
    names = expand_methods(method, capture)
    check_recon_outputs(capture, names)
    check_before_work(capture, names, options, iterations, calibration=calibration, frame=(tile, memory_gb))
    for name in names:
        record = _run_one(capture, name, iterations=iterations, progress=progress, options=options,
                          run=frame_runner(tile, memory_gb), **flags)
        rows.append((name, record["wall_time_s"]))
        _echo_record(capture, name, record)
    if len(rows) > 1:
        typer.echo("method                    wall time (s)")
        for name, wall in rows:
            typer.echo(f"{name:24s}  {wall:10.2f}")


def check_uncertainty_flags(capture: Path, uncertainty: Optional[int], calibration: Optional[str], *,
                            tiled: bool) -> dict:
    """``--uncertainty N`` and ``--uncertainty-calibration``, checked before any work: the count, the calibration
    file, a capture with a noise model, one capture run untiled; the keywords of ``run_method`` they give ({}
    without them)."""
    from capssim.captures.capture import Capture, read_meta
    from capssim.reconstruct.uncertainty.bootstrap import check_noise, check_replicates  # start-up time
    from capssim.reconstruct.uncertainty.conformal import load_calibration

    if uncertainty is None and calibration is None:
        return {}
    if uncertainty is None:
        raise InputError("--uncertainty-calibration", repr(calibration), "a calibration for --uncertainty N",
                         "Add --uncertainty 8, or drop --uncertainty-calibration.")
    count = check_replicates(uncertainty)
    if tiled:
        raise InputError("--uncertainty", count, "a run of one capture, untiled",
                         "Drop --tile/--workers/--scheduler, or reconstruct one capture folder at a time.")
    if calibration not in (None, "none"):
        load_calibration(calibration)
    check_noise(Capture(meta=read_meta(capture), caps_raw=None, path=capture))
    return {"uncertainty": count, "uncertainty_options": {"calibration": calibration}}


def method_list_lines() -> str:
    """What ``capssim reconstruct --list`` prints: every registered method with what its defaults were tuned on, a
    plug-in's package after it; then the plug-ins that could not register."""
    from capssim.reconstruct import available_methods  # start-up time
    from capssim.reconstruct.plugins import broken_plugins

    methods = available_methods()
    lines = []
    for name, spec in methods.items():
        tuned = f" (defaults tuned on: {', '.join(spec.tuned_on)})" if spec.tuned_on else ""
        source = "" if spec.plugin is None else f"  (plug-in: {spec.plugin.label().split('(', 1)[1]}"
        lines.append(f"{name:24s} [{spec.input_kind}] {spec.description}{tuned}{source}")
    for name, message in broken_plugins().items():  # plug-ins that could not take their name
        if name not in methods or methods[name].plugin is None:
            lines.append(f"{name:24s} [broken] {message}")
    return "\n".join(lines)


def method_option_lines(name: str) -> str:
    """What ``capssim reconstruct --options NAME`` prints: every ``-p`` option of the method, one per line."""
    from capssim.reconstruct import get_method  # start-up time
    from capssim.reconstruct.pipeline.option_table import format_options

    spec = get_method(name)
    if spec.options is None:
        return (f"{name}: lists no options here; its reference ({spec.reference}) and the methods guide describe "
                "what it takes.")
    return format_options(name, spec.options())


def check_recon_outputs(capture: Path, names: list[str]) -> None:
    """Before any work: refuse a file or folder in the way of ``recon/NAME.tiff`` / ``recon/NAME.json`` of every
    method, in the capture (or in each capture of a folder of captures)."""
    from capssim.files.output_paths import check_files_in
    from capssim.reconstruct.tiles.frames import capture_folders  # start-up time

    for folder in capture_folders(capture) or [capture]:
        check_files_in(folder, [f"recon/{name}{ext}" for name in names for ext in (".tiff", ".json")],
                       argument="CAPTURE")


def check_iterations_agree(options: dict, iterations: Optional[int]) -> None:
    """Refuse ``--iterations`` and ``-p iterations=`` together unless they are equal (one would be dropped)."""
    if iterations is None or "iterations" not in options:
        return
    from capssim.reconstruct.pipeline.options import coerce_option  # start-up time

    if coerce_option("iterations", options["iterations"], int) != iterations:
        raise InputError("--iterations", f"{iterations} and -p iterations={options['iterations']}",
                         "one of the two (or both equal)", "Drop -p iterations=..., or --iterations.")


def check_before_work(capture: Path, names: list[str], options: dict, iterations: Optional[int], *,
                      tiled: Optional[bool] = None, calibration: Optional[str] = None,
                      frame: Optional[tuple] = None) -> None:
    """Every check that can fail before the first method runs: each method's options
    (:func:`check_method_options`), ``-p track_psnr`` (:func:`check_track_psnr`), then the raw frames' range
    (:func:`capssim.cli.reconstruct_checks.warn_raw_range`, a warning). ``frame``: ``(--tile, --memory-gb)`` of one
    capture run here (``tiled`` then defaults to ``--tile`` given), whose tiling is checked from meta.json."""
    from capssim.cli.reconstruct_checks import check_method_options, check_track_psnr, warn_raw_range
    from capssim.reconstruct import get_method  # start-up time
    from capssim.reconstruct.tiles.frames import capture_folders

    for name in names:
        check_method_options(name, _method_options(name, options, iterations, quiet=True), shared=len(names) > 1)
    folders = capture_folders(capture) or [capture]
    if any(get_method(name).input_kind == "caps" for name in names):  # DoFP methods take no array model
        _check_calibration(folders, calibration)
    check_track_psnr(options, folders, tiled=bool(tiled) if tiled is not None else bool(frame and frame[0] is not None))
    if frame is not None:  # one capture run here: its tiling (--tile, --memory-gb), from meta.json
        check_frames_before_work(capture, None, names, tile=frame[0], memory_gb=frame[1], workers=None,
                                 options_of=lambda name: _method_options(name, options, iterations, quiet=True))
    kinds = {get_method(name).input_kind for name in names}
    for folder in folders:
        warn_raw_range(folder, kinds)


def _check_calibration(folders: list[Path], calibration: Optional[str]) -> None:
    """Read the calibration each capture would use (``--calibration FILE``, or its ``meta.json`` calibration_file)
    as the methods will read it, so that a file they refuse (a gain of 1e300) is refused before any method runs."""
    from capssim.captures.capture import Capture, read_meta
    from capssim.reconstruct.calibration_model import resolve_calibration  # start-up time

    for folder in folders:
        resolve_calibration(Capture(meta=read_meta(folder), caps_raw=None, path=folder), calibration)


def _method_options(name: str, options: dict, iterations: Optional[int], *, quiet: bool = False) -> dict:
    """The method's ``-p`` options, with ``--iterations`` for the CAPS-input methods (DoFP methods take none)."""
    from capssim.reconstruct import get_method  # start-up time

    method_options = dict(options)
    if iterations is not None:
        if get_method(name).input_kind == "caps":
            method_options["iterations"] = iterations
        elif not quiet:
            typer.echo(f"note: --iterations does not apply to the DoFP method {name}; not passed", err=True)
    return method_options


def _run_one(capture: Path, name: str, *, iterations: Optional[int], progress: bool, options: dict,
             run=None, **flags) -> dict:
    """``run_method`` of one method under a progress bar (stderr); ``--iterations`` to the CAPS-input methods only."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from capssim.reconstruct import run_method  # start-up time

    method_options = _method_options(name, options, iterations)
    run = run or run_method
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[message]}"), TimeElapsedColumn(), console=Console(stderr=True),
                  disable=not progress, transient=False) as bar:
        task = bar.add_task(name, total=None, message="")

        def report(done: int, total: int, message: str = "") -> None:
            bar.update(task, completed=done, total=total, message=message)

        return run(capture, name, progress=report, **flags, **method_options)


def _echo_record(capture: Path, name: str, record: dict) -> None:
    """The lines ``capssim reconstruct`` prints of one method's record."""
    stages = ", ".join(f"{k} {v:.2f}s" for k, v in record["stages_s"].items())
    typer.echo(f"{name}: {record['wall_time_s']:.2f} s ({stages}) -> {capture / 'recon' / (name + '.tiff')}")
    reg = record.get("registration", {})
    err = reg.get("error_hr_px_median")
    if err is not None:
        typer.echo(f"  registration ({reg.get('source')}): median error {err:.4f} HR px, "
                   f"max {reg.get('error_hr_px_max', float('nan')):.4f}")
    psnr = [h["psnr_db"] for h in record.get("history") or [] if isinstance(h, dict) and h.get("psnr_db") is not None]
    if psnr:
        typer.echo(f"  PSNR against gt.tiff (track_psnr): {psnr[0]:.2f} dB at iteration 1, {psnr[-1]:.2f} dB at "
                   f"iteration {len(psnr)}")
    if record.get("calibration"):
        typer.echo(f"  array model: calibration {record['calibration'].get('source')}")
    if record.get("uncertainty"):
        unc = record["uncertainty"]
        typer.echo(f"  error bars: {unc['replicates']} replicates in {unc['time_s']:.2f} s, calibration "
                   f"{unc['calibration'].get('name')} -> recon/{name}.std.tiff, .interval90.tiff, "
                   ".stokes-uncertainty.tiff")


def register(app: typer.Typer) -> None:
    app.command("reconstruct")(reconstruct)
