"""The tables, the paired ratios and the plot of ``capssim bench reconstruct``
(:mod:`capssim.eval.benchmarks.reconstruct` runs the timings)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from capssim.files.imageio import atomic_write_bytes

STAGE_ORDER = ("rearrange", "registration", "operator", "cagf", "init", "nlstr_setup", "nlstr_block_matching",
               "nlstr_dictionaries_cores", "data_term", "admm_update")


def paired_ratios(results: list[dict]) -> list[dict]:
    """Add ``per_pixel_vs_reference`` to each run of ``results`` (in place; returned): the median over the rounds
    of ``(wall / pixels) / (reference wall / reference pixels)``, the reference being the first untiled run of the
    same device and method in the list and round ``r`` of one paired with round ``r`` of the other. Where the
    reference also closed each round (``closing_wall_s``), its wall in round ``r`` is the geometric mean of the
    opening and closing runs. ``None`` where there is no untiled reference. Pairing by round cancels the
    machine's drift over a long benchmark; bracketing the round, most of the drift within it."""
    references: dict[tuple, dict] = {}
    for run in results:
        key = (run["device"], run.get("method", "caps"))
        if run.get("tile") is None and key not in references:
            references[key] = run
    for run in results:
        ref = references.get((run["device"], run.get("method", "caps")))
        if ref is None:
            run["per_pixel_vs_reference"], run["reference"] = None, None
            continue
        ref_walls = ref.get("all_wall_s", [ref["wall_s"]])
        if ref.get("closing_wall_s"):
            ref_walls = [math.sqrt(a * b) for a, b in zip(ref_walls, ref["closing_wall_s"])]
        pairs = zip(run.get("all_wall_s", [run["wall_s"]]), ref_walls)
        ratios = [(a / _pixels(run)) / (b / _pixels(ref)) for a, b in pairs]
        run["per_pixel_vs_reference"] = 1.0 if run is ref else float(np.median(ratios))
        run["reference"] = _column_label(ref)
    return results


def _column_label(run: dict, *, with_method: bool = False) -> str:
    """``'WxH'`` of a run, with ``' t<side>'`` for a tiled one (and its method first, ``with_method``)."""
    h, w = _hr_shape(run)
    label = f"{w}x{h}" + (f" t{run['tile']}" if run.get("tile") else "")
    return f"{run.get('method', 'caps')} {label}" if with_method else label


def format_tables(results: list[dict]) -> str:
    """One table per device: rows are stages, columns HR sizes, cells 'seconds (peak MB)'."""
    lines = []
    for dev in dict.fromkeys(r["device"] for r in results):
        rows = [r for r in results if r["device"] == dev]
        names = list(dict.fromkeys(r.get("method", "caps") for r in rows))
        labels = [_column_label(r, with_method=len(names) > 1) for r in rows]
        stages = [s for s in STAGE_ORDER if any(s in r["stages_s"] for r in rows)]
        stages += sorted({s for r in rows for s in r["stages_s"]} - set(stages))
        mem_unit = "peak RSS MB" if dev == "cpu" else "peak allocated MB"
        iterations = ", ".join(f"{n} {next(r['iterations'] for r in rows if r.get('method', 'caps') == n)}"
                               for n in names)
        head = f"{iterations} iterations, device {dev}" + (
            f" ({rows[0]['threads']}{'' if isinstance(rows[0]['threads'], str) else ' threads'})" if dev == "cpu" else "")
        lines.append(head + f"; cells: seconds ({mem_unit}); fastest of {rows[0]['repeats']} run(s)")
        width = 26
        lines.append(f"{'stage':{width}s}" + "".join(f"{label:>22s}" for label in labels))
        for st in stages:
            cells = []
            for r in rows:
                t = r["stages_s"].get(st)
                m = r["stage_peak_mb"].get(st)
                cells.append("-" if t is None else f"{t:8.2f} ({m:6.0f})" if m is not None else f"{t:8.2f}")
            lines.append(f"{st:{width}s}" + "".join(f"{c:>22s}" for c in cells))
        lines.append(f"{'total wall time':{width}s}" + "".join(f"{r['wall_s']:>13.2f} s{'':7s}" for r in rows))
        if rows[0]["repeats"] > 1:
            lines.append(f"{'median wall time':{width}s}" + "".join(
                f"{r.get('median_wall_s', r['wall_s']):>13.2f} s{'':7s}" for r in rows))
        ratios = [r.get("per_pixel_vs_reference") for r in rows]
        if any(v is not None for v in ratios):
            ref = next(r["reference"] for r in rows if r.get("reference"))
            lines.append(f"{'per pixel, x ' + ref:{width}s}" + "".join(
                f"{'-' if v is None else f'{v:.2f}x':>22s}" for v in ratios))
        lines.append(f"{'peak memory (MB)':{width}s}" + "".join(f"{r['peak_mb']:>15.0f}{'':7s}" for r in rows))
        lines.append(f"{'groups / re-matchings':{width}s}"
                     + "".join(f"{str(r['n_groups']) + ' / ' + str(r['rematches']):>22s}" for r in rows))
        lines.append(f"{'load average before/after':{width}s}"
                     + "".join(f"{r['load_before']:>15.2f}/{r['load_after']:<6.2f}" for r in rows))
        lines.append("")
    return "\n".join(lines)


def plot_scaling(results: list[dict], path: Path) -> Path:
    """PNG of wall time and peak memory against the HR pixel count (log-log), one line per device and
    untiled/tiled, with the time per megapixel of each run: the plot of docs/results/full-frames.md."""
    import io

    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(10, 4))
    names = list(dict.fromkeys(r.get("method", "caps") for r in results))
    for key in dict.fromkeys((r["device"], r.get("tile"), r.get("method", "caps")) for r in results):
        rows = sorted((r for r in results if (r["device"], r.get("tile"), r.get("method", "caps")) == key),
                      key=lambda r: _pixels(r))
        mp = [_pixels(r) / 1e6 for r in rows]
        label = (f"{key[2]}, " if len(names) > 1 else "") + f"{key[0]}, " + (
            "untiled" if key[1] is None else f"tiles of {key[1]}")
        ax_t.plot(mp, [r["wall_s"] for r in rows], "o-", label=label)
        ax_m.plot(mp, [r["peak_mb"] / 1024 for r in rows], "o-", label=label)
        for x, r in zip(mp, rows):
            ax_t.annotate(f"{r['wall_s'] / x:.0f} s/MP", (x, r["wall_s"]), fontsize=7, xytext=(4, -10),
                          textcoords="offset points")
    for ax, what in ((ax_t, "wall time (s)"), (ax_m, "peak memory (GB)")):
        ax.set(xscale="log", yscale="log", xlabel="HR pixels (megapixels)", ylabel=what)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    ax_t.set_title(f"{', '.join(names)}, {results[0]['iterations']} iterations: time" if len(names) == 1
                   else f"{', '.join(names)}: time")
    ax_m.set_title("peak memory")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def _hr_shape(run: dict) -> tuple[int, int]:
    """``(height, width)`` of a run (older records carry a square ``hr_size`` only)."""
    h, w = run.get("hr_shape") or (run["hr_size"], run["hr_size"])
    return int(h), int(w)


def _pixels(run: dict) -> int:
    h, w = _hr_shape(run)
    return h * w


__all__ = ["STAGE_ORDER", "format_tables", "paired_ratios", "plot_scaling"]
