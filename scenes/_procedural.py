"""Deterministic procedural textures for the 3-D scenes (numpy; no data files)."""

from __future__ import annotations

import numpy as np


def fractal_noise(shape: tuple[int, int], *, seed: int, octaves: int = 6, base_cells: int = 4,
                  persistence: float = 0.55) -> np.ndarray:
    """Smooth fractal (1/f-like) noise in [0, 1], ``shape`` (rows, cols), periodic in both axes
    (no seam where an environment map wraps round); the same seed gives the same texture."""
    from scipy.ndimage import zoom

    rng = np.random.default_rng(seed)
    h, w = shape
    out = np.zeros(shape)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = base_cells * 2 ** o
        ch = max(2, int(round(cells * h / max(h, w))))
        cw = max(2, int(round(cells * w / max(h, w))))
        grid = rng.standard_normal((ch, cw))
        up = zoom(grid, (h / ch, w / cw), order=3, mode="grid-wrap", grid_mode=True)
        out += amp * up[:h, :w]
        total += amp
        amp *= persistence
    out /= total
    lo, hi = np.percentile(out, [0.5, 99.5])
    return np.clip((out - lo) / (hi - lo), 0.0, 1.0)


def sky_envmap(*, width: int = 1024, seed: int = 3, cloud_cover: float = 0.45, brightness: float = 1.0) -> np.ndarray:
    """Equirectangular sky ``(width/2, width, 3)`` float32, linear RGB, +Y (top row) is the zenith.

    Blue gradient (deeper blue at the zenith, pale at the horizon), fractal cumulus clouds,
    dark ground below the horizon.
    """
    h = width // 2
    elev = (0.5 - (np.arange(h) + 0.5) / h) * np.pi  # +pi/2 at the top row
    t = np.clip(np.sin(elev), 0.0, 1.0)[:, None, None] ** 0.6
    horizon = np.array([0.80, 0.88, 1.00])
    zenith = np.array([0.18, 0.34, 0.80])
    sky = (1 - t) * horizon + t * zenith
    noise = fractal_noise((h, width), seed=seed, octaves=7, base_cells=6)
    clouds = np.clip((noise - (1.0 - cloud_cover)) / 0.18, 0.0, 1.0)[..., None]
    shade = 0.75 + 0.35 * fractal_noise((h, width), seed=seed + 1, octaves=5, base_cells=12)[..., None]
    sky = sky * (1 - clouds) + clouds * shade * np.array([1.05, 1.05, 1.05])
    ground = np.array([0.06, 0.07, 0.05])
    below = (elev < 0)[:, None, None]
    env = np.where(below, ground, sky) * brightness
    return np.ascontiguousarray(env, dtype=np.float32)


def sand_texture(size: int = 512, *, seed: int = 5) -> np.ndarray:
    """``(size, size, 3)`` reflectance in [0, 1]: dark greenish-brown lake bed with ripples of light."""
    n = fractal_noise((size, size), seed=seed, octaves=7, base_cells=6)
    rip = fractal_noise((size, size), seed=seed + 7, octaves=4, base_cells=20)
    v = 0.6 * n + 0.4 * rip
    lo, hi = np.array([0.05, 0.06, 0.03]), np.array([0.30, 0.27, 0.16])
    return np.ascontiguousarray(lo + v[..., None] * (hi - lo), dtype=np.float32)


def poster_texture(size: int = 512, *, seed: int = 11) -> np.ndarray:
    """``(size, size, 3)`` colourful natural-like texture in [0, 1] (three fractal colour layers)."""
    layers = [fractal_noise((size, size), seed=seed + k, octaves=7, base_cells=5) for k in range(3)]
    rgb = np.stack(layers, axis=-1)
    return np.ascontiguousarray(0.05 + 0.9 * rgb ** 1.5, dtype=np.float32)
