"""``capssim gt-check``: how consistent a ground truth's four analyzer images are."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from capssim.errors import InputError
from capssim.imageio import atomic_write_json, read_gt_scene, write_tiff


def gt_check(
    gt: Path = typer.Argument(..., help="Ground truth: folder of 0/45/90/135.png, or a 12-channel TIFF."),
    crop: Optional[int] = typer.Option(None, "--crop", help="Check the centred N x N crop (as simulate --crop)."),
    dolp_max: float = typer.Option(0.1, "--dolp-max", help="Block DoLP below which a pixel is 'weakly polarized'."),
    device: str = typer.Option("cpu", "--device", help="cpu | cuda."),
    as_json: Optional[Path] = typer.Option(None, "-o", "--output", help="Also write the report to this JSON file."),
    write_aligned: Optional[Path] = typer.Option(
        None, "--write-aligned", help="Write a 12-channel float TIFF with the 45/90/135 deg images resampled onto "
                                      "the 0 deg one (usable as simulate --gt)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing --output / --write-aligned files."),
) -> None:
    """Measure the inter-image offsets, Stokes residual and clipping of a ground truth (capssim.eval.gt_check)."""
    # start-up time: the check, the registry and the simulation pull torch
    from capssim.eval.gt_check import MIN_WEAKLY_POLARIZED_SHARE, aligned_ground_truth, check_ground_truth
    from capssim.reconstruct.registry import resolve_device
    from capssim.simulate import prepare_ground_truth

    for name, path in (("-o/--output", as_json), ("--write-aligned", write_aligned)):
        if path is not None and path.exists() and not overwrite:
            raise InputError(name, str(path), "a path that does not exist yet", "Pass --overwrite to replace it.")
    if write_aligned is not None and write_aligned.suffix.lower() not in (".tif", ".tiff"):
        raise InputError("--write-aligned", str(write_aligned), "a .tif or .tiff path")
    dev = resolve_device(device)
    image, source = read_gt_scene(gt)
    if crop is not None:
        image, _ = prepare_ground_truth(image, crop=crop)
    with typer.progressbar(length=1, label="registering the analyzer images") as bar:
        report = check_ground_truth(image, dolp_max=dolp_max, bit_depth=int(source.get("bit_depth", 0)),
                                    device=dev)
        bar.update(1)
    report["gt"] = str(gt)
    report["crop"] = crop
    h, w = report["shape"]
    typer.echo(f"{gt} ({h}x{w}): {report['verdict']}")
    typer.echo(f"{'image':<8} {'dx px':>8} {'dy px':>8} {'rot deg':>9} {'scale ppm':>10} {'mean px':>8}"
               f" {'weak-pol mean px':>17} {'clipped %':>10}")
    weak = report["alignment_weakly_polarized"]
    for j, row in enumerate(report["alignment"]):
        cross = f"{weak[j]['mean_displacement_px']:17.3f}" if weak else f"{'-':>17}"
        typer.echo(f"{report['angles_deg'][j]:>3} deg  {row['shift_x_px']:8.3f} {row['shift_y_px']:8.3f} "
                   f"{row['rotation_deg']:9.4f} {row['scale_ppm']:10.0f} {row['mean_displacement_px']:8.3f}"
                   f"{cross} {100 * report['clipped_share'][j + 1]:10.2f}")
    if weak is None:
        typer.echo(f"weak-pol cross-check skipped: {100 * report['weakly_polarized_share']:.1f} % of the pixels are "
                   f"weakly polarized (block DoLP < --dolp-max), it needs {100 * MIN_WEAKLY_POLARIZED_SHARE:.0f} %")
    st = report["stokes"]
    typer.echo("Stokes residual I0+I90-I45-I135, % of S0 (quantization floor, low-frequency share): "
               + ", ".join(f"{s['colour']} {s['rms_percent_of_s0']:.2f} ({s['quantization_floor_percent']:.2f}, "
                           f"{s['low_frequency_share']:.2f})" for s in st["per_colour"]))
    chk = report["alignment_check"]
    typer.echo(f"alignment check: luminance Stokes residual {chk['stokes_rms_percent_unaligned']:.2f} % of S0 as given, "
               f"{chk['stokes_rms_percent_aligned']:.2f} % after the alignment -> "
               + ("plausible" if chk["reliable"] else "UNRELIABLE (polarization texture misleads the estimate)"))
    g = st["gains"]
    typer.echo(f"best gains g45 {g['g45']:.4f}, g90 {g['g90']:.4f}, g135 {g['g135']:.4f} "
               f"(residual after the fit {st['rms_percent_after_gain_fit']:.2f} % of S0); {report['time_s']:.1f} s")
    if write_aligned is not None:
        if not chk["reliable"]:
            typer.echo("warning: writing an aligned ground truth from an alignment estimate that raises the Stokes "
                       "residual; it is probably worse than the original", err=True)
        write_tiff(write_aligned, aligned_ground_truth(image, report["alignment_matrices"], device=dev))
        typer.echo(f"wrote {write_aligned}")
    if as_json is not None:
        atomic_write_json(as_json, report)
        typer.echo(f"wrote {as_json}")


def register(app: typer.Typer) -> None:
    app.command("gt-check")(gt_check)
