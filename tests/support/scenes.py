"""Scene and ground-truth builders shared by the tests.

Tests receive them as fixtures of the same name (tests/conftest.py); a test file's own helper that needs
one becomes a factory fixture (tests/test_test_hygiene.py checks that no test imports this module).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def smooth_random_scene(size: int = 64, *, seed: int = 0, dolp_max: float = 0.6) -> np.ndarray:
    """A ``(12, size, size)`` physically consistent scene (S0 >= |S1,S2|) with smooth texture."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    s0 = np.stack([gaussian_filter(rng.random((size, size)), 2.0) for _ in range(3)])
    s0 = 0.2 + 0.6 * (s0 - s0.min()) / (np.ptp(s0) + 1e-12)
    d = dolp_max * gaussian_filter(rng.random((size, size)), 4.0)
    d = d / max(d.max(), 1e-12) * dolp_max
    a = np.pi * gaussian_filter(rng.random((size, size)), 4.0) * 2
    s1 = s0 * d * np.cos(2 * a)
    s2 = s0 * d * np.sin(2 * a)
    from capssim.stokes.polarization import twelve_from_stokes

    return twelve_from_stokes(np.stack([s0, s1, s2])).astype(np.float32)


def write_png_gt(folder: Path, scene: np.ndarray) -> Path:
    """``scene`` ``(12, H, W)`` on [0, 1] as a ground-truth folder ``0.png 45.png 90.png 135.png`` (8-bit RGB)."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    for p, angle in enumerate((0, 45, 90, 135)):
        rgb = np.round(np.clip(scene[3 * p:3 * p + 3], 0, 1) * 255).astype(np.uint8).transpose(1, 2, 0)
        cv2.imwrite(str(folder / f"{angle}.png"), rgb[..., ::-1])
    return folder


def write_gt_folder(folder: Path, size: int = 32, seed: int = 0) -> Path:
    """A ``size`` px smooth random scene (:func:`smooth_random_scene` of ``seed``) as a PNG ground-truth folder."""
    return write_png_gt(folder, smooth_random_scene(size, seed=seed))


def natural_scene() -> np.ndarray:
    """A 64 px crop of skimage's astronaut (linearized) under smooth AoP/DoLP ramps, ``(12, 64, 64)``:
    natural colour texture that no training set of the shipped models holds."""
    import skimage.data

    img = (skimage.data.astronaut()[100:164, 180:244].astype(np.float64) / 255) ** 2.2
    yy, xx = np.mgrid[0:64, 0:64] / 64
    aop, dolp = np.pi * (0.3 + 0.5 * xx), 0.2 + 0.4 * yy
    return np.stack([0.5 * img[..., k] * (1 + dolp * np.cos(2 * (a - aop)))
                     for a in np.deg2rad([0, 45, 90, 135]) for k in range(3)])
