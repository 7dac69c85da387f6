"""Display images of 12-channel results: intensity, DoLP and AoP.

* Intensity: ``S0 / 2`` per colour (the mean of the four analyzer images), scaled so the
  99.5th percentile is white, sRGB-encoded.
* DoLP: the DoLP of each colour shown as an RGB image (paper fig. 7, axis labels R, G, B).
* AoP: the paper's fig. 7 style map on the luminance Stokes vector: hue = AoP (0..180 deg
  round the colour circle), saturation = DoLP (scaled by ``dolp_max``), value = 1; dark
  pixels are grey.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capssim.imageio import write_png
from capssim.polarization import aop_deg, dolp, stokes_from_12


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


def intensity_image(image12: np.ndarray, *, white: float | None = None) -> np.ndarray:
    """``(H, W, 3)`` display RGB of the unpolarized intensity ``S0/2``."""
    s = stokes_from_12(np.asarray(image12, dtype=np.float64))
    rgb = np.moveaxis(s[0] / 2, 0, -1)
    if white is None:
        finite = rgb[np.isfinite(rgb)]
        white = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    return srgb_encode(rgb / max(white, 1e-6))


def dolp_image(image12: np.ndarray, *, dolp_max: float = 1.0, min_s0: float = 1e-3) -> np.ndarray:
    """``(H, W, 3)``: DoLP of R, G and B as the three display channels."""
    s = stokes_from_12(np.asarray(image12, dtype=np.float64))
    d = dolp(s, min_s0=min_s0)  # (3, H, W)
    return np.clip(np.moveaxis(d, 0, -1) / dolp_max, 0, 1)


def aop_image(image12: np.ndarray, *, dolp_max: float = 0.5, min_s0: float = 1e-3) -> np.ndarray:
    """``(H, W, 3)``: hue = AoP, saturation = DoLP / dolp_max, on the RGB-summed Stokes vector."""
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
    """Colour key: AoP along x (0..180 deg), DoLP along y (0 at the bottom, dolp_max at the top)."""
    x = np.linspace(0, 1, size, endpoint=False)
    y = np.linspace(1, 0, size)
    hue, sat = np.meshgrid(x, y)
    return _hsv_to_rgb(hue, sat, np.ones_like(hue))


def preview_panel(image12: np.ndarray, *, white: float | None = None, dolp_max: float = 0.5) -> np.ndarray:
    """Intensity | DoLP | AoP side by side, ``(H, 3W + 2*gap, 3)`` float in [0, 1]."""
    inten = intensity_image(image12, white=white)
    dl = dolp_image(image12, dolp_max=dolp_max)
    ao = aop_image(image12, dolp_max=dolp_max)
    gap = np.ones((inten.shape[0], 4, 3))
    return np.concatenate([inten, gap, dl, gap, ao], axis=1)


def write_previews(image12: np.ndarray, out_dir, *, prefix: str = "", white: float | None = None,
                   dolp_max: float = 0.5) -> dict[str, Path]:
    """Write ``intensity.png``, ``dolp.png``, ``aop.png`` and ``panel.png`` (with ``prefix``)."""

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
    write_png(paths["panel"], preview_panel(image12, white=white, dolp_max=dolp_max))
    return paths
