"""``DIR/report.md`` and ``DIR/*.png`` of a design map, from ``DIR/map.jsonl``.

Per metric (:data:`~.margins.METRICS`): a table of every cell's margin (best array method minus best DoFP method,
positive = the array wins; mean and standard error over the seeds; the verdict, :mod:`.margins`), and a picture
(:mod:`.plots`): a heatmap per pair of the first two axes (one per combination of the other axes' values), or
curves for a one-axis map. With a pose axis the theory goes beside it (the resolved fraction of the stacked
sampling, :mod:`.theory`), with a registration-error axis the error the project's registration reaches on the
scene; the paper's design numbers (eq. 5-8, :func:`~.theory.design_numbers`) head the report.
"""

from __future__ import annotations

import itertools
from pathlib import Path

from capssim.files.imageio import atomic_write_text

from ..benchmarks.results import read_results
from .cells import cell_label
from .margins import METRICS, cell_field, margins, method_curves
from .plots import axis_curves, margin_heatmap
from .spec import POSE_AXES
from .theory import design_numbers


def _fmt(value, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}g}"


def _theory(records: list[dict], axes: list[str], axis: str) -> dict | None:
    """``{axis, values, fractions}``: the resolved fraction along a pose ``axis`` (mean over the other axes)."""
    if axis not in POSE_AXES:
        return None
    by_cell = cell_field(records, "theory", "resolved_fraction", axes)
    i = axes.index(axis)
    sums: dict = {}
    for cell, value in by_cell.items():
        sums.setdefault(cell[i], []).append(value)
    values = sorted(sums)
    return {"axis": axis, "values": values, "fractions": [sum(sums[v]) / len(sums[v]) for v in values]} if values \
        else None


def _reached(records: list[dict]) -> float | None:
    values = [r["registration_reached_hr_px"] for r in records if r.get("registration_reached_hr_px") is not None]
    return sum(values) / len(values) if values else None


def _pictures(records: list[dict], spec: dict, metric: str, out: Path) -> list[str]:
    """The pictures of one metric (module docstring); returns their file names."""
    axes = list(spec["axes"])
    label = METRICS[metric][0]
    table = margins(records, metric, axes)
    reached = _reached(records)
    names = []
    if len(axes) == 1:
        axis = axes[0]
        curves = {m: {c[0]: v for c, v in cells.items()} for m, cells in method_curves(records, metric, axes).items()}
        name = f"{metric}.png"
        axis_curves(out / name, axis=axis, values=spec["axes"][axis], curves=curves,
                    margin={c[0]: v for c, v in table.items()}, metric_label=label, title=f"{spec['name']}: {label}",
                    theory=_theory(records, axes, axis),
                    reached=reached if axis == "registration_error_px" else None)
        return [name]
    rest = axes[2:]
    for combo in itertools.product(*(spec["axes"][a] for a in rest)):
        grid = {c[:2]: v for c, v in table.items() if tuple(c[2:]) == combo}
        suffix = "".join(f"_{a}={v:g}" if isinstance(v, float) else f"_{a}={v}" for a, v in zip(rest, combo))
        name = f"{metric}{suffix}.png"
        theory = _theory(records, axes, axes[1]) or _theory(records, axes, axes[0])
        where = {a: reached for a in axes[:2] if a == "registration_error_px" and reached is not None}
        margin_heatmap(out / name, grid=grid, axes=(axes[0], axes[1]), values=(spec["axes"][axes[0]],
                       spec["axes"][axes[1]]), metric_label=label, theory=theory, reached=where,
                       title=f"{spec['name']}: {label}{suffix.replace('_', ' ')}")
        names.append(name)
    return names


def _metric_section(records: list[dict], spec: dict, metric: str, names: list[str]) -> list[str]:
    axes = list(spec["axes"])
    table = margins(records, metric, axes)
    if not table:
        return []
    theory = cell_field(records, "theory", "resolved_fraction", axes)
    lines = [f"## {METRICS[metric][0]}", ""] + [f"![{metric}]({n})" for n in names] + [""]
    head = axes + ["best array", "best DoFP", "margin", "SE", "verdict"] + (["resolved fraction"] if theory else [])
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cell in sorted(table, key=lambda c: tuple(spec["axes"][a].index(v) for a, v in zip(axes, c))):
        m = table[cell]
        row = [f"{v:g}" if isinstance(v, float) else str(v) for v in cell]
        row += [f"{m['best_array']} {_fmt(m['best_array_mean'], 4)}", f"{m['best_dofp']} {_fmt(m['best_dofp_mean'], 4)}",
                f"{m['margin']:+.3g}", _fmt(m["se"], 2), m["verdict"]]
        if theory:
            row.append(_fmt(theory.get(cell), 3))
        lines.append("| " + " | ".join(row) + " |")
    wins = {v: sum(m["verdict"] == v for m in table.values()) for v in ("array", "dofp", "undecided")}
    lines += ["", f"The array wins {wins['array']} of {len(table)} cells, the DoFP sensor {wins['dofp']}, "
                  f"{wins['undecided']} undecided.", ""]
    return lines


def _head(spec: dict, records: list[dict], command: str | None) -> list[str]:
    design = design_numbers()
    failed = [r for r in records if r.get("status") != "ok"]
    methods = ", ".join(f"{m['label']} ({r})" for m in spec["methods"]
                        for r in [next((x.get("kind") for x in records if x.get("method") == m["label"]), "?")])
    lines = [f"# Design map: {spec['name']}", "", spec.get("description", "").strip(), "",
             f"- scene: `{spec['scene']}`", "- axes: " + "; ".join(f"`{a}` {v}" for a, v in spec["axes"].items()),
             f"- fixed: {spec.get('fixed') or 'nothing (the simulate defaults)'}", f"- seeds: {spec['seeds']}",
             f"- methods (kind): {methods}",
             f"- cases: {len(records)} ({len(failed)} not ok)",
             "- margin: best array method - best DoFP method, seed by seed (for AoP error and time: DoFP - array), "
             "so positive = the array wins; SE over the seeds; `undecided` = |margin| <= 1 SE.",
             f"- theory, eq. 5 at the paper's prototype (f/{1.65}, 4.8 um pixels, 550 nm): r_SR = "
             f"{design['r_sr']:.3g} ({design['sr_limited_by']}-limited). The resolved fraction is the share of "
             "singular values above 0.1 s_max of the four apertures' stacked sampling at the cell's poses "
             "(0.25 = no more than one aperture; eval/maps/theory.py)."]
    reached = _reached(records)
    if reached is not None:
        lines.append(f"- the project's registration (local-correlation) reaches a median {reached:.3g} HR px on these "
                     "captures (dashed line).")
    parallax = {cell_label(r["axes"]): r["parallax_p95_hr_px"] for r in records if "parallax_p95_hr_px" in r}
    if parallax:
        lines.append("- the render's parallax that the apertures' homographies miss (95th percentile over the view, "
                     "worst aperture, HR px): " + "; ".join(f"{k}: {v:.2g}" for k, v in parallax.items()) + ".")
    if "depth_m" in spec["axes"] and "baseline_m" not in spec["axes"]:
        parts = [f"{d:g} m: overlap {design_numbers(depth_m=d)['overlap_width_m']:.3g} m" for d in spec["axes"]["depth_m"]]
        lines.append("- eq. 6 at the prototype's 40 mm baseline: " + "; ".join(parts) + ".")
    if command:
        lines += ["", "Regenerate:", "", "```", command, "```"]
    return lines + [""]


def write_map_report(output: str | Path, spec: dict, *, command: str | None = None, plots: bool = True) -> Path:
    """Write ``output/report.md`` (and the pictures, unless ``plots`` is false) from ``output/map.jsonl``;
    returns the report's path."""
    out = Path(output)
    wanted = {m["label"] for m in spec["methods"]}
    records = [r for r in read_results(out / "map.jsonl").values() if r.get("method") in wanted and "axes" in r
               and tuple(r["axes"]) == tuple(spec["axes"])]
    lines = _head(spec, records, command)
    for metric in METRICS:
        names = _pictures(records, spec, metric, out) if plots and margins(records, metric, list(spec["axes"])) else []
        lines += _metric_section(records, spec, metric, names)
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path
