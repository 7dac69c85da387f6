"""``capssim simulate`` and ``capssim design``."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from capssim.camera.design import DesignInputs, system_design
from capssim.cli._options import (
    DeviceOption,
    OverwriteOption,
    SeedOption,
    ThreadsOption,
    apply_compute,
)
from capssim.cli._setup_options import SetupOptions, check_rig_psfs, rig_homographies, with_setup_options
from capssim.files.imageio import check_output_free, read_gt_scene


@with_setup_options
def simulate(
    gt: Path = typer.Argument(..., help="Ground truth: folder of 0/45/90/135.png, or a 12-channel TIFF."),
    output: Path = typer.Option(..., "-o", "--output", help="Capture folder to create."),
    crop: Optional[int] = typer.Option(None, "--crop", help="Centred N x N crop of the ground truth (multiple of 4)."),
    seed: int = SeedOption,
    shift_max: float = typer.Option(2.0, "--shift-max", help="Max random aperture offset, HR pixels."),
    rotation_max: float = typer.Option(0.5, "--rotation-max", help="Max random aperture rotation, degrees."),
    scale_max: float = typer.Option(0.005, "--scale-max", help="Max random relative scale error."),
    setup_options: SetupOptions = SetupOptions(),
    overwrite: bool = OverwriteOption,
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Simulate CAPS and DoFP captures from a ground-truth scene (paper section 5.2), through an ideal or imperfect array.

    The simulation computes on the CPU; --device is checked like every command's.
    """
    apply_compute(threads, device)
    rig_model, rig_geometry = setup_options.rig_model()
    # these pull torch and the operators: loaded when the command runs (start-up time)
    from capssim.captures.capture import write_capture
    from capssim.simulate import PoseRanges, prepare_ground_truth, simulate_capture

    t0 = time.perf_counter()
    check_output_free(output, overwrite=overwrite)
    image, source = read_gt_scene(gt)
    image, crop_info = prepare_ground_truth(image, crop=crop)
    source.update(crop_info)
    setup = setup_options.camera_setup(rig_model)
    check_rig_psfs(rig_model, image.shape[1:], aperture_psf_sigmas=setup_options.aperture_psf_sigmas)
    homographies = rig_homographies(rig_geometry, image.shape[1:], fix="--crop the ground truth to it")
    capture = simulate_capture(
        image, setup, seed=seed, pose_ranges=PoseRanges(shift_max, rotation_max, scale_max), source=source,
        aperture_homographies=homographies)
    write_capture(output, capture, overwrite=overwrite)
    hh, ww = capture.hr_shape
    typer.echo(f"wrote {output}: GT {hh}x{ww}, 4 raw frames {hh // 2}x{ww // 2}, DoFP {hh}x{ww}, "
               f"sensor {capture.meta['sensor']['model']}, seed {seed} ({time.perf_counter() - t0:.2f} s)")


def design(
    focal_length_mm: float = typer.Option(35.0, "--focal-length-mm"),
    f_number: float = typer.Option(1.65, "--f-number"),
    pixel_um: float = typer.Option(4.8, "--pixel-um"),
    wavelength_nm: float = typer.Option(550.0, "--wavelength-nm"),
    apertures: int = typer.Option(4, "--apertures"),
    baseline_mm: float = typer.Option(40.0, "--baseline-mm"),
    depth_m: float = typer.Option(10.0, "--depth-m"),
    width_px: int = typer.Option(1280, "--width-px"),
    height_px: int = typer.Option(1024, "--height-px"),
    as_json: bool = typer.Option(False, "--json", help="Print the numbers as JSON to stdout instead of a table."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Print the system-design quantities of the paper (eq. 5-8). Defaults: the paper's prototype.

    Closed-form arithmetic on the CPU; --threads and --device are checked like every command's.
    """
    apply_compute(threads, device)
    d = system_design(DesignInputs(focal_length_mm, f_number, pixel_um, wavelength_nm, apertures, baseline_mm,
                                   depth_m, width_px, height_px))
    rows = [
        ("aperture diameter A", f"{d['aperture_diameter_mm']:.3f} mm"),
        ("f_diffraction / f_Nyquist", f"{d['diffraction_to_nyquist_ratio']:.2f}"),
        ("sqrt(apertures)", f"{d['sqrt_apertures']:.3f}"),
        ("r_SR (eq. 5)", f"{d['r_sr']:.3f} (limited by {d['sr_limited_by']})"),
        ("pixel focal length f_P", f"{d['pixel_focal_length_px']:.1f} px"),
        ("overlap width R_x (eq. 6)", f"{d['overlap_width_m']:.4f} m at Z = {depth_m} m"),
        ("overlap height R_y", f"{d['overlap_height_m']:.4f} m"),
        ("effective FOV_h (eq. 7)", f"{d['fov_h_deg']:.3f} deg"),
        ("effective FOV_v (eq. 8)", f"{d['fov_v_deg']:.3f} deg"),
        ("single-aperture FOV_h", f"{d['single_aperture_fov_h_deg']:.3f} deg"),
        ("equivalent focal length sqrt(N) f", f"{d['equivalent_focal_length_mm']:.1f} mm"),
    ]
    if as_json:
        typer.echo(json.dumps(d, indent=2, allow_nan=False))
        return
    width = max(len(r[0]) for r in rows)
    for name, value in rows:
        typer.echo(f"{name:<{width}}  {value}")


def register(app: typer.Typer) -> None:
    app.command("simulate")(simulate)
    app.command("design")(design)
