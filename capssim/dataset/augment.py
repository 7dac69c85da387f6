"""Augmentations of 12-channel ground truth that keep the polarization physics right.

Turning or mirroring an image also turns or mirrors the polarization directions in it, so the
four analyzer images must be permuted, not just moved:

* ``rot90`` k quarter turns counter-clockwise on the display (``numpy.rot90`` on (row, col)):
  a direction at image angle b becomes b + 90k, so the new image behind an analyzer at angle a
  is the turned old image behind a - 90k: analyzer index p <- (p - 2k) mod 4.
* ``flip`` mirrors left-right (col -> W-1-col): angle a becomes -a (mod 180), so
  p <- (-p) mod 4 (0 and 90 stay, 45 and 135 swap).

Flip is applied first, then the turn. Angles follow the project convention (0 deg = +col,
positive towards -row).

* ``gain_red``, ``gain_blue`` and ``exposure`` (:func:`scale_colours`) multiply the red and the blue
  channels of all four analyzers (another illuminant or white balance), then the whole image (another
  exposure). Stokes parameters are linear in intensity, so every analyzer relation (``I0 + I90 = I45 +
  I135``, DoLP, AoP) still holds; the exposure is capped so that no value exceeds 1 (nothing clipped).
"""

from __future__ import annotations

import numpy as np

from capssim.conventions import N_CHANNELS
from capssim.errors import InputError


def _permute_angles(image12: np.ndarray, source_index) -> np.ndarray:
    """New analyzer p takes old analyzer ``source_index(p)`` (all 3 colours)."""
    channels = [3 * source_index(p) + k for p in range(4) for k in range(3)]
    return image12[channels]


def rotate_flip_twelve(image12: np.ndarray, *, rot90: int = 0, flip: bool = False) -> np.ndarray:
    """Mirror (``flip``) then turn by ``rot90`` quarter turns a ``(12, H, W)`` image, permuting
    its analyzer channels so the result is the image of the mirrored/turned scene.

    Returns a new contiguous array ``(12, H, W)`` (``(12, W, H)`` for odd ``rot90``).
    """
    image12 = np.asarray(image12)
    if image12.ndim != 3 or image12.shape[0] != N_CHANNELS:
        raise InputError("image12", f"shape {image12.shape}", "a (12, H, W) array")
    if int(rot90) != rot90 or not 0 <= rot90 <= 3:
        raise InputError("rot90", rot90, "an integer 0..3 (quarter turns counter-clockwise)")
    out = image12
    if flip:
        out = _permute_angles(out[:, :, ::-1], lambda p: (-p) % 4)
    k = int(rot90)
    if k:
        out = _permute_angles(np.rot90(out, k, axes=(1, 2)), lambda p: (p - 2 * k) % 4)
    return np.ascontiguousarray(out)


def scale_colours(image12: np.ndarray, *, gain_red: float = 1.0, gain_blue: float = 1.0,
                  exposure: float = 1.0) -> tuple[np.ndarray, float]:
    """Multiply the red and blue channels (``c = 3 p + k``, ``k`` 0 and 2) of a ``(12, H, W)`` image by
    ``gain_red`` and ``gain_blue``, then the whole image by ``exposure``, capped at ``1 / max`` so that the
    brightest value stays at most 1. Returns the new float32 image and the exposure applied."""
    image12 = np.asarray(image12)
    if image12.ndim != 3 or image12.shape[0] != N_CHANNELS:
        raise InputError("image12", f"shape {image12.shape}", "a (12, H, W) array")
    for name, value in (("gain_red", gain_red), ("gain_blue", gain_blue), ("exposure", exposure)):
        if not np.isfinite(value) or value <= 0:
            raise InputError(name, value, "a finite number > 0")
    gains = np.tile(np.array([gain_red, 1.0, gain_blue], dtype=np.float64), 4)[:, None, None]
    out = image12.astype(np.float64) * gains
    peak = float(out.max()) if out.size else 0.0
    applied = min(float(exposure), 1.0 / peak) if peak > 0 else float(exposure)
    return (out * applied).astype(np.float32), applied
