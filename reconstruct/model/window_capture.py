"""A window's capture: the raw pixels of each aperture that see a window of the HR reference grid, with warps
re-based to it (a tile of a full frame, :mod:`capssim.reconstruct.tiles`; the central window ``caps-plus``
validates its iteration count on).

Aperture ``n`` sees the window where its homography ``H_n`` (HR reference -> aperture-HR) takes it. Its
crop is the window's size, centred on ``H_n`` of the window's centre, rounded to whole RGGB cells (4
aperture-HR = 2 raw pixels, so the Bayer sites stay), and kept inside the raw frame. The crop's warps
are ``T(-o_n) @ H_n @ T(w)`` with ``w`` the window's corner and ``o_n`` the crop's corner, both in HR
pixels: the same warps as the whole frame's, seen from the crop (the reference aperture stays ``I``).
"""

from __future__ import annotations

import copy

import numpy as np

from capssim.camera.array_geometry import ArrayGeometry
from capssim.captures.capture import Capture
from capssim.conventions import N_APERTURES

__all__ = ["WINDOW_ALIGN", "aperture_offsets", "crop_window", "translation"]

#: a window's corner and size are multiples of this many HR pixels: one RGGB cell of every aperture (4 HR = 2 raw)
WINDOW_ALIGN = 4


def translation(dx: float, dy: float) -> np.ndarray:
    """``(3, 3)`` homography adding ``(dx, dy)`` to ``(x=col, y=row)``."""
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def aperture_offsets(aperture_homographies: np.ndarray, window, hr_shape) -> np.ndarray:
    """``(4, 2)`` int crop corners ``(top, left)`` in aperture-HR pixels (multiples of 4) of a window.

    ``window`` is ``(top, left, bottom, right)`` on the HR reference grid; each crop has the window's size
    and lies inside the ``hr_shape`` aperture-HR frame.
    """
    top, left, bottom, right = window
    rows, cols = bottom - top, right - left
    centre = np.array([(left + right - 1) / 2.0, (top + bottom - 1) / 2.0, 1.0])
    out = np.zeros((N_APERTURES, 2), dtype=np.int64)
    for n, hom in enumerate(np.asarray(aperture_homographies, dtype=np.float64)):
        p = hom @ centre
        x, y = p[0] / p[2], p[1] / p[2]
        oy = WINDOW_ALIGN * round((y - (rows - 1) / 2.0) / WINDOW_ALIGN)
        ox = WINDOW_ALIGN * round((x - (cols - 1) / 2.0) / WINDOW_ALIGN)
        out[n] = (min(max(0, oy), hr_shape[0] - rows), min(max(0, ox), hr_shape[1] - cols))
    return out


def crop_window(capture: Capture, window, aperture_homographies: np.ndarray, *, name: str = "window") -> Capture:
    """The capture of ``window``: raw crops ``(4, rows/2, cols/2)`` and re-based warps.

    Parameters
    ----------
    capture : Capture
        The whole frame (CAPS raw ``(4, H, W)``).
    window : tuple
        ``(top, left, bottom, right)`` on the HR reference grid (bottom/right exclusive); its corner and size are
        multiples of :data:`WINDOW_ALIGN` HR pixels.
    aperture_homographies : numpy.ndarray
        ``(4, 3, 3)`` the whole frame's warps to reconstruct with (stored or registered once).

    Returns
    -------
    Capture
        A capture of the window's HR size whose stored warps are the re-based ones (reconstruct it with
        ``true_warps=True``), without ground truth, DoFP frame, rig or calibration file.
    """
    window = tuple(int(v) for v in window)
    top, left, bottom, right = window
    rows, cols = bottom - top, right - left
    hr_shape = capture.hr_shape
    offsets = aperture_offsets(aperture_homographies, window, hr_shape)
    raw = np.stack([capture.caps_raw[n, oy // 2: oy // 2 + rows // 2, ox // 2: ox // 2 + cols // 2]
                    for n, (oy, ox) in enumerate(offsets)])
    homs = np.stack([translation(-ox, -oy) @ h @ translation(left, top)
                     for (oy, ox), h in zip(offsets, np.asarray(aperture_homographies, dtype=np.float64))])
    geometry = ArrayGeometry(homs, (rows, cols))
    meta = copy.deepcopy(capture.meta)
    meta["geometry"].update({"hr_height": rows, "hr_width": cols, "raw_height": rows // 2, "raw_width": cols // 2,
                             "sub_height": rows // 4, "sub_width": cols // 4})
    stored = geometry.to_meta()
    meta["aperture_homographies"] = stored["aperture_homographies"]
    for entry, hom in zip(meta.get("lr_images", []), stored["lr_homographies"]):
        entry["homography"] = hom
    for key in ("rig", "calibration_file"):
        meta.pop(key, None)
    meta["files"] = {k: v for k, v in meta.get("files", {}).items() if k == "caps_raw"}
    meta["tile"] = {"name": name, "window": list(window), "aperture_offsets_hr": offsets.tolist()}
    return Capture(meta=meta, caps_raw=np.ascontiguousarray(raw), dofp_raw=None, gt=None, path=None)
