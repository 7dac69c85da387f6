"""Synthetic 12-channel ground truths for benchmarks that must run without data or rendering.

All are physically consistent (``S0 >= sqrt(S1^2 + S2^2)``), built from Stokes images
through Malus's law, on [0, 1], with HR pixel integration (box, supersampled) so that they
are valid "HR pixel" ground truths for :func:`capssim.simulate.simulate_capture`.

* ``texture``: smooth random colour texture with a weakly polarized background and a few
  sharp-edged, strongly polarized discs and rectangles (edges, DoLP and AoP steps).
* ``star``: sinusoidal Siemens star in intensity (``cycles`` periods per turn), partially
  polarized (DoLP 0.3 at 30 deg), slightly coloured.
* ``polarization-star``: flat S0, DoLP 0.8, AoP = (N/2) phi: every analyzer channel is a
  full sinusoidal star while the intensity is flat (RENDERING-NOTES "polarization Siemens
  star").

Star scenes return their geometry (``cycles``, ``center_rowcol``, ``radius_px`` in HR pixels)
for ``meta["scene"]["star"]``.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from capssim.errors import UnknownNameError
from capssim.stokes.polarization import twelve_from_stokes

from .star import sinusoidal_star

GENERATORS = ("texture", "star", "polarization-star")


def _box_supersampled(field_fn, size: int, factor: int = 4) -> np.ndarray:
    """Evaluate ``field_fn(rows, cols)`` on a fine grid and average it over each HR pixel."""
    fine = (np.arange(size * factor) + 0.5) / factor - 0.5
    rr, cc = np.meshgrid(fine, fine, indexing="ij")
    vals = field_fn(rr, cc)
    return vals.reshape(*vals.shape[:-2], size, factor, size, factor).mean(axis=(-3, -1))


def texture_scene(size: int = 128, *, seed: int = 0) -> tuple[np.ndarray, dict]:
    """Smooth random colour texture with sharp, strongly polarized objects (module docstring).

    Parameters
    ----------
    size : int
        Side of the square image, HR pixels.
    seed : int
        Seed of the texture and of the objects' places, colours, DoLP and AoP.

    Returns
    -------
    gt : numpy.ndarray
        ``(12, size, size)`` float32 on [0, 1], channel ``c = 3 p + k`` (polarizer ``45 p`` deg, colour k).
    scene_meta : dict
        ``{"generator": "texture", "seed": seed}``, for ``meta.json["scene"]``.
    """
    rng = np.random.default_rng(seed)

    def smooth(sigma, n=1):
        f = np.stack([gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap") for _ in range(n)])
        return f / (f.std(axis=(1, 2), keepdims=True) + 1e-12)

    # multi-scale texture: coloured low frequencies, grey mid and fine detail
    s0 = 0.8 + 0.18 * smooth(size / 10, 3) + 0.12 * smooth(3.0) + 0.05 * smooth(1.2)
    dolp = np.clip(0.08 + 0.05 * smooth(size / 12)[0], 0.0, 0.3)
    aop = np.pi * (0.5 + 0.25 * smooth(size / 8)[0])
    # sharp-edged polarized objects on a jittered 3x3 layout, and two grating patches
    cells = [(i, j) for i in range(3) for j in range(3)]
    order = rng.permutation(len(cells))
    step = size / 3
    for n_obj, idx in enumerate(order[:7]):
        i, j = cells[idx]
        cy, cx = (np.array([i, j]) + 0.5 + rng.uniform(-0.15, 0.15, 2)) * step
        extent = rng.uniform(0.22, 0.34) * step
        if n_obj < 2:  # grating patch: sinusoid at 0.08..0.3 cycles/HR px, random orientation
            freq, theta = rng.uniform(0.08, 0.3), rng.uniform(0, np.pi)
            inside = _box_supersampled(lambda r, c: ((np.abs(r - cy) <= extent) & (np.abs(c - cx) <= extent))
                                       .astype(float), size)
            grating = _box_supersampled(lambda r, c: np.cos(2 * np.pi * freq * ((c - cx) * np.cos(theta)
                                                                                + (r - cy) * np.sin(theta))), size)
            s0 = s0 * (1 - inside) + inside * (0.9 + 0.6 * grating)[None]
            continue
        if n_obj % 2:
            inside = _box_supersampled(lambda r, c: ((r - cy) ** 2 + (c - cx) ** 2 <= extent ** 2).astype(float), size)
        else:
            inside = _box_supersampled(lambda r, c: ((np.abs(r - cy) <= extent) & (np.abs(c - cx) <= 0.6 * extent))
                                       .astype(float), size)
        colour = rng.uniform(0.25, 1.0, 3)
        s0 = s0 * (1 - inside) + inside * (colour[:, None, None] * 1.1)
        dolp = dolp * (1 - inside) + inside * rng.uniform(0.3, 0.7)
        aop = aop * (1 - inside) + inside * rng.uniform(0, np.pi)
    s0 = np.clip(s0, 0.05, 1.5)
    stokes = np.stack([s0, s0 * dolp * np.cos(2 * aop), s0 * dolp * np.sin(2 * aop)])
    gt = twelve_from_stokes(stokes)
    return np.clip(gt, 0.0, 1.0).astype(np.float32), {"generator": "texture", "seed": seed}


def star_scene(size: int = 128, *, cycles: int = 36, polarization: bool = False) -> tuple[np.ndarray, dict]:
    """Sinusoidal Siemens star, in intensity or (``polarization``) in every analyzer channel (module docstring).

    Parameters
    ----------
    size : int
        Side of the square image, HR pixels; the star's radius is ``0.47 size``.
    cycles : int
        Periods per turn.
    polarization : bool
        False: intensity star, DoLP 0.3 at 30 deg; True: flat S0, DoLP 0.8, AoP ``(cycles/2) phi``.

    Returns
    -------
    gt : numpy.ndarray
        ``(12, size, size)`` float32 on [0, 1].
    scene_meta : dict
        ``generator`` and ``star``: ``cycles``, ``center_rowcol``, ``radius_px`` (HR pixels), ``contrast``.
    """
    centre = ((size - 1) / 2, (size - 1) / 2)
    radius = 0.47 * size
    cos_n = sinusoidal_star((size, size), cycles, center_rowcol=centre, radius=radius, mean=1.0, modulation=1.0,
                            pixel_box=1.0, supersample=5, background=1.0) - 1.0
    sin_n = sinusoidal_star((size, size), cycles, center_rowcol=centre, radius=radius, mean=1.0, modulation=1.0,
                            pixel_box=1.0, supersample=5, phase_rad=-np.pi / 2, background=1.0) - 1.0
    colour = np.array([0.9, 1.0, 0.8])[:, None, None]
    if polarization:
        s0 = 0.8 * colour * np.ones((1, size, size))
        d = 0.8
        stokes = np.stack([s0, s0 * d * cos_n[None], s0 * d * sin_n[None]])
    else:
        s0 = 0.7 * colour * (1.0 + 0.9 * cos_n[None])
        d, a = 0.3, np.deg2rad(30.0)
        stokes = np.stack([s0, s0 * d * np.cos(2 * a), s0 * d * np.sin(2 * a)])
    gt = twelve_from_stokes(stokes)
    star = {"cycles": int(cycles), "center_rowcol": [float(centre[0]), float(centre[1])], "radius_px": float(radius),
            "contrast": 0.8 if polarization else 0.9}  # the modulation of every channel
    return np.clip(gt, 0.0, 1.0).astype(np.float32), {"generator": "polarization-star" if polarization else "star",
                                                      "star": star}


def synthetic_scene(generator: str, *, size: int = 128, seed: int = 0, cycles: int = 36) -> tuple[np.ndarray, dict]:
    """``(gt12, scene_meta)`` of a named generator (module docstring)."""
    if generator == "texture":
        return texture_scene(size, seed=seed)
    if generator == "star":
        return star_scene(size, cycles=cycles)
    if generator == "polarization-star":
        return star_scene(size, cycles=cycles, polarization=True)
    raise UnknownNameError("synthetic scene generator", generator, list(GENERATORS))
