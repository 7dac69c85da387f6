"""``capssim bench SUBJECT``: every benchmark of capssim behind one command-line shape.

Subjects (``capssim.eval.benchmarks``): ``suite`` (scenes x methods x noise levels, resume,
regression baselines, report and results page), ``reconstruct`` (time and memory per stage of
``caps``), ``registration`` (warp error and time per capture), ``dofp`` (the DoFP baselines on
the published protocol), ``render`` (the rendering choices), ``dataset`` (generation
throughput) and ``map`` (a design map, a sweep of conditions: :mod:`capssim.cli.bench_map`). They
follow the command-line grammar (docs: guides/cli.md): inputs positional,
``-o/--output`` only for what the subject makes (``suite``: its output folder), ``--json`` prints
the measurements as JSON to stdout (the tables then go to stderr), lists by repetition
(``-m/--method``, ``--scene``, ``--size``, ``--device``, ``-w/--workers``), and ``--threads`` and
``--device`` on every subject.
"""

from __future__ import annotations

import os
from functools import partial
from pathlib import Path
from typing import List, Optional

import typer

from capssim.cli._options import (
    DEFAULT_DEVICE,
    DEVICE_HELP,
    DEVICES,
    DeviceOption,
    JsonOption,
    ThreadsOption,
    apply_compute,
    check_device,
    check_iterations,
    echo_json,
    number_in,
)
from capssim.cli._setup_options import DofpLayoutOption
from capssim.cli.bench_budget import add_budget_command
from capssim.cli.bench_compare import add_compare_command
from capssim.cli.bench_map import add_map_command
from capssim.cli.bench_suite import add_suite_command
from capssim.cli.bench_uncertainty import add_uncertainty_command

bench_app = typer.Typer(name="bench", no_args_is_help=True, rich_markup_mode=None,
                        help="Benchmarks: capssim bench SUBJECT [options] with SUBJECT in suite, reconstruct, "
                             "registration, dofp, render, dataset, budget, compare, map, uncertainty.")

RepeatsOption = typer.Option(1, "--repeats", help="Runs of each measurement; the tables show the fastest.",
                             callback=number_in("--repeats", 1, 1000, what="runs"))
MethodsOption = typer.Option(None, "--method", "-m", metavar="METHOD", help="Method (repeatable).")
ScenesOption = typer.Option(None, "--scene", metavar="SCENE", help="Scene (repeatable).")


def _set_threads(threads: Optional[int], device: str, *, adaptive: bool = False):
    """--threads, else $CAPSSIM_THREADS, else capssim.runtime.threads' default, inherited by workers; returns the
    ``torch.device`` of --device. Benchmarks other than ``reconstruct`` (the default's own benchmark) keep
    one fixed count, so that their timings compare within a run: the default ``auto`` is then its starting count."""
    from capssim.runtime.threads import resolve_threads  # start-up time: pulls torch

    return apply_compute(threads if adaptive or threads is not None else resolve_threads(None), device)


def _say(as_json: bool):
    """``typer.echo`` of the human-readable text: to stderr with ``--json`` (stdout holds only the JSON)."""
    return partial(typer.echo, err=as_json)


# -- suite (capssim.cli.bench_suite) -------------------------------------------------------------
add_suite_command(bench_app)


# -- reconstruct ---------------------------------------------------------------------------------
def parse_hr_size(text) -> "int | tuple[int, int]":
    """``--size`` of ``bench reconstruct``: ``N`` (``N x N``) or ``WxH`` (width x height, HR pixels), multiples of 4
    of at least 16 whose scene fits the memory limit; ``N`` stays an int, ``WxH`` becomes ``(W, H)``."""
    from capssim.errors import InputError
    from capssim.runtime.resources import SCENE_BYTES_PER_HR_PIXEL, check_memory

    parts = str(text).strip().lower().replace("×", "x").split("x")
    if len(parts) > 2 or not all(p.strip().isdigit() for p in parts):
        raise InputError("--size", repr(text), "N or WxH in HR pixels (e.g. --size 512, --size 2560x2048)",
                         "Write the width, an x and the height, with no spaces.")
    width, height = int(parts[0]), int(parts[-1])
    if any(side < 16 or side % 4 for side in (width, height)):
        w4, h4 = (max(16, side - side % 4) for side in (width, height))
        raise InputError("--size", text, "sides that are multiples of 4 and at least 16 (the camera model's HR grid)",
                         f"Try --size {w4}" + ("." if len(parts) == 1 else f"x{h4}."))
    check_memory("--size", float(width) * height * SCENE_BYTES_PER_HR_PIXEL, what=f"a {width}x{height} scene",
                 fix="Use a smaller --size.")
    return width if len(parts) == 1 else (width, height)


def _check_caps_methods(names):
    """``-m`` names of registered CAPS-input methods, in order, without repeats."""
    from capssim.errors import InputError
    from capssim.reconstruct import available_methods, get_method  # start-up time

    for name in names:
        get_method(name)  # UnknownNameError lists the valid names
        if available_methods()[name].input_kind != "caps":
            caps = sorted(n for n, spec in available_methods().items() if spec.input_kind == "caps")
            raise InputError("--method", name, "a method of CAPS captures: " + ", ".join(caps),
                             "Time DoFP methods with 'capssim bench dofp'.")
    return list(dict.fromkeys(names))


def _parse_sizes(values):
    return None if values is None else [parse_hr_size(v) for v in values]


@bench_app.command("reconstruct")
def reconstruct(
    gt: Optional[Path] = typer.Argument(None, metavar="[GT]", help="Ground-truth scene (default: ../shared/data/gt/qiu-kettle if "
                                                   "present, else a synthetic scene)."),
    sizes: List[str] = typer.Option(["256", "512", "1024"], "--size", metavar="N|WxH",
                                    help="HR output size, N for NxN or width x height, e.g. 2560x2048 (the prototype's "
                                         "full frame); repeatable.", callback=_parse_sizes),
    devices: List[str] = typer.Option([DEFAULT_DEVICE], "--device", metavar="|".join(DEVICES), callback=check_device,
                                      help=DEVICE_HELP + " Repeatable: one timing per device."),
    iterations: Optional[int] = typer.Option(None, "--iterations", help="ADMM iterations of every method (default: "
                                             "each method's own; caps: 25, the paper's).", callback=check_iterations),
    methods: List[str] = typer.Option(["caps"], "--method", "-m", metavar="NAME",
                                      help="CAPS method to time (repeatable), each on the same capture, e.g. "
                                           "-m caps -m caps-plus.", callback=_check_caps_methods),
    repeats: int = RepeatsOption,
    threads: Optional[int] = ThreadsOption,
    estimated_warps: bool = typer.Option(False, "--estimated-warps", help="Time the registration too."),
    tile: Optional[int] = typer.Option(None, "--tile", metavar="PIXELS",
                                       help="Also reconstruct in tiles of this HR core side; untiled only where the "
                                            "memory estimate fits the machine.",
                                       callback=number_in("--tile", 64, 65536, what="HR pixels")),
    plot: Optional[Path] = typer.Option(None, "--plot", metavar="PNG",
                                        help="Also write a plot of time and peak memory against the pixel count."),
    as_json: bool = JsonOption,
) -> None:
    """Wall time and peak memory per stage of 'caps' (or each -m method) at its defaults, each run in a fresh process."""
    resolved = list(dict.fromkeys(_set_threads(threads, d, adaptive=True).type for d in devices))
    from capssim.eval.benchmarks.reconstruct import run_benchmark
    from capssim.eval.benchmarks.reconstruct_report import format_tables, plot_scaling

    results = run_benchmark(sizes=sizes, devices=resolved, iterations=iterations, repeats=repeats, gt=gt,
                            true_warps=not estimated_warps, threads=threads, tile=tile, methods=methods,
                            log=lambda msg: typer.echo(msg, err=True))
    _say(as_json)(format_tables(results))
    if plot is not None:
        _say(as_json)(f"plot: {plot_scaling(results, plot)}")
    if as_json:
        echo_json(results)


# -- registration --------------------------------------------------------------------------------
@bench_app.command("registration")
def registration(
    captures: List[Path] = typer.Argument(..., metavar="CAPTURE...",
                                          help="Capture folders with true homographies (simulated or rendered)."),
    mode: str = typer.Option("local-correlation", "--registration", help="Registration mode (as capssim "
                                                                         "reconstruct --registration)."),
    stokes_weight: Optional[float] = typer.Option(None, "--stokes-weight",
                                                  help="Weight of the Stokes-consistency term (default: the mode's)."),
    content_alignment: Optional[Path] = typer.Option(
        None, "--content-alignment", help="capssim gt-check --json record of the captures' ground truth: also "
                                          "report the error against the content warps."),
    device: str = DeviceOption,
    threads: Optional[int] = ThreadsOption,
    as_json: bool = JsonOption,
) -> None:
    """Registration error against the true warps (HR px) and time per capture."""
    from capssim.eval.benchmarks.registration import format_registration_bench, run_registration_bench

    _set_threads(threads, device)
    result = run_registration_bench([str(c) for c in captures], mode=mode, content_alignment=content_alignment,
                                    stokes_weight=stokes_weight, device=device)
    _say(as_json)(format_registration_bench(result))
    if as_json:
        echo_json(result)


# -- dofp ----------------------------------------------------------------------------------------
@bench_app.command("dofp")
def dofp(
    gt_root: Optional[Path] = typer.Argument(None, metavar="[GT_ROOT]", help="Folder holding the scene folders (default: "
                                                        "../shared/data/gt)."),
    scenes: List[str] = typer.Option(["qiu-kettle", "qiu-cellphonecases"], "--scene", metavar="SCENE",
                                     help="Scene folder under GT_ROOT (repeatable)."),
    methods: List[str] = typer.Option(["dofp-bilinear", "dofp-eari"], "--method", "-m", metavar="METHOD",
                                      help="DoFP method (repeatable)."),
    layout: str = DofpLayoutOption,
    psf_sigma_hr_px: float = typer.Option(
        0.0, "--psf-sigma-hr-px", callback=number_in("--psf-sigma-hr-px", 0.0, what="HR pixels; 0 = no blur"),
        help="Gaussian optical PSF std, HR px. Default 0: the published DoFP protocol has no blur (a capture's "
             "camera set-up default is 0.5)."),
    border: Optional[int] = typer.Option(None, "--border", help="Border crop of the metrics (default: Tokyo Tech's 15)."),
    device: str = DeviceOption,
    repeats: int = RepeatsOption,
    threads: Optional[int] = ThreadsOption,
    eari_variants: bool = typer.Option(False, "--eari-variants", help="Score dofp-eari under its numerical variants."),
    as_json: bool = JsonOption,
) -> None:
    """The DoFP demosaicking baselines on the published protocol (noise-free, Tokyo Tech / EARI scores)."""
    import torch  # start-up time

    from capssim.eval.benchmarks.dofp import format_table as dofp_table
    from capssim.eval.benchmarks.dofp import run_dofp_benchmark
    from capssim.eval.metrics import CONVENTIONS

    _set_threads(threads, device)
    rows = run_dofp_benchmark(scenes, methods, gt_root=gt_root, layout=layout, psf_sigma_hr_px=psf_sigma_hr_px,
                              border=border, device=device, repeats=repeats, eari_variants=eari_variants)
    crop = CONVENTIONS["tokyotech"].border if border is None else border
    say = _say(as_json)
    say(f"DoFP demosaicking, noise-free, layout {layout}, PSF sigma {psf_sigma_hr_px} HR px, border crop {crop} px "
        f"(MATLAB indexing); PSNR in dB (peak 1), AoP RMSE in degrees; "
        f"time: min of {repeats} run(s) on {device}, {torch.get_num_threads()} CPU thread(s)")
    say(dofp_table(rows))
    if as_json:
        echo_json(rows)


# -- render --------------------------------------------------------------------------------------
def _scene_cost_lines(rows: list[dict]) -> list[str]:
    keys = sorted({k for r in rows for k in r if k.startswith("saved:")})
    header = f"{'scene':<18} {'variant':<28} {'path':<13} {'spp':>5} {'render s':>9} {'wall s':>7}"
    lines = [header + "".join(f" {k[6:]:>22}" for k in keys)]
    for r in rows:
        line = (f"{r['scene']:<18} {r['variant']:<28} {r['path']:<13} {r['spp']:>5} {r['render_s']:>9.1f} "
                f"{r['wall_s']:>7.1f}")
        for k in keys:
            v = r.get(k)
            saved = "-" if v is None or v[0] is None else f"{v[0]:+.1f}" + (" m" if "measured" in v[1] else " e")
            line += f" {saved:>22}"
        lines.append(line)
    lines.append("saved seconds: m = measured by rendering the alternative (compile excluded), e = estimated")
    return lines


#: the scenes of the render cost table when no --scene, --warp-accuracy or --samplers is given
COST_SCENES = ("siemens-star", "aop-wheel", "colorchecker", "textured", "materials", "window-reflection",
               "water-glare", "polarization-star", "dolp-ramp")


@bench_app.command("render")
def render(
    scenes: Optional[List[str]] = typer.Option(None, "--scene", metavar="SCENE",
                                               help="Scene of the cost table (repeatable; default: nine library "
                                                    "scenes, none with --warp-accuracy or --samplers)."),
    size: int = typer.Option(128, "--size", help="HR size."),
    spp: Optional[int] = typer.Option(None, "--spp", help="Fixed spp per HR pixel (default: --target-noise)."),
    target_noise: Optional[float] = typer.Option(None, "--target-noise", help="Monte-Carlo target (default 0.004).",
                                                 callback=number_in("--target-noise", 0.0, 1.0, low_open=True)),
    measure: bool = typer.Option(False, "--measure-savings", help="Measure each choice's saving (slow)."),
    warp_scene: Optional[str] = typer.Option(None, "--warp-accuracy",
                                             help="Planar scene: raw error of the planar warp vs real renders."),
    warp_spp: int = typer.Option(256, "--warp-spp", help="spp per HR pixel for --warp-accuracy."),
    sampler_scene: Optional[str] = typer.Option(None, "--samplers",
                                                help="Scene: RMS error of independent vs multijitter sampling."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
    as_json: bool = JsonOption,
) -> None:
    """Tables behind the rendering choices: cost per scene, planar-warp accuracy, sampler gain."""
    from capssim.eval.benchmarks import render as bench  # start-up time: Mitsuba's set-up and the scenes

    _set_threads(threads, device)
    say = _say(as_json)
    measured: dict[str, list] = {}
    names = scenes or ([] if warp_scene or sampler_scene else list(COST_SCENES))
    if names:
        say(f"render cost, {size} px HR ({'--spp ' + str(spp) if spp else 'target noise'}), time in render_capture")
        measured["scene_costs"] = bench.scene_costs(names, size=size, spp=spp, target_noise=target_noise,
                                                    measure=measure)
        say("\n".join(_scene_cost_lines(measured["scene_costs"])))
    if warp_scene:
        say(f"\nplanar warp accuracy, {warp_scene}, {size} px, {warp_spp} spp, no PSF: raw frames of apertures "
            "1-3 against real per-aperture renders")
        say(f"{'method':<42} {'rms':>9} {'rel. to mean':>13} {'MC noise':>9} {'s':>6}")
        measured["warp_accuracy"] = bench.warp_accuracy(warp_scene, size=size, spp=warp_spp)
        for r in measured["warp_accuracy"]:
            noise = "-" if r["mc_noise_rms"] is None else f"{r['mc_noise_rms']:.5f}"
            secs = "-" if r["seconds"] is None else f"{r['seconds']:.1f}"
            say(f"{r['method']:<42} {r['rms']:>9.5f} {r['relative']:>12.2%} {noise:>9} {secs:>6}")
    if sampler_scene:
        say(f"\nsampler, {sampler_scene} reference view, {size} px: RMS error against a 1024 spp render")
        say(f"{'sampler':<12} {'spp':>5} {'rms error':>10}")
        measured["sampler_gain"] = bench.sampler_gain(sampler_scene, size=size)
        for r in measured["sampler_gain"]:
            say(f"{r['sampler']:<12} {r['spp']:>5} {r['rms_error']:>10.5f}")
    if as_json:
        echo_json(measured)


# -- dataset -------------------------------------------------------------------------------------
@bench_app.command("dataset")
def dataset(
    config: Path = typer.Argument(..., help="Dataset config YAML (e.g. examples/dataset-bench-gt.yaml)."),
    workers: List[int] = typer.Option([1, 2], "--workers", "-w", metavar="N", min=0,
                                      help="Local worker count to time (repeatable; 0: in this process)."),
    keep: Optional[Path] = typer.Option(None, "--keep", help="Move the generated datasets into this folder."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
    as_json: bool = JsonOption,
) -> None:
    """Dataset generation throughput (samples per hour) for each number of local workers."""
    from capssim.eval.benchmarks.dataset import format_table as dataset_table
    from capssim.eval.benchmarks.dataset import run_dataset_benchmark

    _set_threads(threads, device)
    if keep is not None:  # before any work: a file, a link loop or an unwritable place in the way
        from capssim.files.output_paths import resolve_output

        keep = resolve_output(keep, kind="folder", overwrite=True, argument="--keep")
    rows = run_dataset_benchmark(config, list(workers), keep=keep)
    say = _say(as_json)
    say(f"cores: {os.cpu_count()}, config: {config}")
    say(dataset_table(rows))
    if as_json:
        echo_json(rows)


add_budget_command(bench_app)
add_compare_command(bench_app)
add_map_command(bench_app)
add_uncertainty_command(bench_app)


def register(app: typer.Typer) -> None:
    app.add_typer(bench_app, name="bench")
