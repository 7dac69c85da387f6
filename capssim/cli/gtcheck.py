"""``capssim gt-check``: how consistent a ground truth's four analyzer images are."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from capssim.cli._options import DeviceOption, ThreadsOption, apply_compute, echo_json
from capssim.errors import InputError
from capssim.files.imageio import read_gt_scene, write_tiff


def gt_check(
    gt: Path = typer.Argument(..., help="Ground truth: folder of 0/45/90/135.png, or a 12-channel TIFF."),
    crop: Optional[int] = typer.Option(None, "--crop", help="Check the centred N x N crop (as simulate --crop)."),
    dolp_max: float = typer.Option(0.1, "--dolp-max", help="Block DoLP below which a pixel is 'weakly polarized'."),
    as_json: bool = typer.Option(False, "--json", help="Print the report as JSON to stdout (the record that "
                                                       "capssim bench registration --content-alignment reads)."),
    write_aligned: Optional[Path] = typer.Option(
        None, "--write-aligned", help="Write a 12-channel float TIFF with the 45/90/135 deg images resampled onto "
                                      "the 0 deg one (usable as simulate's GT)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --write-aligned file."),
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Measure the inter-image offsets, Stokes residual and clipping of a ground truth (capssim.eval.gt_check)."""
    # start-up time: the check and the simulation pull torch
    from capssim.eval.gt_check import aligned_ground_truth, check_ground_truth
    from capssim.simulate import prepare_ground_truth

    if write_aligned is not None and write_aligned.suffix.lower() not in (".tif", ".tiff"):
        raise InputError("--write-aligned", str(write_aligned), "a .tif or .tiff path")
    if write_aligned is not None:  # before any work: an existing file, a folder in the way, a link loop
        from capssim.files.output_paths import resolve_output

        write_aligned = resolve_output(write_aligned, kind="file", overwrite=overwrite, argument="--write-aligned")
    dev = apply_compute(threads, device)
    image, source = read_gt_scene(gt)
    if crop is not None:
        image, _ = prepare_ground_truth(image, crop=crop)
    with typer.progressbar(length=1, label="registering the analyzer images", file=sys.stderr) as bar:
        report = check_ground_truth(image, dolp_max=dolp_max, bit_depth=int(source.get("bit_depth", 0)),
                                    device=dev)
        bar.update(1)
    report["gt"] = str(gt)
    report["crop"] = crop
    if as_json:
        echo_json(report)
    else:
        typer.echo(report_text(report, gt))
    if write_aligned is not None:
        if not report["alignment_check"]["reliable"]:
            typer.echo("warning: writing an aligned ground truth from an alignment estimate that raises the Stokes "
                       "residual; it is probably worse than the original", err=True)
        write_tiff(write_aligned, aligned_ground_truth(image, report["alignment_matrices"], device=dev))
        typer.echo(f"wrote {write_aligned}", err=as_json)  # stdout stays pure JSON with --json


def report_text(report: dict, gt: Path) -> str:
    """The lines ``capssim gt-check`` prints of a :func:`~capssim.eval.gt_check.check_ground_truth` report."""
    from capssim.eval.gt_check import MIN_WEAKLY_POLARIZED_SHARE

    h, w = report["shape"]
    lines = [f"{gt} ({h}x{w}): {report['verdict']}",
             f"{'image':<8} {'dx px':>8} {'dy px':>8} {'rot deg':>9} {'scale ppm':>10} {'mean px':>8}"
             f" {'weak-pol mean px':>17} {'clipped %':>10}"]
    weak = report["alignment_weakly_polarized"]
    for j, row in enumerate(report["alignment"]):
        cross = f"{weak[j]['mean_displacement_px']:17.3f}" if weak else f"{'-':>17}"
        lines.append(f"{report['angles_deg'][j]:>3} deg  {row['shift_x_px']:8.3f} {row['shift_y_px']:8.3f} "
                     f"{row['rotation_deg']:9.4f} {row['scale_ppm']:10.0f} {row['mean_displacement_px']:8.3f}"
                     f"{cross} {100 * report['clipped_share'][j + 1]:10.2f}")
    if weak is None:
        lines.append(f"weak-pol cross-check skipped: {100 * report['weakly_polarized_share']:.1f} % of the pixels are "
                     f"weakly polarized (block DoLP < --dolp-max), it needs {100 * MIN_WEAKLY_POLARIZED_SHARE:.0f} %")
    st = report["stokes"]
    lines.append("Stokes residual I0+I90-I45-I135, % of S0 (quantization floor, low-frequency share): "
                 + ", ".join(f"{s['colour']} {s['rms_percent_of_s0']:.2f} ({s['quantization_floor_percent']:.2f}, "
                             f"{s['low_frequency_share']:.2f})" for s in st["per_colour"]))
    chk = report["alignment_check"]
    lines.append(f"alignment check: luminance Stokes residual {chk['stokes_rms_percent_unaligned']:.2f} % of S0 as "
                 f"given, {chk['stokes_rms_percent_aligned']:.2f} % after the alignment -> "
                 + ("plausible" if chk["reliable"] else "UNRELIABLE (polarization texture misleads the estimate)"))
    g = st["gains"]
    lines.append(f"best gains g45 {g['g45']:.4f}, g90 {g['g90']:.4f}, g135 {g['g135']:.4f} "
                 f"(residual after the fit {st['rms_percent_after_gain_fit']:.2f} % of S0); {report['time_s']:.1f} s")
    return "\n".join(lines)


def register(app: typer.Typer) -> None:
    app.command("gt-check")(gt_check)
