"""``capssim evaluate`` and ``capssim mtf``: scoring from the command line (benchmarks: ``capssim bench``)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from capssim.cli._options import DeviceOption, JsonOption, ThreadsOption, apply_compute, number_in
from capssim.conventions import CHANNEL_NAMES
from capssim.errors import InputError
from capssim.files.imageio import read_image
from capssim.runtime.resources import MEMORY_LIMIT_ENV, check_image_memory

#: peak bytes per stored value of a capture's largest image while ``capssim evaluate`` scores it (the ground
#: truth, one estimate, the metric and MTF working arrays; measured about 50)
EVALUATE_BYTES_PER_VALUE = 80
#: peak bytes per stored value of the image ``capssim mtf`` measures (the float64 copy and the star fit;
#: measured about 18)
MTF_BYTES_PER_VALUE = 32


def check_capture_memory(capture: Path, methods: Optional[List[str]]) -> None:
    """Refuse a capture whose images (``*.tiff``, ``recon/*.tiff`` of ``methods`` and their error bars), read
    from their headers, would pass the memory limit while scored, before any is decoded."""
    from capssim.captures.capture import COMPANION_SUFFIXES

    capture = Path(capture)
    recon = sorted((capture / "recon").glob("*.tiff")) if (capture / "recon").is_dir() else []
    stems = None if not methods else {m + suffix for m in methods for suffix in ("", *COMPANION_SUFFIXES.values())}
    files = sorted(capture.glob("*.tiff")) + [f for f in recon if stems is None or f.stem in stems]
    for path in files:
        check_image_memory("CAPTURE", path, EVALUATE_BYTES_PER_VALUE, what="scoring",
                           fix=f"Score a crop of the capture, or raise {MEMORY_LIMIT_ENV} if the machine has the memory.")


def format_value(value, digits: int = 2) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:.{digits}f}"
    return str(value)


def format_table(headers: list[str], rows: list[list], *, align_first_left: bool = True) -> str:
    """Plain aligned text table (readable in CI logs and pipes)."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = []
    for j, r in enumerate(cells):
        parts = [(r[i].ljust(widths[i]) if (i == 0 and align_first_left) else r[i].rjust(widths[i]))
                 for i in range(len(r))]
        lines.append("  ".join(parts))
        if j == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


# -- evaluate ------------------------------------------------------------------------------------
def evaluate(
    capture: Path = typer.Argument(..., help="Capture folder with gt.tiff and recon/*.tiff."),
    convention: str = typer.Option("capssim", "--convention",
                                   help="Metric definitions: capssim | tokyotech | qiu (docs: guides/scoring.md, 'Metrics')."),
    methods: Optional[List[str]] = typer.Option(None, "--method", "-m", metavar="METHOD",
                                                help="Reconstruction to score (repeatable; default: all)."),
    min_s0: Optional[float] = typer.Option(None, "--min-s0", help="AoP mask / DoLP guard: GT S0 above this (S0 in [0,2])."),
    min_dolp: Optional[float] = typer.Option(None, "--min-dolp", help="AoP mask: GT DoLP above this."),
    border: Optional[int] = typer.Option(None, "--border", help="Border crop in pixels (default: the convention's).",
                                         callback=number_in("--border", 0, what="pixels", fix="Try --border 0.")),
    lpips_weights: Optional[Path] = typer.Option(None, "--lpips-weights",
                                                 help="Local LPIPS-Alex weights (file or folder); never downloaded."),
    no_mtf: bool = typer.Option(False, "--no-mtf", help="Skip the Siemens-star MTF of star scenes."),
    plots: Optional[Path] = typer.Option(None, "--plots", metavar="DIR",
                                         help="Also draw the error-bar plots (PNG) of each reconstruction with "
                                              "uncertainty files (reconstruct --uncertainty) into this folder."),
    as_json: bool = JsonOption,
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """Score every reconstruction of a capture against its ground truth; write CAPTURE/metrics.json.

    A reconstruction with error bars (recon/METHOD.std.tiff and companions) also gets the coverage of its
    90 % intervals and its AUSE. The metrics compute on the CPU; --device is the LPIPS network's.
    """
    dev = apply_compute(threads, device)
    # start-up time: the scoring pulls torch and skimage
    from capssim.eval.evaluate import evaluate_capture
    from capssim.eval.metric_records import json_safe
    from capssim.eval.metrics import check_thresholds

    check_thresholds(min_s0=min_s0, min_dolp=min_dolp)
    check_capture_memory(capture, methods)
    from capssim.files.output_paths import check_files_in, resolve_output

    check_files_in(capture, ["metrics.json"], argument="CAPTURE")  # before scoring: a folder in the way refused
    if plots is not None:
        plots = resolve_output(plots, kind="folder", overwrite=True, argument="--plots")
    lpips = None
    if lpips_weights is not None:
        from capssim.eval.lpips import LPIPS

        lpips = LPIPS.from_path(lpips_weights, device=dev)
    result = evaluate_capture(capture, convention=convention, methods=methods or None, min_s0=min_s0, min_dolp=min_dolp,
                              border=border, lpips=lpips, with_mtf=not no_mtf, plot_dir=plots)
    if as_json:
        typer.echo(json.dumps(json_safe(result), indent=2, allow_nan=False))
    else:
        typer.echo(render_evaluation(result, lpips_used=lpips is not None))
        typer.echo(f"wrote {Path(capture) / 'metrics.json'}")
        for line in plot_lines(result, plots):
            typer.echo(line)
    if any("error" in e or "error" in e.get("uncertainty", {}) for e in result["methods"].values()):
        raise typer.Exit(1)


def uncertainty_lines(result: dict) -> list[str]:
    """One line per method with error bars: coverage of its 90 % intervals per group and its 12-channel AUSE."""
    lines = []
    for name, entry in result["methods"].items():
        block = entry.get("uncertainty")
        if not block:
            continue
        if "error" in block:
            lines.append(f"{name}: error bars not scored: {block['error']}")
            continue
        groups = block["groups"]
        cover = ", ".join(f"{g} {format_value(v['coverage'])}" for g, v in groups.items())
        calibration = f" (calibration {block['calibration']})" if block.get("calibration") else ""
        lines.append(f"{name}: {100 * block['nominal_coverage']:.0f} % intervals cover {cover}; "
                     f"AUSE 12ch {format_value(groups['12ch']['ause'])}{calibration}")
        lines += [f"{name}: note: {note}" for note in block.get("notes", [])]
    if lines:
        lines = ["", "error bars: fraction of ground-truth values inside the 90 % intervals (12 channels pooled; "
                     "S0, DoLP, AoP pooled over R, G, B; the metrics' crop and masks);",
                 "AUSE: area between the sparsification curve and its oracle's (0 = the std ranks the errors "
                 "perfectly)."] + lines
    return lines


def plot_lines(result: dict, plot_dir: Optional[Path]) -> list[str]:
    """What ``--plots`` wrote (or why not) for each method with error bars; ``[]`` without ``--plots``."""
    if plot_dir is None:
        return []
    blocks = {name: entry["uncertainty"] for name, entry in result["methods"].items()
              if "uncertainty" in entry and "error" not in entry["uncertainty"]}
    if not blocks:
        return [f"--plots: no reconstruction has error bars (recon/METHOD.std.tiff): nothing drawn in {plot_dir}"]
    lines = []
    for name, block in blocks.items():
        lines += [f"wrote {p}" for p in block.get("plots", [])]
        if "plots_error" in block:
            lines.append(f"{name}: plots failed: {block['plots_error']}")
    return lines


def render_evaluation(result: dict, *, lpips_used: bool) -> str:
    """The tables ``capssim evaluate`` prints of an :func:`~capssim.eval.evaluate.evaluate_capture` result."""
    fv = format_value
    out = [f"capture: {result['capture']}",
           f"convention: {result['convention']} ({result['convention_description']})"]
    rows, ch_psnr, ch_ssim = [], [], []
    for name, e in result["methods"].items():
        if "error" in e:
            rows.append([name, f"ERROR: {e['error']}"] + [""] * 12)
            continue
        m = e["metrics"]
        rows.append([name, fv(m["psnr_mean"]), fv(m.get("psnr_gt_peak_mean")), fv(m["ssim_mean"], 4),
                     fv(m.get("ssim_gt_peak_mean"), 4), fv(m["s0_psnr"]), fv(m["s1_psnr"]),
                     fv(m["s2_psnr"]), fv(m["dolp_psnr"]), fv(m["dolp_ssim"], 4), fv(m["aop_rmse_deg"]),
                     fv(m["aop_mae_deg"]), fv(m.get("lpips_mean"), 4), fv(e.get("wall_time_s"), 2)])
        ch_psnr.append([name] + [fv(m["psnr"][c]) for c in CHANNEL_NAMES] + [fv(m["psnr_mean"])])
        ch_ssim.append([name] + [fv(m["ssim"][c], 3) for c in CHANNEL_NAMES] + [fv(m["ssim_mean"], 3)])
    out.append("")
    out.append(format_table(["method", "PSNR", "PSNR-GTpk", "SSIM", "SSIM-GTpk", "S0", "S1", "S2", "DoLP",
                             "DoLP-SSIM", "AoP-RMSE", "AoP-MAE", "LPIPS", "time-s"], rows))
    if ch_psnr:
        out += ["", "PSNR per channel (dB, data range 1):",
                format_table(["method", *CHANNEL_NAMES, "mean"], ch_psnr), "",
                "SSIM per channel (data range 1, Gaussian window sigma 1.5):",
                format_table(["method", *CHANNEL_NAMES, "mean"], ch_ssim)]
    s = result.get("settings")
    if s:
        out += ["", f"units: PSNR dB; AoP degrees (wrap-aware, per colour, pooled); border crop {s['border']} px; "
                    f"DoLP per colour, clipped to [0, 1], 0 where S0 <= {s['min_s0']}.",
                f"AoP mask: ground-truth S0 > {s['min_s0']} and DoLP > {s['min_dolp']} "
                f"(None = no mask); S0 = (I0+I45+I90+I135)/2 on [0, 2]."]
        if s.get("gt_peak") is not None:
            out.append(f"PSNR, SSIM: data range 1 (full scale); PSNR-GTpk, SSIM-GTpk: data range = the ground truth's "
                       f"peak {s['gt_peak']:.3g} (the scene exposed to full scale; they rank methods on dark scenes).")
        fractions = {n: e["metrics"]["aop_fraction"] for n, e in result["methods"].items() if "metrics" in e}
        if fractions:
            out.append(f"AoP scored on {100 * next(iter(fractions.values())):.1f}% of colour-pixels.")
        notes = {note for e in result["methods"].values() if "metrics" in e for note in e["metrics"]["notes"]}
        out += [f"note: {n}" for n in sorted(notes)]
    if not lpips_used:
        out.append("LPIPS: skipped (no --lpips-weights given; capssim never downloads network weights).")
    if "gt_mtf" in result:
        star = result["star"]
        rows = []
        g = result["gt_mtf"]["mean"]
        rows.append(["(ground truth)", fv(g["limit_cyc_per_ref_px"]["hv"], 3), fv(g["magnification"]["hv"], 3),
                     fv(g["limit_cyc_per_ref_px"]["diagonal"], 3), fv(g["magnification"]["diagonal"], 3),
                     g["limited_by"]["hv"]])
        for name, e in result["methods"].items():
            mt = e.get("mtf")
            if not mt:
                continue
            if "error" in mt:
                rows.append([name, f"ERROR: {mt['error']}", "", "", "", ""])
                continue
            mm = mt["mean"]
            rows.append([name, fv(mm["limit_cyc_per_ref_px"]["hv"], 3), fv(mm["magnification"]["hv"], 3),
                         fv(mm["limit_cyc_per_ref_px"]["diagonal"], 3), fv(mm["magnification"]["diagonal"], 3),
                         mm["limited_by"]["hv"]])
        out += ["", f"Siemens star ({star['cycles']} cycles): limit resolution in cycles per Bayer sub-image pixel "
                    f"(4 HR px), channel-mean MTF = 0.03; SR magnification = limit / 0.5",
                format_table(["method", "limit-hv", "mag-hv", "limit-diag", "mag-diag", "limited-by"], rows)]
    if "mtf_error" in result:
        out.append(f"MTF not measured: {result['mtf_error']}")
    return "\n".join(out + uncertainty_lines(result))


# -- mtf -----------------------------------------------------------------------------------------
def _read_star_image(path: Path):
    """``(C, H, W)`` float64 and channel names from a grey, RGB or 12-channel image."""
    arr, bits = read_image(path, argument="image")
    arr = arr.astype(np.float64) / (2 ** bits - 1) if bits else arr.astype(np.float64)
    if arr.ndim == 2:
        return arr[None], ["grey"]
    if arr.ndim == 3 and arr.shape[0] == 12:
        return arr, list(CHANNEL_NAMES)
    if arr.ndim == 3 and arr.shape[2] == 12:
        return np.moveaxis(arr, 2, 0), list(CHANNEL_NAMES)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        return np.moveaxis(arr[..., :3], 2, 0), ["R", "G", "B"]
    if arr.ndim == 3 and arr.shape[0] == 3:
        return arr, ["R", "G", "B"]
    raise InputError("image", f"{path} with shape {arr.shape}", "a grey, RGB or 12-channel image")


def _parse_center(center: Optional[str]):
    """``--center ROW,COL`` (one point, two components) as ``(row, col)`` pixels, or ``None``."""
    if not center:
        return None
    try:
        centre = tuple(float(v) for v in center.split(","))
    except ValueError:
        centre = ()
    if len(centre) != 2:
        raise InputError("--center", center, "ROW,COL in pixels, e.g. 255.5,255.5")
    return centre


def _pick_channels(imgs, names: list[str], channels: Optional[List[str]]):
    """The ``--channel`` picks (names or indices, repeatable) of ``imgs``; all without any."""
    if not channels:
        return imgs, names
    picked = []
    for token in (t.strip() for t in channels if t.strip()):
        if token in names:
            picked.append(names.index(token))
        elif token.isdigit() and int(token) < len(names):
            picked.append(int(token))
        else:
            raise InputError("--channel", token, f"one of {', '.join(names)} or an index < {len(names)}",
                             "Repeat --channel for several, e.g. --channel G --channel B.")
    return imgs[picked], [names[i] for i in picked]


def mtf_text(res: dict, names: list[str], *, image: Path, cycles: int, given_centre: bool, pitch: float,
             default_pitch: bool, threshold: float, residual_limit: float) -> str:
    """The tables ``capssim mtf`` prints of a :func:`~capssim.eval.mtf.measure_star` result."""
    head = res["mean"] if "mean" in res else res[names[0]]
    lines = [f"image: {image} ({len(names)} channel{'s' if len(names) > 1 else ''}: {', '.join(names)})",
             f"star: {cycles} cycles, centre row {head.center_rowcol[0]:.2f} col {head.center_rowcol[1]:.2f}"
             f"{' (given)' if given_centre else ' (found)'}, radius {head.radius_px:.1f} px",
             f"reference pitch: {pitch:g} px of this image"
             + (" (default for a 12-channel capssim image: one Bayer sub-image pixel = 4 HR px)"
                if default_pitch and pitch == 4.0 else ""),
             f"frequencies: cycles/px of this image (f) and cycles per reference pixel (f_ref = f x {pitch:g})", ""]
    label = "channel mean" if "mean" in res else names[0]
    rows = []
    for i, f in enumerate(head.frequency):
        flags = "".join("*" if not head.credited[g][i] else " " for g in ("hv", "diagonal"))
        rows.append([f"{f:.4f}", f"{f * pitch:.3f}", format_value(float(head.mtf["hv"][i]), 3),
                     format_value(float(head.mtf["diagonal"][i]), 3), format_value(float(head.residual_ratio["hv"][i]), 3),
                     format_value(float(head.residual_ratio["diagonal"][i]), 3), flags])
    lines.append(f"MTF per segment direction ({label}); hv = segments centred on 0/90/180/270 deg, "
                 f"diagonal = 45/135/225/315 deg; '*' = not credited (beyond a stop):")
    lines.append(format_table(["f", "f_ref", "MTF-hv", "MTF-diag", "resid-hv", "resid-diag", "hv/diag"], rows))
    lines.append("")
    summary = []
    for name, r in res.items():
        summary.append([name, f"{r.limit['hv']:.4f}", f"{r.limit['hv'] * pitch:.3f}", f"{r.magnification('hv'):.3f}",
                        r.limited_by["hv"], f"{r.limit['diagonal']:.4f}", f"{r.limit['diagonal'] * pitch:.3f}",
                        f"{r.magnification('diagonal'):.3f}", r.limited_by["diagonal"]])
    lines.append(f"limit resolution (MTF = {threshold}) and SR magnification = limit (cycles/reference px) / 0.5:")
    lines.append(format_table(["channel", "limit-hv", "ref-hv", "mag-hv", "by", "limit-diag", "ref-diag", "mag-diag",
                               "by"], summary))
    lines.append(f"reference modulation: {head.reference_source}; the measurement never credits frequencies above "
                 "0.5 cycles/px of this grid and stops where the fit residual reaches "
                 f"{residual_limit} x the sinusoid (aliasing or noise).")
    return "\n".join(lines)


def mtf(
    image: Path = typer.Argument(..., help="Star image: PNG/TIFF, grey, RGB or 12-channel (capssim output)."),
    cycles: int = typer.Option(..., "--cycles", help="Sinusoidal periods of the star per turn."),
    center: Optional[str] = typer.Option(None, "--center", help="Star centre ROW,COL in pixels (default: found)."),
    radius: Optional[float] = typer.Option(None, "--radius", help="Star radius in pixels (default: found).",
                                           callback=number_in("--radius", 0.0, low_open=True, what="pixels")),
    reference_pitch: Optional[float] = typer.Option(
        None, "--reference-pitch",
        help="Pixels of this image per reference pixel for the magnification (default 1; 4 for a 12-channel image).",
        callback=number_in("--reference-pitch", 0.0, low_open=True, what="pixels per reference pixel")),
    channel: Optional[List[str]] = typer.Option(None, "--channel", metavar="NAME",
                                                help="Channel name or index (repeatable; default: all)."),
    modulation: Optional[float] = typer.Option(None, "--modulation",
                                               help="The target's true modulation (default: extrapolated to f=0).",
                                               callback=number_in("--modulation", 0.0, 1.0, low_open=True)),
    threshold: float = typer.Option(0.03, "--threshold", help="MTF at the limit resolution (paper: 0.03).",
                                    callback=number_in("--threshold", 0.0, 1.0, low_open=True, high_open=True)),
    residual_limit: float = typer.Option(0.5, "--residual-limit",
                                         help="Stop where residual RMS / sinusoid RMS reaches this.",
                                         callback=number_in("--residual-limit", 0.0, low_open=True)),
    as_json: bool = JsonOption,
    threads: Optional[int] = ThreadsOption,
    device: str = DeviceOption,
) -> None:
    """MTF of a sinusoidal Siemens star per segment direction, limit resolution and SR magnification.

    The measurement computes on the CPU (numpy); --device is checked like every command's.
    """
    from capssim.eval.metric_records import json_safe  # start-up time
    from capssim.eval.mtf import measure_star

    apply_compute(threads, device)
    check_image_memory("IMAGE", image, MTF_BYTES_PER_VALUE, what="the MTF measurement",
                       fix=f"Crop the star image, or raise {MEMORY_LIMIT_ENV} if the machine has the memory.")
    imgs, names = _read_star_image(image)
    is_twelve = len(names) == 12
    centre = _parse_center(center)
    imgs, names = _pick_channels(imgs, names, channel)
    pitch = reference_pitch if reference_pitch is not None else (4.0 if is_twelve else 1.0)
    res = measure_star(imgs, cycles, names=names, center_rowcol=centre, radius=radius, reference_modulation=modulation,
                       reference_pitch=pitch, threshold=threshold, residual_limit=residual_limit).results
    if as_json:
        typer.echo(json.dumps(json_safe({"image": str(image), "channels": {k: v.to_dict() for k, v in res.items()}}),
                              indent=2, allow_nan=False))
        return
    typer.echo(mtf_text(res, names, image=image, cycles=cycles, given_centre=centre is not None, pitch=pitch,
                        default_pitch=reference_pitch is None, threshold=threshold, residual_limit=residual_limit))


def register(app: typer.Typer) -> None:
    app.command("evaluate")(evaluate)
    app.command("mtf")(mtf)
