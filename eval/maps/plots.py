"""The pictures of a design map (matplotlib, Agg): margin heatmaps and one-axis curves, the theory beside them.

* :func:`margin_heatmap`: two axes, the margin (:mod:`.margins`: best array method minus best DoFP method,
  positive = the array wins) per cell on a diverging scale centred on 0, the zero contour drawn, each cell
  marked ``A`` (array), ``D`` (DoFP) or ``?`` (undecided: within one standard error over the seeds) with its
  margin; beside it, when one axis sets the poses, the resolved fraction of the stacked sampling
  (:mod:`.theory`) along that axis; a registration-error axis gets the error the project's registration reaches
  marked on it (dashed line).
* :func:`axis_curves`: one axis, every method's mean with its standard error, and the margin below with the zero
  line, the theory on a second scale.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..plots import _plt, _save, method_colours

_MARK = {"array": "A", "dofp": "D", "undecided": "?"}


def _position(value: float, ticks: list[float]) -> float | None:
    """Where ``value`` falls on a categorical axis of ``ticks`` (linear between neighbours), or None outside."""
    if value is None or not ticks or value < min(ticks) or value > max(ticks):
        return None
    return float(np.interp(value, ticks, np.arange(len(ticks))))


def margin_heatmap(path: Path, *, grid: dict[tuple, dict], axes: tuple[str, str], values: tuple[list, list],
                   metric_label: str, title: str, theory: dict | None = None,
                   reached: dict[str, float] | None = None) -> Path:
    """Write the heatmap of ``grid`` (``{(y value, x value): cell margin}``) to ``path`` (module docstring).

    ``axes``: ``(y axis, x axis)`` names; ``values``: their values; ``theory``: ``{axis, values, fractions}`` of a
    pose axis; ``reached``: ``{axis: HR px}`` of a registration axis.
    """
    plt = _plt()
    ys, xs = values
    m = np.full((len(ys), len(xs)), np.nan)
    for (yv, xv), cell in grid.items():
        m[ys.index(yv), xs.index(xv)] = cell["margin"]
    panels = 2 if theory else 1
    fig, axs = plt.subplots(1, panels, figsize=(6.0 + 3.2 * (panels - 1), 4.6), squeeze=False,
                            gridspec_kw={"width_ratios": [3, 1.4][:panels]}, layout="constrained")
    ax = axs[0][0]
    span = float(np.nanmax(np.abs(m))) if np.isfinite(m).any() else 1.0
    image = ax.imshow(m, cmap="RdBu", vmin=-(span or 1.0), vmax=span or 1.0, origin="lower", aspect="auto")
    fig.colorbar(image, ax=ax, label=f"margin, array - DoFP ({metric_label})")
    if len(xs) > 1 and len(ys) > 1 and np.isfinite(m).all() and m.min() < 0 < m.max():
        ax.contour(np.arange(len(xs)), np.arange(len(ys)), m, levels=[0.0], colors="k", linewidths=2)
    for (yv, xv), cell in grid.items():
        se = "" if cell["se"] is None else f"\n±{cell['se']:.2g}"
        ax.text(xs.index(xv), ys.index(yv), f"{_MARK[cell['verdict']]} {cell['margin']:+.2g}{se}", ha="center",
                va="center", fontsize=7)
    ax.set_xticks(range(len(xs)), [f"{v:g}" if isinstance(v, float) else str(v) for v in xs])
    ax.set_yticks(range(len(ys)), [f"{v:g}" if isinstance(v, float) else str(v) for v in ys])
    ax.set_xlabel(axes[1])
    ax.set_ylabel(axes[0])
    for name, hr_px in (reached or {}).items():
        if name == axes[1] and _position(hr_px, xs) is not None:
            ax.axvline(_position(hr_px, xs), color="k", linestyle="--", label=f"registration reaches {hr_px:.2g} px")
        elif name == axes[0] and _position(hr_px, ys) is not None:
            ax.axhline(_position(hr_px, ys), color="k", linestyle="--", label=f"registration reaches {hr_px:.2g} px")
    if reached:
        ax.legend(loc="upper right", fontsize=7)
    ax.set_title(f"{title}\nA: array wins, D: DoFP wins, ?: within 1 SE; black: zero contour", fontsize=8)
    if theory:
        _theory_panel(axs[0][1], theory)
    return _save(fig, path)


def _theory_panel(ax, theory: dict) -> None:
    ax.plot(theory["values"], theory["fractions"], "o-", color="tab:purple")
    ax.set_xlabel(theory["axis"])
    ax.set_ylabel("resolved fraction of stacked sampling")
    ax.set_ylim(0, 1)
    ax.axhline(0.25, color="grey", linestyle=":", linewidth=1)
    ax.set_title("theory: share of singular values\n> 0.1 s_max (0.25 = one aperture)", fontsize=8)


def axis_curves(path: Path, *, axis: str, values: list, curves: dict[str, dict], margin: dict, metric_label: str,
                title: str, theory: dict | None = None, reached: float | None = None) -> Path:
    """Write the curves of a one-axis map to ``path`` (module docstring): ``curves`` ``{method: {value: (mean,
    se)}}``, ``margin`` ``{value: cell margin}``."""
    plt = _plt()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6.0, 6.0), sharex=True, gridspec_kw={"height_ratios": [2, 1]},
                                      layout="constrained")
    colours = method_colours(sorted(curves))
    for label in sorted(curves):
        xs = [v for v in values if v in curves[label]]
        means = [curves[label][v][0] for v in xs]
        errs = [curves[label][v][1] or 0.0 for v in xs]
        top.errorbar(xs, means, yerr=errs, marker="o", capsize=3, color=colours[label], label=label)
    top.set_ylabel(metric_label)
    top.legend(fontsize=7)
    top.set_title(title, fontsize=9)
    xs = [v for v in values if v in margin]
    bottom.errorbar(xs, [margin[v]["margin"] for v in xs], yerr=[margin[v]["se"] or 0.0 for v in xs], marker="s",
                    capsize=3, color="k")
    bottom.axhline(0.0, color="grey", linewidth=1)
    bottom.set_ylabel("margin, array - DoFP")
    bottom.set_xlabel(axis)
    if reached is not None and math.isfinite(reached):
        for ax in (top, bottom):
            ax.axvline(reached, color="k", linestyle="--")
        top.text(reached, top.get_ylim()[0], f" registration reaches {reached:.2g} px", fontsize=7, va="bottom")
    if theory:
        twin = top.twinx()
        twin.plot(theory["values"], theory["fractions"], ":", color="tab:purple", marker="x")
        twin.set_ylabel("resolved fraction (theory)", color="tab:purple")
        twin.set_ylim(0, 1)
    return _save(fig, path)
