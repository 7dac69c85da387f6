"""Benchmark plots (matplotlib, Agg): speed vs error with the Pareto front, crops, MTF curves."""

from __future__ import annotations

import io
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from capssim.files.imageio import atomic_write_bytes
from capssim.stokes.polarization import dolp, stokes_from_12
from capssim.visualize import aop_image, dolp_image, draw_aop_key, draw_dolp_key, draw_intensity_key, intensity_image

_MARKERS = "osD^v<>pP*hX"


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())
    _plt().close(fig)
    return path


def pareto_front(times: np.ndarray, values: np.ndarray, *, higher_is_better: bool = True) -> np.ndarray:
    """Indices of the points no other point beats in both time (lower) and value, by time."""
    v = values if higher_is_better else -values
    order = np.lexsort((-v, times))
    front, best = [], -np.inf
    for i in order:
        if v[i] > best:
            front.append(i)
            best = v[i]
    return np.asarray(front, dtype=int)


def method_colours(methods: list[str]) -> dict[str, tuple]:
    plt = _plt()
    cmap = plt.get_cmap("tab10" if len(methods) <= 10 else "tab20")
    return {m: cmap(i % cmap.N) for i, m in enumerate(methods)}


def _group_means(records: list[dict], metric: str) -> dict[tuple, dict[str, tuple[float, float]]]:
    """(scene, noise) -> method -> (mean time, mean metric) over seeds."""
    acc: dict[tuple, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        value = r["metrics"].get(metric)
        if value is None or r.get("wall_time_s") is None:
            continue
        acc[(r["scene"], r["noise"])][r["method"]].append((r["wall_time_s"], value))
    return {g: {m: tuple(np.mean(v, axis=0)) for m, v in ms.items()} for g, ms in acc.items()}


def speed_vs_error(records: list[dict], path: Path, *, metric: str = "psnr_mean", label: str = "PSNR (dB)",
                   higher_is_better: bool = True, methods: list[str] | None = None) -> Path | None:
    """One panel per (scene, noise): wall time (log) vs ``metric``; the Pareto front marked."""
    plt = _plt()
    groups = _group_means(records, metric)
    if not groups:
        return None
    methods = methods or sorted({m for g in groups.values() for m in g})
    colours = method_colours(methods)
    n = len(groups)
    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.0 * rows), squeeze=False)
    for ax, ((scene, noise), pts) in zip(axes.flat, sorted(groups.items())):
        names = [m for m in methods if m in pts]
        t = np.array([pts[m][0] for m in names])
        v = np.array([pts[m][1] for m in names])
        front = pareto_front(t, v, higher_is_better=higher_is_better)
        ft, fv = t[front], v[front]
        ax.step(np.r_[ft, ft[-1] * 3], np.r_[fv, fv[-1]], where="post", color="0.55", lw=1.2, ls="--", zorder=1,
                label="Pareto front")
        for i, m in enumerate(names):
            on_front = i in set(front.tolist())
            ax.scatter(t[i], v[i], s=70 if on_front else 45, color=colours[m], marker=_MARKERS[methods.index(m) % len(_MARKERS)],
                       edgecolors="black" if on_front else "none", linewidths=1.3, zorder=3, label=m)
            ax.annotate(m, (t[i], v[i]), textcoords="offset points", xytext=(5, 4), fontsize=8)
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(plt.NullFormatter())  # labelled minor ticks overlap on short ranges
        lo, hi = t.min(), t.max()
        ax.set_xlim(lo / 2, hi * 3)
        ax.set_xlabel("wall time per reconstruction (s, log)")
        ax.set_ylabel(label + ("" if higher_is_better else " (lower is better)"))
        ax.set_title(f"{scene} / {noise}", fontsize=10)
        ax.grid(True, which="both", alpha=0.25)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    fig.legend(uniq.values(), uniq.keys(), loc="upper center", ncol=min(6, len(uniq)), fontsize=8,
               bbox_to_anchor=(0.5, 1.0 + 0.04 / rows), frameon=False)
    fig.suptitle(f"Speed vs {label}: black-edged markers are on the Pareto front", y=1.0 + 0.09 / rows, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


def _crop_window(shape, size: int) -> tuple[slice, slice]:
    h, w = shape
    ch, cw = min(size, h), min(size, w)
    top, left = (h - ch) // 2, (w - cw) // 2
    return slice(top, top + ch), slice(left, left + cw)


def crops(gt: np.ndarray, estimates: dict[str, np.ndarray], path: Path, *, title: str = "", crop: int = 128,
          center_rowcol: tuple[float, float] | None = None) -> Path:
    """Ground truth and each method: intensity, DoLP and AoP (fig. 7 colour map) of one crop; a key under each column."""
    plt = _plt()
    if center_rowcol is not None:
        h, w = gt.shape[1:]
        ch, cw = min(crop, h), min(crop, w)
        top = int(np.clip(round(center_rowcol[0] - ch / 2), 0, h - ch))
        left = int(np.clip(round(center_rowcol[1] - cw / 2), 0, w - cw))
        win = (slice(top, top + ch), slice(left, left + cw))
    else:
        win = _crop_window(gt.shape[1:], crop)
    s_gt = stokes_from_12(gt.astype(np.float64))
    white = 1.2 * float(np.percentile(s_gt[0] / 2, 99.5)) or 1.0  # headroom: overshoots stay visible
    lum = s_gt.sum(axis=1)
    dmax = float(np.clip(np.percentile(dolp(lum, min_s0=1e-3), 99), 0.1, 1.0))
    rows = [("ground truth", gt)] + list(estimates.items())
    height, keys_in = len(rows) * 2.6 + 0.3 + 1.1, 1.1  # inches; the keys take the bottom keys_in
    fig, axes = plt.subplots(len(rows), 3, figsize=(3 * 2.6, height), squeeze=False)
    for r, (name, img) in enumerate(rows):
        img_c = img[:, win[0], win[1]]
        panels = [intensity_image(img_c, white=white), dolp_image(img_c, dolp_max=dmax),
                  aop_image(img_c, dolp_max=dmax)]
        for c, panel in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(np.clip(panel, 0, 1), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(name, fontsize=9)
            if r == 0:
                ax.set_title([f"intensity S0/2 (sRGB)\nwhite = {white:.3g} of full scale",
                              f"DoLP of R, G, B\n0 (black) .. {dmax:.2f} (white)",
                              f"AoP: hue = angle\nsaturation = DoLP / {dmax:.2f}"][c], fontsize=8)
    fig.suptitle(f"{title}  (crop {win[0].stop - win[0].start}x{win[1].stop - win[1].start} HR px)", fontsize=10)
    fig.subplots_adjust(left=0.06, right=0.98, top=1 - 0.85 / height, bottom=keys_in / height, wspace=0.04,
                        hspace=0.06)
    for c, (draw, key_in) in enumerate(((lambda ax: draw_intensity_key(ax, white), 0.12),
                                        (lambda ax: draw_dolp_key(ax, dmax), 0.12),
                                        (lambda ax: draw_aop_key(ax, dmax), 0.55))):
        box = axes[-1, c].get_position()
        key_w = box.width * (0.55 if key_in > 0.2 else 0.85)
        draw(fig.add_axes((box.x0 + (box.width - key_w) / 2, (keys_in - 0.12 - key_in) / height, key_w,
                           key_in / height)))
    return _save(fig, path)


def mtf_curves(gt_mtf: dict | None, method_mtfs: dict[str, dict], path: Path, *, title: str = "",
               methods: list[str] | None = None) -> Path | None:
    """Channel-mean MTF vs frequency in cycles per Bayer sub-image pixel; hv solid, diagonal dashed."""
    plt = _plt()
    if not method_mtfs and not gt_mtf:
        return None
    methods = methods or list(method_mtfs)
    colours = method_colours(methods)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), sharey=True)
    curves = ([("ground truth", gt_mtf, "black")] if gt_mtf else []) + [(m, method_mtfs[m], colours[m])
                                                                         for m in methods if m in method_mtfs]
    for ax, group, style in ((axes[0], "hv", "-"), (axes[1], "diagonal", "--")):
        for name, mt, colour in curves:
            f = np.asarray(mt["frequency_cyc_per_ref_px"], dtype=float)
            m = np.asarray([np.nan if v is None else v for v in mt["mtf"][group]], dtype=float)
            cred = np.asarray(mt["credited"][group], dtype=bool)
            ax.plot(f[cred], m[cred], style, color=colour, lw=2.0 if name == "ground truth" else 1.4,
                    label=f"{name} (x{mt['magnification'][group]:.2f}, {mt['limited_by'][group]})")
            if (~cred).any():
                ax.plot(f[~cred], m[~cred], ":", color=colour, lw=0.8, alpha=0.5)
            lim = mt["limit_cyc_per_ref_px"][group]
            ax.plot([lim], [mt.get("threshold", 0.03)], "|", color=colour, ms=14, mew=2)
        ax.axhline(0.03, color="0.4", lw=0.8, ls=":")
        ax.text(0.02, 0.045, "MTF 0.03 (limit)", fontsize=7, color="0.3", transform=ax.get_yaxis_transform())
        for x, lab in ((0.5, "sub-image Nyquist"), (2.0, "HR Nyquist")):
            ax.axvline(x, color="0.6", lw=0.8, ls="-.")
            ax.text(x, 1.02, lab, fontsize=7, ha="center", color="0.35")
        ax.set_xlim(0, 2.2)
        ax.set_ylim(-0.02, 1.15)
        ax.set_xlabel("frequency (cycles per Bayer sub-image pixel = 4 HR px)")
        ax.set_title(f"{'horizontal/vertical' if group == 'hv' else 'diagonal'} segments", fontsize=10)
        ax.grid(True, alpha=0.25)
        ax.legend(fontsize=7, loc="center right")
    axes[0].set_ylabel("MTF (mean of 12 channels)")
    fig.suptitle(f"{title}: SR magnification = limit / 0.5; dotted = not credited (aliasing/noise/Nyquist)",
                 fontsize=10)
    fig.tight_layout()
    return _save(fig, path)
