"""A tile's capture: the raw pixels of each aperture that see the tile's window, with warps re-based to it
(:func:`capssim.reconstruct.model.window_capture.crop_window` for a tile)."""

from __future__ import annotations

import numpy as np

from capssim.captures.capture import Capture

from ..model.window_capture import aperture_offsets, crop_window, translation
from .geometry import Tile

__all__ = ["aperture_offsets", "crop_capture", "translation"]


def crop_capture(capture: Capture, tile: Tile, aperture_homographies: np.ndarray) -> Capture:
    """The capture of ``tile``'s window (:func:`~capssim.reconstruct.model.window_capture.crop_window`), named
    after the tile; reconstruct it with ``true_warps=True``."""
    return crop_window(capture, tile.window, aperture_homographies, name=tile.name)
