"""The fixed conventions every part of capssim agrees on (docs: guides/captures.md, "Conventions").

* 12-channel order: ``c = 3*p + k`` with p over polarizer angles (0, 45, 90, 135) deg
  and k over colours (R, G, B). Arrays are ``(12, H, W)``.
* 16 low-resolution images: ``m = 4*n + q`` with n the aperture (polarizer ``45*n`` deg)
  and q over Bayer sites (R, G1, G2, B) at raw offsets (0,0), (0,1), (1,0), (1,1) (row, col).
* Grids: ground truth / HR is ``2H x 2W``, each raw sensor ``H x W``, each Bayer
  sub-image ``H/2 x W/2``. Reference raw pixel (i, j) integrates HR pixels
  ``2i..2i+1, 2j..2j+1``. Pixel centres are on integers.
* Homographies act on ``(x=col, y=row, 1)`` column vectors, as OpenCV does.
"""

from __future__ import annotations

import numpy as np

from capssim.errors import InputError

POLARIZER_ANGLES_DEG: tuple[int, ...] = (0, 45, 90, 135)
COLOURS: tuple[str, ...] = ("R", "G", "B")
N_CHANNELS = 12
N_APERTURES = 4
N_LR_IMAGES = 16
SR_FACTOR = 2

BAYER_SITES: tuple[str, ...] = ("R", "G1", "G2", "B")
#: raw (row, col) offset of each Bayer site inside the 2x2 RGGB cell
BAYER_OFFSETS: tuple[tuple[int, int], ...] = ((0, 0), (0, 1), (1, 0), (1, 1))
#: colour index k (R=0, G=1, B=2) of each Bayer site
BAYER_SITE_COLOUR: tuple[int, ...] = (0, 1, 1, 2)
#: RGGB colour index at raw (row % 2, col % 2)
BAYER_RGGB = ((0, 1), (1, 2))

#: the Bayer patterns a capture's ``meta.json["cfa"]`` may name: the colour index of the 2x2 cell's sites
#: at raw (0, 0), (0, 1), (1, 0), (1, 1) (the order of :data:`BAYER_OFFSETS`)
CFA_PATTERNS: dict[str, tuple[int, int, int, int]] = {
    "RGGB": (0, 1, 1, 2), "BGGR": (2, 1, 1, 0), "GRBG": (1, 0, 2, 1), "GBRG": (1, 2, 0, 1)}
#: the axes ``(rows, cols)`` to reverse so that a frame of even size with this pattern reads as RGGB
#: (an involution: reversing them again restores the frame; the 4x4 DoFP quad Bayer alike)
CFA_FLIPS: dict[str, tuple[bool, bool]] = {
    "RGGB": (False, False), "BGGR": (True, True), "GRBG": (False, True), "GBRG": (True, False)}

DOFP_LAYOUTS: dict[str, tuple[tuple[int, int], tuple[int, int]]] = {
    "sony": ((90, 45), (135, 0)),
    "0-45-135-90": ((0, 45), (135, 90)),
}
#: the DoFP 2x2 polarizer cell of a camera that names none: the Sony IMX250MYR's (the camera set-up's default)
DEFAULT_DOFP_LAYOUT = "sony"


def channel_index(angle_deg: int, colour: int | str) -> int:
    """12-channel index of (polarizer angle in degrees, colour 'R'/'G'/'B' or 0..2)."""
    k = COLOURS.index(colour) if isinstance(colour, str) else int(colour)
    return 3 * POLARIZER_ANGLES_DEG.index(int(angle_deg)) + k


def channel_name(c: int) -> str:
    """Human name of channel c, e.g. ``'0-R'``, ``'135-B'``."""
    return f"{POLARIZER_ANGLES_DEG[c // 3]}-{COLOURS[c % 3]}"


CHANNEL_NAMES: tuple[str, ...] = tuple(channel_name(c) for c in range(N_CHANNELS))


def lr_image_channel(m: int) -> int:
    """12-channel index observed by low-resolution image ``m = 4*n + q``."""
    n, q = divmod(m, 4)
    return 3 * n + BAYER_SITE_COLOUR[q]


LR_IMAGE_CHANNELS: tuple[int, ...] = tuple(lr_image_channel(m) for m in range(N_LR_IMAGES))


def cfa_pattern(cfa: str = "RGGB") -> str:
    """The Bayer pattern ``cfa`` (one of :data:`CFA_PATTERNS`, any case) in capitals; InputError otherwise."""
    key = cfa.strip().upper() if isinstance(cfa, str) else cfa
    if key not in CFA_PATTERNS:
        raise InputError("cfa", repr(cfa), f"one of {', '.join(CFA_PATTERNS)} (the colour of raw pixels (0,0), "
                         "(0,1), (1,0), (1,1))")
    return key


def lr_image_channels(cfa: str = "RGGB") -> tuple[int, ...]:
    """The 12-channel index seen by each of the 16 low-resolution images ``m = 4*n + q`` under ``cfa``
    (RGGB: :data:`LR_IMAGE_CHANNELS`); the sites' positions, hence their homographies, do not change."""
    colours = CFA_PATTERNS[cfa_pattern(cfa)]
    return tuple(3 * (m // 4) + colours[m % 4] for m in range(N_LR_IMAGES))


def flip_to_rggb(array, cfa: str = "RGGB"):
    """``(..., H, W)`` frames of pattern ``cfa`` (H, W even) -> the same frames with rows and/or columns
    reversed so that they read as RGGB (RGGB: the array itself). Applying it twice restores the array,
    so it also maps a result computed on the flipped frames back onto the original pixel grid."""
    flip_rows, flip_cols = CFA_FLIPS[cfa_pattern(cfa)]
    axes = tuple(a for a, f in ((-2, flip_rows), (-1, flip_cols)) if f)
    if not axes:
        return array
    return np.ascontiguousarray(np.flip(array, axis=axes))


def mirror_layout(layout, cfa: str = "RGGB") -> tuple[tuple[int, int], tuple[int, int]]:
    """The DoFP 2x2 polarizer cell as seen after :func:`flip_to_rggb` of a mosaic of pattern ``cfa``."""
    cell = np.asarray(dofp_layout(layout))
    flip_rows, flip_cols = CFA_FLIPS[cfa_pattern(cfa)]
    cell = cell[::-1] if flip_rows else cell
    cell = cell[:, ::-1] if flip_cols else cell
    return (int(cell[0, 0]), int(cell[0, 1])), (int(cell[1, 0]), int(cell[1, 1]))


def lr_image_name(m: int) -> str:
    n, q = divmod(m, 4)
    return f"{POLARIZER_ANGLES_DEG[n]}-{BAYER_SITES[q]}"


def dofp_layout(layout: str | tuple | list) -> tuple[tuple[int, int], tuple[int, int]]:
    """Resolve a DoFP 2x2 polarizer layout given by name or as ``[[a, b], [c, d]]`` degrees."""
    if isinstance(layout, str):
        key = layout.strip().lower()
        if key in DOFP_LAYOUTS:
            return DOFP_LAYOUTS[key]
        parts = key.replace("_", "-").split("-")
        try:
            values = [int(p) for p in parts]
        except ValueError:
            values = []
        if len(values) == 4:
            layout = [values[:2], values[2:]]
        else:
            raise InputError(
                "dofp_layout", repr(layout),
                f"one of {sorted(DOFP_LAYOUTS)} or four angles like '90-45-135-0' (row-major 2x2 cell)",
            )
    try:
        arr = np.asarray(layout, dtype=np.float64)
    except (TypeError, ValueError):  # ragged lists, nulls, strings
        arr = np.zeros(0)
    if arr.shape != (2, 2) or sorted(arr.ravel().tolist()) != sorted(POLARIZER_ANGLES_DEG):
        raise InputError(
            "dofp_layout", repr(layout),
            "a 2x2 cell holding each of 0, 45, 90, 135 degrees once",
        )
    return (int(arr[0, 0]), int(arr[0, 1])), (int(arr[1, 0]), int(arr[1, 1]))


def dofp_layout_name(layout) -> str:
    cell = dofp_layout(layout)
    for name, known in DOFP_LAYOUTS.items():
        if known == cell:
            return name
    return "-".join(str(v) for row in cell for v in row)


def dofp_channel_map(height: int, width: int, layout=DEFAULT_DOFP_LAYOUT) -> np.ndarray:
    """12-channel index sampled at each DoFP pixel, shape ``(height, width)``, int64.

    Polarizer angle follows the 2x2 ``layout`` cell; colour is a quad Bayer RGGB over
    2x2 cells (4x4 period), as on the Sony IMX250MYR.
    """
    cell = dofp_layout(layout)
    rows = np.arange(height)[:, None]
    cols = np.arange(width)[None, :]
    angle = np.asarray(cell)[rows % 2, cols % 2]
    colour = np.asarray(BAYER_RGGB)[(rows // 2) % 2, (cols // 2) % 2]
    p = np.searchsorted(np.asarray(POLARIZER_ANGLES_DEG), angle)
    return (3 * p + colour).astype(np.int64)


def bayer_channel_map(height: int, width: int) -> np.ndarray:
    """Colour index (0=R, 1=G, 2=B) at each RGGB raw pixel, shape ``(height, width)``."""
    rows = np.arange(height)[:, None]
    cols = np.arange(width)[None, :]
    return np.asarray(BAYER_RGGB)[rows % 2, cols % 2].astype(np.int64)


def split_bayer(raw, *, argument: str = "raw") -> np.ndarray:
    """``(4, H, W)`` RGGB frames -> ``(16, H/2, W/2)``: image ``4n + q`` is site q of frame n."""
    arr = np.asarray(raw)
    if arr.ndim != 3 or arr.shape[0] != N_APERTURES:
        raise InputError(argument, f"shape {arr.shape}", "(4, H, W): one RGGB raw frame per polarizer angle")
    n, h, w = arr.shape
    if h % 2 or w % 2 or h < 2 or w < 2:
        raise InputError(argument, f"frames of {h}x{w}", "even height and width (whole RGGB cells)")
    return np.ascontiguousarray(arr.reshape(n, h // 2, 2, w // 2, 2).transpose(0, 2, 4, 1, 3).reshape(N_LR_IMAGES, h // 2, w // 2))
