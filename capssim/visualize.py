"""Display images of 12-channel results: intensity, DoLP and AoP.

* Intensity: ``S0 / 2`` per colour (the mean of the four analyzer images), scaled so the
  99.5th percentile is white, sRGB-encoded.
* DoLP: the DoLP of each colour shown as an RGB image (paper fig. 7, axis labels R, G, B).
* AoP: the paper's fig. 7 style map on the luminance Stokes vector: hue = AoP (0..180 deg
  round the colour circle), saturation = DoLP (scaled by ``dolp_max``), value = 1; dark
  pixels are grey.
* Panel (``panel.png``, ``render --preview``): the three side by side, each with its title and
  key: the intensity scale, the DoLP scale (0 .. ``dolp_max``) and the AoP colour key.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capssim.files.imageio import write_png
from capssim.stokes.polarization import aop_deg, dolp, stokes_from_12


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    x = np.clip(np.nan_to_num(linear), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _hsv_to_rgb(h, s, v):
    i = np.floor(h * 6.0).astype(int) % 6
    f = h * 6.0 - np.floor(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    choices = [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)]
    out = np.zeros((*h.shape, 3))
    for k, (r, g, b) in enumerate(choices):
        m = i == k
        out[m, 0], out[m, 1], out[m, 2] = r[m], g[m], b[m]
    return out


def display_white(image12: np.ndarray) -> float:
    """The intensity ``S0/2`` shown as white: its 99.5th percentile.

    Parameters
    ----------
    image12 : numpy.ndarray
        ``(12, H, W)`` intensities on [0, 1], channel ``c = 3 p + k``.

    Returns
    -------
    float
        The white level, a fraction of full scale, at least 1e-6 (1 when no value is finite).
    """
    s0_half = stokes_from_12(np.asarray(image12, dtype=np.float64))[0] / 2
    finite = s0_half[np.isfinite(s0_half)]
    return max(float(np.percentile(finite, 99.5)) if finite.size else 1.0, 1e-6)


def intensity_image(image12: np.ndarray, *, white: float | None = None) -> np.ndarray:
    """Display RGB of the unpolarized intensity ``S0/2``.

    Parameters
    ----------
    image12 : numpy.ndarray
        ``(12, H, W)`` intensities on [0, 1], channel ``c = 3 p + k``.
    white : float, optional
        The ``S0/2`` level shown as white; default :func:`display_white` of ``image12`` (give one
        value to show several images on one scale).

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` sRGB-encoded float64 on [0, 1].
    """
    s = stokes_from_12(np.asarray(image12, dtype=np.float64))
    rgb = np.moveaxis(s[0] / 2, 0, -1)
    white = display_white(image12) if white is None else white
    return srgb_encode(rgb / max(white, 1e-6))


def dolp_image(image12: np.ndarray, *, dolp_max: float = 1.0, min_s0: float = 1e-3) -> np.ndarray:
    """The DoLP of R, G and B as the three display channels.

    Parameters
    ----------
    image12 : numpy.ndarray
        ``(12, H, W)`` intensities, channel ``c = 3 p + k``.
    dolp_max : float
        The DoLP shown at full brightness.
    min_s0 : float
        Pixels with ``S0`` at most this have DoLP 0.

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` float64 on [0, 1]: ``DoLP / dolp_max``, clipped.
    """
    s = stokes_from_12(np.asarray(image12, dtype=np.float64))
    d = dolp(s, min_s0=min_s0)  # (3, H, W)
    return np.clip(np.moveaxis(d, 0, -1) / dolp_max, 0, 1)


def aop_image(image12: np.ndarray, *, dolp_max: float = 0.5, min_s0: float = 1e-3) -> np.ndarray:
    """AoP as hue and DoLP as saturation, of the RGB-summed Stokes vector.

    Parameters
    ----------
    image12 : numpy.ndarray
        ``(12, H, W)`` intensities, channel ``c = 3 p + k``.
    dolp_max : float
        The DoLP shown fully saturated.
    min_s0 : float
        Pixels with ``S0`` at most this are grey (0.5).

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` RGB float64 on [0, 1]; hue = AoP / 180 deg (key: :func:`aop_legend`).
    """
    s = stokes_from_12(np.asarray(image12, dtype=np.float64)).sum(axis=1)  # (3, H, W)
    angle = aop_deg(s)
    d = dolp(s, min_s0=min_s0)
    hue = angle / 180.0
    sat = np.clip(d / dolp_max, 0, 1)
    rgb = _hsv_to_rgb(hue, sat, np.ones_like(hue))
    dark = ~(s[0] > min_s0)
    rgb[dark] = 0.5
    return rgb


def aop_legend(size: int = 64, *, dolp_max: float = 0.5) -> np.ndarray:
    """Colour key of :func:`aop_image`: AoP along x (0..180 deg), DoLP along y (0 at the bottom).

    Parameters
    ----------
    size : int
        Side of the square key, pixels.
    dolp_max : float
        The DoLP at the top row (label only: the key spans saturation 0..1).

    Returns
    -------
    numpy.ndarray
        ``(size, size, 3)`` RGB float64 on [0, 1].
    """
    x = np.linspace(0, 1, size, endpoint=False)
    y = np.linspace(1, 0, size)
    hue, sat = np.meshgrid(x, y)
    return _hsv_to_rgb(hue, sat, np.ones_like(hue))


# -- keys drawn on matplotlib axes (eval.plots uses them too) ---------------------------------
def draw_intensity_key(ax, white: float) -> None:
    """Horizontal bar: the grey level of ``S0/2`` from 0 to ``white`` (fraction of full scale), sRGB-encoded."""
    ax.imshow(srgb_encode(np.linspace(0, 1, 256))[None, :], cmap="gray", vmin=0, vmax=1, aspect="auto",
              extent=(0, white, 0, 1))
    ax.set_yticks([])
    ax.set_xticks([0, white / 2, white], [f"{v:.3g}" for v in (0, white / 2, white)])
    ax.tick_params(labelsize=7)
    ax.set_xlabel("S0/2, fraction of full scale (sRGB)", fontsize=7)


def draw_dolp_key(ax, dolp_max: float) -> None:
    """Horizontal bar: DoLP 0 (black) .. ``dolp_max`` (white); each colour's DoLP drives its display channel."""
    ax.imshow(np.linspace(0, 1, 256)[None, :], cmap="gray", vmin=0, vmax=1, aspect="auto", extent=(0, dolp_max, 0, 1))
    ax.set_yticks([])
    ax.set_xticks([0, dolp_max / 2, dolp_max], [f"{v:.2g}" for v in (0, dolp_max / 2, dolp_max)])
    ax.tick_params(labelsize=7)
    ax.set_xlabel("DoLP; 0 where S0 <= 0.001", fontsize=7)


def draw_aop_key(ax, dolp_max: float) -> None:
    """The AoP colour key of :func:`aop_image`: AoP in degrees along x, DoLP 0 .. ``dolp_max`` along y."""
    ax.imshow(aop_legend(64, dolp_max=dolp_max), extent=(0, 180, 0, dolp_max), aspect="auto")
    ax.set_xticks([0, 45, 90, 135, 180])
    ax.set_yticks([0, dolp_max], ["0", f"{dolp_max:.2g}"])
    ax.tick_params(labelsize=7)
    ax.set_xlabel("AoP (deg); grey: S0 <= 0.001", fontsize=7)
    ax.set_ylabel("DoLP", fontsize=7)


def panel_figure(image12: np.ndarray, *, white: float | None = None, dolp_max: float = 0.5, title: str = ""):
    """Intensity | DoLP | AoP side by side with titles and keys: a matplotlib ``Figure`` (Agg canvas, 100 dpi).

    Each map is shown at least 260 display pixels wide where possible, at most 512 (nearest-
    neighbour when enlarged); under it its key: the intensity scale (``white`` =
    :func:`display_white` by default), the DoLP scale 0 .. ``dolp_max``, the AoP colour key.
    ``title`` (optional) heads the panel.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # display only: no global backend
    from matplotlib.figure import Figure

    h, w = np.asarray(image12).shape[1:]
    white = display_white(image12) if white is None else float(white)
    zoom = min(max(260 / w, min(max(h, w), 512) / max(h, w)), 1024 / h)  # >= 260 px wide where possible
    dw, dh, gap, top, keys = w * zoom, h * zoom, 40.0, 36.0 + (24.0 if title else 0.0), 116.0
    fig_w, fig_h = 3 * dw + 2 * gap + 40.0, dh + top + keys
    fig = Figure(figsize=(fig_w / 100, fig_h / 100), dpi=100)
    FigureCanvasAgg(fig)
    maps = ((intensity_image(image12, white=white), f"intensity S0/2\nwhite = {white:.3g} of full scale",
             lambda ax: draw_intensity_key(ax, white), 14.0),
            (dolp_image(image12, dolp_max=dolp_max), f"DoLP of R, G, B\n0 (black) .. {dolp_max:.3g} (white)",
             lambda ax: draw_dolp_key(ax, dolp_max), 14.0),
            (aop_image(image12, dolp_max=dolp_max), f"AoP: hue = angle\nsaturation = DoLP / {dolp_max:.3g}",
             lambda ax: draw_aop_key(ax, dolp_max), 60.0))
    for i, (picture, label, draw_key, key_h) in enumerate(maps):
        left = 20.0 + i * (dw + gap)
        ax = fig.add_axes((left / fig_w, keys / fig_h, dw / fig_w, dh / fig_h))
        ax.imshow(np.clip(picture, 0, 1), interpolation="nearest" if zoom >= 1 else "antialiased", aspect="auto")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(label, fontsize=8)
        key_w = dw * (0.5 if key_h > 20 else 0.8)
        draw_key(fig.add_axes(((left + (dw - key_w) / 2) / fig_w, (keys - 20 - key_h) / fig_h, key_w / fig_w,
                               key_h / fig_h)))
    if title:
        fig.suptitle(title, fontsize=9, y=1 - 6 / fig_h, va="top")
    return fig


def preview_panel(image12: np.ndarray, *, white: float | None = None, dolp_max: float = 0.5,
                  title: str = "") -> np.ndarray:
    """:func:`panel_figure` rendered: ``(h, w, 3)`` float in [0, 1], ready for :func:`capssim.files.imageio.write_png`."""
    fig = panel_figure(image12, white=white, dolp_max=dolp_max, title=title)
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.float64) / 255.0


def preview_scales(image12: np.ndarray, *, white: float | None = None, dolp_max: float = 0.5) -> dict[str, str]:
    """What each file of :func:`write_previews` shows, with its scale (for a JSON record next to them)."""
    white = display_white(image12) if white is None else float(white)
    return {"intensity.png": f"S0/2 per colour, sRGB-encoded, white = {white:.4g} of full scale",
            "dolp.png": "DoLP of R, G, B as the display's R, G, B, 0 (black) .. 1 (full); 0 where S0 <= 1e-3",
            "aop.png": f"AoP of the luminance Stokes vector as hue (0..180 deg round the colour circle), saturation "
                       f"= DoLP / {dolp_max:g}; grey where S0 <= 1e-3",
            "panel.png": "intensity | DoLP | AoP with titles and keys"}


def write_previews(image12: np.ndarray, out_dir, *, prefix: str = "", white: float | None = None,
                   dolp_max: float = 0.5, title: str = "") -> dict[str, Path]:
    """Write ``intensity.png``, ``dolp.png``, ``aop.png`` and ``panel.png`` (with ``prefix``).

    The first three are the bare maps pixel for pixel (:func:`preview_scales` says their scales,
    for a record); ``panel.png`` is :func:`preview_panel`, with titles and keys.
    """

    out_dir = Path(out_dir)
    paths = {
        "intensity": out_dir / f"{prefix}intensity.png",
        "dolp": out_dir / f"{prefix}dolp.png",
        "aop": out_dir / f"{prefix}aop.png",
        "panel": out_dir / f"{prefix}panel.png",
    }
    write_png(paths["intensity"], intensity_image(image12, white=white))
    write_png(paths["dolp"], dolp_image(image12, dolp_max=1.0))
    write_png(paths["aop"], aop_image(image12, dolp_max=dolp_max))
    write_png(paths["panel"], preview_panel(image12, white=white, dolp_max=dolp_max, title=title))
    return paths
