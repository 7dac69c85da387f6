"""Aperture homographies from a planar textured target.

Reference: the paper's registration step (section 3.1) run on a target chosen for it: a planar
card textured at every scale, at the working distance, so every aperture sees the same plane.
The 16 Bayer sub-images are flat-field corrected (gain and vignetting divided out) and
registered with :func:`capssim.reconstruct.registration.estimate_lr_homographies`; the aperture
homographies map HR reference pixels to each aperture's HR grid (docs/architecture.md, "The camera, its grids and its channels").
"""

from __future__ import annotations

import numpy as np

from capssim.camera.array_geometry import ArrayGeometry
from capssim.conventions import split_bayer
from capssim.reconstruct.registration import estimate_lr_homographies
from capssim.runtime.threads import small_tensor_threads


def fit_geometry(raw: np.ndarray, saturated: np.ndarray, flat: np.ndarray | None, hr_shape) -> tuple[ArrayGeometry, dict]:
    """The array geometry of a target capture: ``raw`` ``(4, H, W)`` float, ``saturated`` bool, ``flat`` ``(4, H, W)``."""
    corrected = raw / flat if flat is not None else raw
    images = split_bayer(corrected).reshape(16, raw.shape[1] // 2, raw.shape[2] // 2)
    masks = split_bayer(saturated).reshape(16, raw.shape[1] // 2, raw.shape[2] // 2)
    with small_tensor_threads():
        result = estimate_lr_homographies(images.astype(np.float32), hr_shape=tuple(hr_shape), saturated=masks)
    geometry = ArrayGeometry(np.asarray(result.aperture_homographies, dtype=np.float64), tuple(hr_shape))
    return geometry, {"warnings": list(result.diagnostics.get("warnings", [])),
                      "time_s": result.diagnostics.get("time_s")}


__all__ = ["fit_geometry"]
