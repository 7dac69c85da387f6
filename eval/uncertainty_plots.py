"""Plots of a reconstruction's error bars (matplotlib, Agg), written as PNG files atomically.

Three pictures per method (:func:`write_uncertainty_plots`):

``METHOD.sparsification.png`` (:func:`sparsification_plot`)
    the sparsification curve of each group and its oracle (Ilg et al., ECCV 2018), AUSE in the legend;
``METHOD.s0-std.png`` (:func:`s0_uncertainty_plot`)
    the standard deviation of S0 beside the actual ``|S0 error|`` of one colour, on one colour scale;
``METHOD.dolp-aop.png`` (:func:`polarization_uncertainty_plot`)
    DoLP with the width of its 90 % interval, and AoP drawn only where its interval is narrower than a
    threshold (grey elsewhere).

The maps cover the whole HR grid (no border crop), on the layout of
:mod:`capssim.reconstruct.uncertainty.maps`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capssim.conventions import COLOURS
from capssim.reconstruct.uncertainty.maps import UncertaintyMaps, stokes_plane
from capssim.stokes.polarization import aop_deg, dolp, stokes_from_12

from .plots import _plt, _save
from .uncertainty_scores import GROUPS, UncertaintyScores

__all__ = ["aop_where_certain", "polarization_uncertainty_plot", "s0_uncertainty_plot", "sparsification_plot", "write_uncertainty_plots"]

#: the default AoP interval width (degrees) above which :func:`polarization_uncertainty_plot` greys AoP out
AOP_MAX_WIDTH_DEG = 20.0
#: the grey of pixels whose AoP is too uncertain to draw
UNCERTAIN_GREY = (0.55, 0.55, 0.55, 1.0)


def _titled(title: str, text: str) -> str:
    return f"{title}: {text}" if title else text


def _colour_index(colour: int | str) -> int:
    return COLOURS.index(colour) if isinstance(colour, str) else int(colour)


def _image_axes(ax, image, title: str, *, cmap: str = "viridis", vmin: float = 0.0, vmax: float | None = None,
                colourbar: str | None = None):
    """``image`` shown on ``ax`` without ticks, with ``title`` and (``colourbar``: its label) a colour bar."""
    shown = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")  # RGBA: as it is
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=9)
    if colourbar is not None:
        ax.figure.colorbar(shown, ax=ax, fraction=0.046, pad=0.03).set_label(colourbar, fontsize=8)
    return shown


def sparsification_plot(scores: UncertaintyScores, path, *, title: str = "") -> Path | None:
    """One panel per group of ``scores``: the sparsification curve (RMSE of the values left after removing the
    fraction with the largest std, over the RMSE of all) and the oracle's (largest ``|error|`` removed), AUSE in
    the legend; written to ``path`` (PNG). None when no group has curves."""
    plt = _plt()
    drawn = [(name, scores.groups[name].sparsification) for name in GROUPS
             if name in scores.groups and scores.groups[name].sparsification is not None]
    if not drawn:
        return None
    fig, axes = plt.subplots(1, len(drawn), figsize=(3.6 * len(drawn), 3.4), squeeze=False)
    for ax, (name, sp) in zip(axes.flat, drawn):
        ax.plot(sp.fractions, sp.curve, color="tab:blue", lw=1.6, label=f"by std (AUSE {sp.ause:.3f})")
        ax.plot(sp.fractions, sp.oracle, color="black", lw=1.2, ls="--", label="oracle (by |error|)")
        ax.fill_between(sp.fractions, sp.oracle, sp.curve, color="tab:blue", alpha=0.15)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, max(1.05, float(np.max(sp.curve)) * 1.05))
        ax.set_xlabel("fraction removed")
        ax.set_title(f"{name} ({scores.groups[name].scored} values)", fontsize=9)
        ax.grid(True, alpha=0.25)
        ax.legend(fontsize=7, loc="lower left")
    axes[0, 0].set_ylabel("RMSE of the rest / RMSE of all")
    fig.suptitle(_titled(title, "sparsification (Ilg et al. 2018); AUSE 0 = std ranks the errors perfectly"),
                 fontsize=10)
    fig.tight_layout()
    return _save(fig, Path(path))


def s0_uncertainty_plot(estimate, gt, maps: UncertaintyMaps, path, *, colour: int | str = "G",
                        title: str = "") -> Path:
    """The standard deviation of S0 (S0 scale [0, 2]) of ``colour`` beside the actual ``|S0 error|`` of the
    ``(12, H, W)`` ``estimate`` against ``gt``, on one colour scale (up to the 99th percentile of both); PNG."""
    plt = _plt()
    k = _colour_index(colour)
    s0_error = np.abs(stokes_from_12(np.asarray(estimate, np.float64))[0, k]
                      - stokes_from_12(np.asarray(gt, np.float64))[0, k])
    s0_std = maps.stokes[stokes_plane("S0", "std", k)]
    top = float(np.percentile(np.concatenate([s0_std.ravel(), s0_error.ravel()]), 99)) or 1e-6
    fig, axes = plt.subplots(1, 2, figsize=(8.4, 3.9))
    _image_axes(axes[0], s0_std, f"S0 std ({COLOURS[k]})", cmap="magma", vmax=top)
    shown = _image_axes(axes[1], s0_error, f"|S0 error| ({COLOURS[k]})", cmap="magma", vmax=top)
    fig.colorbar(shown, ax=list(axes), fraction=0.046, pad=0.03).set_label("S0 (scale [0, 2])", fontsize=8)
    fig.suptitle(_titled(title, "the error bars should be large where the error is"), fontsize=10)
    return _save(fig, Path(path))


def aop_where_certain(aop: np.ndarray, width: np.ndarray, *, max_width_deg: float = AOP_MAX_WIDTH_DEG) -> np.ndarray:
    """``(H, W, 4)`` RGBA: AoP (degrees, ``(H, W)``) on the cyclic ``twilight`` map where its interval ``width``
    (degrees) is below ``max_width_deg``, :data:`UNCERTAIN_GREY` elsewhere."""
    rgba = _plt().get_cmap("twilight")(np.mod(aop, 180.0) / 180.0)
    rgba[~(width < max_width_deg)] = UNCERTAIN_GREY
    return rgba


def polarization_uncertainty_plot(estimate, maps: UncertaintyMaps, path, *, colour: int | str = "G",
                                  aop_max_width_deg: float = AOP_MAX_WIDTH_DEG, title: str = "") -> Path:
    """DoLP of ``colour`` of the ``(12, H, W)`` ``estimate`` with the width of its 90 % interval, and its AoP
    where the AoP interval is narrower than ``aop_max_width_deg`` degrees (grey elsewhere); PNG at ``path``."""
    plt = _plt()
    k = _colour_index(colour)
    stokes = stokes_from_12(np.asarray(estimate, np.float64))[:, k]
    planes = {(q, s): maps.stokes[stokes_plane(q, s, k)] for q in ("DoLP", "AoP") for s in ("lower", "upper")}
    dolp_width = planes["DoLP", "upper"] - planes["DoLP", "lower"]
    aop_width = planes["AoP", "upper"] - planes["AoP", "lower"]
    fig, axes = plt.subplots(1, 3, figsize=(12.6, 3.9))
    _image_axes(axes[0], dolp(stokes), f"DoLP ({COLOURS[k]})", cmap="gray", vmax=1.0, colourbar="DoLP")
    _image_axes(axes[1], dolp_width, "DoLP 90 % interval width", cmap="magma",
                vmax=max(float(np.percentile(dolp_width, 99)), 1e-6), colourbar="DoLP")
    share = float(np.mean(aop_width < aop_max_width_deg))
    _image_axes(axes[2], aop_where_certain(aop_deg(stokes), aop_width, max_width_deg=aop_max_width_deg),
                f"AoP where its interval < {aop_max_width_deg:g} deg ({100 * share:.0f} %)\ngrey: too uncertain")
    key = plt.cm.ScalarMappable(cmap="twilight", norm=plt.Normalize(0.0, 180.0))
    fig.colorbar(key, ax=axes[2], fraction=0.046, pad=0.03, ticks=[0, 45, 90, 135, 180]).set_label("AoP (deg)",
                                                                                                  fontsize=8)
    fig.suptitle(_titled(title, "polarization with its error bars"), fontsize=10)
    return _save(fig, Path(path))


def write_uncertainty_plots(estimate, gt, maps: UncertaintyMaps, scores: UncertaintyScores, out_dir, *,
                            method: str, colour: int | str = "G",
                            aop_max_width_deg: float = AOP_MAX_WIDTH_DEG) -> list[Path]:
    """The three error-bar plots of ``method`` (module docstring) in ``out_dir``, created when missing.

    Parameters
    ----------
    estimate, gt : array_like
        ``(12, H, W)`` reconstruction and ground truth.
    maps : UncertaintyMaps
        The reconstruction's error bars.
    scores : UncertaintyScores
        Their scores (:func:`~capssim.eval.uncertainty_scores.score_uncertainty`), for the sparsification plot.
    out_dir : str or pathlib.Path
        The folder of the PNG files, named ``METHOD.sparsification.png``, ``METHOD.s0-std.png`` and
        ``METHOD.dolp-aop.png``.
    method : str
        The reconstruction's name (file names and titles).
    colour : int or str
        The colour (R, G, B or 0-2) of the S0, DoLP and AoP maps.
    aop_max_width_deg : float
        AoP is drawn where its interval is narrower than this (degrees).

    Returns
    -------
    list of pathlib.Path
        The files written.
    """
    out_dir = Path(out_dir)
    written = [sparsification_plot(scores, out_dir / f"{method}.sparsification.png", title=method),
               s0_uncertainty_plot(estimate, gt, maps, out_dir / f"{method}.s0-std.png", colour=colour, title=method),
               polarization_uncertainty_plot(estimate, maps, out_dir / f"{method}.dolp-aop.png", colour=colour,
                                             aop_max_width_deg=aop_max_width_deg, title=method)]
    return [p for p in written if p is not None]
