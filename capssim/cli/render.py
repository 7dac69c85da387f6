"""``capssim render`` and ``capssim scenes``: physically based captures from the scene library."""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import List, Optional

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from capssim.cli._options import (
    DeviceOption,
    OverwriteOption,
    SeedOption,
    ThreadsOption,
    apply_compute,
    number_in,
)
from capssim.cli._setup_options import SetupOptions, check_rig_psfs, rig_homographies, with_setup_options
from capssim.errors import InputError
from capssim.files.imageio import check_output_file, check_output_free, write_png


def _parse_pairs(pairs: Optional[List[str]], option: str) -> dict:
    out: dict = {}
    for item in pairs or []:
        if "=" not in item:
            raise InputError(option, repr(item), "KEY=VALUE", f"For example {option} cycles=36.")
        key, value = item.split("=", 1)
        key = key.strip().replace("-", "_")
        text = value.strip()
        try:
            parsed = json.loads(text)
        except json.JSONDecodeError:
            parsed = text
        out[key] = parsed
    return out


def _render_with_rig(scene: str, **options):
    """``render_capture``; the array geometry of a ``--rig`` file is refused by that flag's name."""
    from capssim.render import render_capture

    try:
        return render_capture(scene, **options)
    except InputError as exc:
        if exc.argument != "aperture_homographies":
            raise
        raise InputError("--rig", "a capssim-rig file with an array geometry, for a scene rendered per aperture",
                         "a rig file's geometry only on the planar warp path",
                         "Use a planar scene or --planar on, or a rig file without geometry.") from None


@with_setup_options
def render(
    scene: str = typer.Argument(..., help="Scene name (see 'capssim scenes')."),
    output: Path = typer.Option(..., "-o", "--output", help="Capture folder to create."),
    size: int = typer.Option(256, "--size", help="HR ground-truth size in pixels (raw frames are half)."),
    spp: Optional[int] = typer.Option(None, "--spp", help="Samples per HR pixel (default: from --target-noise)."),
    target_noise: Optional[float] = typer.Option(
        None, "--target-noise", help="RMS Monte-Carlo std of the ground truth on [0, 1] (default 0.004, or half "
                                     "the sensor noise).",
        callback=number_in("--target-noise", 0.0, 1.0, low_open=True, what="RMS std on [0, 1] full scale")),
    max_spp: int = typer.Option(1024, "--max-spp", help="Upper limit of spp per HR pixel for --target-noise."),
    seed: int = SeedOption,
    variant: str = typer.Option("auto", "--variant", help="Mitsuba variant: auto (cuda -> llvm -> scalar) or a name."),
    param: Optional[List[str]] = typer.Option(None, "--param", "-p", metavar="KEY=VALUE",
                                              help="Scene parameter KEY=VALUE (repeatable), e.g. -p cycles=36."),
    geometry: Optional[List[str]] = typer.Option(
        None, "--geometry", metavar="KEY=VALUE",
        help="Array parameter KEY=VALUE (repeatable): baseline_m, tilt_max_deg, roll_max_deg, "
                                 "focal_scale_max, converge."),
    planar: str = typer.Option("auto", "--planar", help="auto | on | off: render a planar scene once and warp."),
    oversample: Optional[int] = typer.Option(None, "--oversample",
                                             help="Render grid factor for the planar warp (default 4, 2 above 512 px)."),
    camera: str = typer.Option("Nikon 5100 (NPL)", "--camera", help="Camera sensitivities (colour-science)."),
    no_timing: bool = typer.Option(False, "--no-timing", help="Keep wall times out of meta.json (reproducible bytes)."),
    measure_savings: bool = typer.Option(False, "--measure-savings",
                                         help="Also render what each choice avoided and record measured savings."),
    preview: Optional[Path] = typer.Option(None, "--preview", help="Also write an intensity|DoLP|AoP PNG of the GT."),
    preview_white: Optional[float] = typer.Option(
        None, "--preview-white", help="Preview intensity shown white (default: 99.5th percentile).",
        callback=number_in("--preview-white", 0.0, low_open=True, what="intensity, full scale 1")),
    preview_dolp_max: float = typer.Option(0.5, "--preview-dolp-max", help="Preview DoLP shown saturated.",
                                           callback=number_in("--preview-dolp-max", 0.0, 1.0, low_open=True,
                                                              what="a DoLP", fix="Try --preview-dolp-max 0.5.")),
    setup_options: SetupOptions = SetupOptions(),
    overwrite: bool = OverwriteOption,
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Render a library scene through the four CAPS apertures and a DoFP camera (Mitsuba 3).

    Mitsuba picks its variant with --variant; --device is the torch device, checked like every command's.
    """
    apply_compute(threads, device, renderer=True)
    rig_model, rig_geometry = setup_options.rig_model()
    check_rig_psfs(rig_model, (size, size), aperture_psf_sigmas=setup_options.aperture_psf_sigmas)
    homographies = rig_homographies(rig_geometry, (size, size), fix="render at that --size")
    # these pull torch, the operators and the scene library: loaded when the command runs (start-up time)
    from capssim.captures.capture import write_capture

    t0 = time.perf_counter()
    check_output_free(output, overwrite=overwrite)
    if preview is not None:
        check_output_file(preview, argument="--preview")
    setup = setup_options.camera_setup(rig_model)
    capture = _render_with_progress(
        scene, size=size, spp=spp, seed=seed, setup=setup, variant=variant,
        scene_params=_parse_pairs(param, "--param"), geometry_params=_parse_pairs(geometry, "--geometry"),
        target_noise=target_noise, record_timing=not no_timing, planar=planar, oversample=oversample,
        camera=camera, max_spp=max_spp, measure_savings=measure_savings, aperture_homographies=homographies)
    write_capture(output, capture, overwrite=overwrite)
    _echo_capture(capture, output, scene, seed, t0)
    if preview is not None:
        from capssim.visualize import preview_panel  # pulls torch (start-up time)

        write_png(preview, preview_panel(capture.gt, white=preview_white, dolp_max=preview_dolp_max))
        typer.echo(f"  preview {preview}")


def _render_with_progress(scene: str, **options):
    """:func:`_render_with_rig` under a progress bar per stage (transient)."""
    tasks: dict = {}
    with Progress(TextColumn("{task.description:<22}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                  TimeElapsedColumn(), transient=True) as bar:
        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=max(total, 1))
            bar.update(tasks[stage], completed=done)

        return _render_with_rig(scene, progress=progress, **options)


def _echo_capture(capture, output: Path, scene: str, seed: int, t0: float) -> None:
    """The lines ``capssim render`` prints of a rendered capture: size, sampling, time per stage, choices."""
    r = capture.meta["render"]
    timing = capture.render_timing["timing_s"]
    hh, ww = capture.hr_shape
    typer.echo(f"wrote {output}: {scene}, GT {hh}x{ww}, 4 raw frames {hh // 2}x{ww // 2}, DoFP {hh}x{ww}, "
               f"sensor {capture.meta['sensor']['model']}, seed {seed}")
    noise_text = (f", MC noise ~{r['mc_noise_rms_estimate']:.2g}" if r.get("mc_noise_rms_estimate") is not None
                  else "")
    typer.echo(f"  variant {r['variant']['variant']}, {r['path']}, {r['spp_per_hr_pixel']} spp/HR px{noise_text}, "
               f"parallax residual <= {r['depth']['parallax_residual_max_hr_px']:.3g} HR px")
    stages = ", ".join(f"{k[:-2]} {v:.1f}s" for k, v in timing.items() if k != "total_s")
    typer.echo(f"  time {timing['total_s']:.1f} s in render_capture ({stages}); "
               f"{time.perf_counter() - t0:.1f} s in all")
    for c in capture.render_timing["choices"]:
        saved = c.get("saved_s")
        saved_text = f"saved {saved:+.1f} s ({c['saved_how']})" if saved is not None else ""
        typer.echo(f"  choice {c['choice']}: {c['value']} instead of {c['instead_of']}; {saved_text}")


def scenes(
    name: Optional[str] = typer.Argument(None, help="Show one scene in detail."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON to stdout instead of a table."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """List the scene library (or describe one scene); --threads and --device are checked like every command's."""
    apply_compute(threads, device)
    # the scene library and the renderer pull torch: loaded when the command runs (start-up time)
    from capssim.render import get_scene, list_scenes

    infos = list_scenes()
    if name is not None:
        info = get_scene(name).info
        if as_json:
            typer.echo(json.dumps(asdict(info), indent=2))
            return
        for key, value in asdict(info).items():
            typer.echo(f"{key:<12} {value}")
        typer.echo(f"{'needs':<12} {info.needs()}")
        return
    if as_json:
        typer.echo(json.dumps({k: asdict(v) for k, v in infos.items()}, indent=2))
        return
    width = max(len(k) for k in infos)
    typer.echo(f"{'scene':<{width}}  planar pol. spectral  depth  description")
    for key, info in infos.items():
        flags = f"{'yes' if info.planar else 'no':<6} {'yes' if info.polarizing else 'no':<4} " \
                f"{'yes' if info.spectral else 'no':<8}"
        typer.echo(f"{key:<{width}}  {flags}  {info.depth_m:4.0f} m  {info.description}")
        typer.echo(f"{'':<{width}}  {'':<21}         for: {info.purpose}")


def register(app: typer.Typer) -> None:
    app.command("render")(render)
    app.command("scenes")(scenes)
