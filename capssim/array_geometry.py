"""The camera array's geometry: four aperture homographies, and everything derived from them.

Frames (all matrices act on ``(x=col, y=row, 1)``, pixel centres on integers; docs/architecture.md, "The camera, its grids and its channels"):

* HR reference: the ground-truth grid ``2H x 2W`` (the 0 deg aperture at twice its resolution).
* aperture-HR: aperture n's own grid at twice its resolution; its raw pixel ``(i, j)``
  integrates aperture-HR pixels ``2i..2i+1, 2j..2j+1``. ``H_n`` maps HR reference -> aperture-HR;
  the reference aperture has ``H_0 = I`` by definition.
* sub-image: Bayer site q of aperture n, ``H/2 x W/2``. Sub-image pixel ``(u, v)`` is raw pixel
  ``(2u + oy, 2v + ox)``, centred at aperture-HR ``(4u + 2oy + 0.5, 4v + 2ox + 0.5)``.

:class:`ArrayGeometry` holds the four ``H_n`` once. The 16 sub-image homographies of the paper's
rearrangement (section 3.1), ``H_{4n+q} = S_q @ H_n`` for ``m = 4n + q``, are derived here and
nowhere else (:func:`lr_homographies`); ``meta.json`` stores both, and
:meth:`ArrayGeometry.from_meta` refuses a file whose 16 disagree with its 4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from capssim.conventions import BAYER_OFFSETS, N_APERTURES, N_LR_IMAGES
from capssim.errors import CaptureFormatError, InputError

#: largest difference (in target pixels, over the HR frame's corners) tolerated between a stored
#: sub-image homography and the one derived from its aperture's homography
STORED_LR_TOLERANCE_PX = 1e-6


def sub_image_matrix(q: int) -> np.ndarray:
    """``S_q`` ``(3, 3)``: aperture-HR coordinates -> Bayer sub-image q pixel coordinates."""
    oy, ox = BAYER_OFFSETS[q]
    return np.array([[0.25, 0.0, -(2 * ox + 0.5) / 4], [0.0, 0.25, -(2 * oy + 0.5) / 4], [0.0, 0.0, 1.0]])


def raw_matrix() -> np.ndarray:
    """``R`` ``(3, 3)``: aperture-HR coordinates -> raw pixel coordinates (raw pixel centres at ``2i + 0.5``)."""
    return np.array([[0.5, 0.0, -0.25], [0.0, 0.5, -0.25], [0.0, 0.0, 1.0]])


def lr_homographies(aperture_homographies) -> np.ndarray:
    """``(16, 3, 3)``: ``H_{4n+q} = S_q @ H_n`` from the four aperture homographies ``(4, 3, 3)``.

    The one derivation of the sub-image homographies (paper section 3.1, the 16 observations).
    """
    h = _check_stack(aperture_homographies, N_APERTURES, "aperture_homographies")
    return np.stack([sub_image_matrix(q) @ h[n] for n in range(N_APERTURES) for q in range(4)])


def _check_stack(homographies, count: int, argument: str) -> np.ndarray:
    h = np.asarray(homographies, dtype=np.float64)
    if h.shape != (count, 3, 3):
        raise InputError(argument, f"shape {h.shape}", f"shape ({count}, 3, 3)")
    if not np.all(np.isfinite(h)):
        raise InputError(argument, "non-finite values", "finite 3x3 matrices")
    return h


@dataclass(frozen=True, eq=False)
class ArrayGeometry:
    """The 2x2 array's warps on an HR reference grid.

    Derived views: :attr:`lr_homographies` (the 16 sub-image homographies), :attr:`lr_aperture_warps`
    (each sub-image's aperture warp), :attr:`raw_homographies` (HR reference -> raw pixel).

    Parameters
    ----------
    aperture_homographies : numpy.ndarray
        ``(4, 3, 3)`` HR reference -> aperture HR pixel (x=col, y=row); copied.
    hr_shape : tuple of int
        ``(2H, 2W)``, the HR reference grid in pixels.
    """

    aperture_homographies: np.ndarray
    hr_shape: tuple[int, int]

    def __post_init__(self):
        h = _check_stack(self.aperture_homographies, N_APERTURES, "aperture_homographies")
        object.__setattr__(self, "aperture_homographies", h.copy())  # its own copy: a value, never aliased
        object.__setattr__(self, "hr_shape", tuple(int(v) for v in self.hr_shape))

    @classmethod
    def identity(cls, hr_shape) -> "ArrayGeometry":
        """Four co-registered apertures (all ``H_n = I``)."""
        return cls(np.stack([np.eye(3)] * N_APERTURES), hr_shape)

    # derived views ---------------------------------------------------------------------
    @property
    def raw_shape(self) -> tuple[int, int]:
        """``(H, W)`` raw frame size."""
        return self.hr_shape[0] // 2, self.hr_shape[1] // 2

    @property
    def sub_shape(self) -> tuple[int, int]:
        """``(H/2, W/2)`` Bayer sub-image size."""
        return self.hr_shape[0] // 4, self.hr_shape[1] // 4

    @property
    def lr_homographies(self) -> np.ndarray:
        """``(16, 3, 3)`` HR reference -> sub-image ``m = 4n + q`` pixel (:func:`lr_homographies`)."""
        return lr_homographies(self.aperture_homographies)

    @property
    def lr_aperture_warps(self) -> np.ndarray:
        """``(16, 3, 3)``: sub-image m's aperture warp ``H_n`` (``n = m // 4``), HR reference -> aperture-HR."""
        return np.repeat(self.aperture_homographies, 4, axis=0)

    @property
    def raw_homographies(self) -> np.ndarray:
        """``(4, 3, 3)`` HR reference -> raw pixel of aperture n: ``R @ H_n``."""
        return np.stack([raw_matrix() @ h for h in self.aperture_homographies])

    def cropped(self, top: int, left: int, hr_shape) -> "ArrayGeometry":
        """The geometry of the HR window at (``top``, ``left``) of size ``hr_shape`` (HR pixels).

        Offsets must be multiples of 4 HR pixels (one Bayer cell of every aperture), so that each
        sub-image keeps its Bayer site; the crop's frames start at the window's corner.
        """
        if top % 4 or left % 4:
            raise InputError("crop offset", (top, left), "multiples of 4 HR pixels (one RGGB cell)")
        into = np.array([[1.0, 0.0, left], [0.0, 1.0, top], [0.0, 0.0, 1.0]])
        back = np.array([[1.0, 0.0, -left], [0.0, 1.0, -top], [0.0, 0.0, 1.0]])
        return ArrayGeometry(back @ self.aperture_homographies @ into, hr_shape)

    # capture format --------------------------------------------------------------------
    def to_meta(self) -> dict:
        """``meta.json`` entries: ``aperture_homographies`` and the 16 derived ``homography`` values."""
        return {"aperture_homographies": self.aperture_homographies.tolist(),
                "lr_homographies": [h.tolist() for h in self.lr_homographies]}

    @classmethod
    def from_meta(cls, meta: dict) -> "ArrayGeometry":
        """The geometry of a ``meta.json`` dict; refuses stored sub-image homographies that disagree
        with the ones derived from ``aperture_homographies`` (:class:`CaptureFormatError`)."""
        geo = meta["geometry"]
        try:
            geometry = cls(meta["aperture_homographies"], (geo["hr_height"], geo["hr_width"]))
        except InputError as exc:
            raise CaptureFormatError(f"meta.json aperture_homographies: {exc}") from None
        entries = meta.get("lr_images") or []
        if entries:
            stored = np.asarray([e.get("homography") for e in entries], dtype=np.float64)
            geometry.check_stored_lr(stored)
        return geometry

    def check_stored_lr(self, stored) -> None:
        """Raise :class:`CaptureFormatError` unless ``stored`` ``(16, 3, 3)`` equals :attr:`lr_homographies`
        to :data:`STORED_LR_TOLERANCE_PX` target pixels at the HR frame's corners."""
        stored = np.asarray(stored, dtype=np.float64)
        if stored.shape != (N_LR_IMAGES, 3, 3) or not np.all(np.isfinite(stored)):
            raise CaptureFormatError(f"meta.json lr_images: 16 finite 3x3 'homography' entries expected, got "
                                     f"shape {stored.shape}.")
        gap = self._corner_gap(stored)
        worst = int(np.argmax(gap))
        if gap[worst] > STORED_LR_TOLERANCE_PX:
            raise CaptureFormatError(
                f"meta.json: lr_images[{worst}].homography disagrees with the one derived from "
                f"aperture_homographies[{worst // 4}] by {gap[worst]:.3g} sub-image px (tolerance "
                f"{STORED_LR_TOLERANCE_PX:g}). The 16 sub-image homographies are S_q @ H_n of the 4 aperture "
                "homographies: fix aperture_homographies, then rewrite the 16 entries from them "
                "(capssim.capture.build_meta writes both).")

    def _corner_gap(self, stored: np.ndarray) -> np.ndarray:
        hh, ww = self.hr_shape
        corners = np.array([[0.0, 0.0, 1.0], [ww - 1.0, 0.0, 1.0], [0.0, hh - 1.0, 1.0], [ww - 1.0, hh - 1.0, 1.0]])
        a = np.einsum("mij,kj->mki", self.lr_homographies, corners)
        b = np.einsum("mij,kj->mki", stored, corners)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = a[..., :2] / a[..., 2:] - b[..., :2] / b[..., 2:]
        return np.nan_to_num(np.hypot(d[..., 0], d[..., 1]), nan=np.inf).max(axis=1)
