"""A tile's margin and the checks of a tiling that need no data (docs: guides/limits.md, "Third round").

The margin around a tile's core holds what a pixel of the core depends on: the NLSTR block and search
window, the CAGF window, the PSF and the warp's reach (:func:`margin_parts`). :func:`check_tiling` refuses,
from ``meta.json`` alone (so before registration and before a Dask cluster starts): a margin option past its
range on the whole frame (named as the untiled run names it), a budget too small for ``workers`` tiles with
their margins, and a ``--tile`` narrower than its margin (naming the option that makes the margin).
:func:`choose_layout` picks the tiles once the warps are known.
"""

from __future__ import annotations

import math

import numpy as np

from capssim.camera.psf import PSF
from capssim.captures.capture import Capture
from capssim.errors import InputError
from capssim.runtime.resources import check_range

from .geometry import MIN_TILE, TILE_ALIGN, TileLayout, default_margin, plan_tiles, split_axis
from .memory import fits, memory_budget, tile_for_budget

__all__ = ["MARGIN_OPTIONS", "check_cores_hold_margin", "check_margin_options", "check_tiling", "choose_layout",
           "describe_margin", "margin_cause", "margin_parts", "tile_margin", "warp_reach"]


def warp_reach(aperture_homographies, hr_shape, side: int) -> int:
    """How far (HR pixels) a warp departs from a translation over a ``side`` window at the frame's centre."""
    cy, cx = (hr_shape[0] - 1) / 2.0, (hr_shape[1] - 1) / 2.0
    half = side / 2.0
    corners = np.array([[cx + sx * half, cy + sy * half, 1.0] for sx in (-1, 1) for sy in (-1, 1)])
    worst = 0.0
    for hom in np.asarray(aperture_homographies, dtype=np.float64):
        c = hom @ np.array([cx, cy, 1.0])
        p = corners @ hom.T
        moved = p[:, :2] / p[:, 2:] - c[:2] / c[2]
        worst = max(worst, float(np.max(np.abs(moved - (corners[:, :2] - [cx, cy])))))
    return int(math.ceil(worst)) + 4  # + the crop's rounding to whole RGGB cells (<= 2 px) and a safety pixel


#: the ``-p`` options that size a tile's margin (:func:`margin_parts`), and their defaults
MARGIN_OPTIONS = {"block": 8, "search_radius": 7, "cagf_radius": 4}


def _int_option(options: dict, name: str, default: int) -> int:
    value = options.get(name, options.get(name.replace("_", "-"), default))
    try:
        return int(float(value))
    except (TypeError, ValueError, OverflowError):  # not a number: the method refuses it when it parses it
        return default


def _psf_radius(capture: Capture, options: dict) -> int:
    """The PSF kernel's radius (HR pixels): ``-p psf_sigma`` when it replaces the capture's PSF, else the capture's."""
    try:
        sigma = float(options.get("psf_sigma", -1))
    except (TypeError, ValueError):
        sigma = -1.0
    if sigma >= 0 and math.isfinite(sigma):
        return PSF.gaussian(sigma).kernel_radius()
    return int(np.asarray(capture.psf_kernel()).shape[-1]) // 2


def margin_parts(capture: Capture, options: dict, *, aperture_homographies=None, side: int) -> dict:
    """What a ``side`` tile's margin is made of, HR pixels: ``block``, ``search_radius``, ``cagf_radius`` (4 HR px per
    LR px), ``psf_radius`` and ``warp_reach`` (0 before the warps are known: ``aperture_homographies`` None)."""
    return {"block": _int_option(options, "block", 8), "search_radius": _int_option(options, "search_radius", 7),
            "cagf_radius": _int_option(options, "cagf_radius", 4), "psf_radius": _psf_radius(capture, options),
            "warp_reach": 0 if aperture_homographies is None
            else warp_reach(aperture_homographies, capture.hr_shape, side)}


def describe_margin(parts: dict) -> str:
    """``block 8 + search_radius 7 + 4 x cagf_radius 4 + PSF radius 2 + warp reach 6``."""
    return (f"block {parts['block']} + search_radius {parts['search_radius']} + 4 x cagf_radius {parts['cagf_radius']}"
            f" + PSF radius {parts['psf_radius']} + warp reach {parts['warp_reach']}, rounded up to {TILE_ALIGN}")


def margin_cause(parts: dict) -> str | None:
    """The ``-p`` option that makes most of the margin when it is past its default (``block``); else None."""
    sizes = {"block": parts["block"], "search_radius": parts["search_radius"], "cagf_radius": 4 * parts["cagf_radius"]}
    name = max(sizes, key=sizes.get)
    return name if parts[name] > MARGIN_OPTIONS[name] else None


def check_margin_options(capture: Capture, options: dict) -> None:
    """The options that size the margin, checked against the whole frame as an untiled run checks them, before
    registration: a value past its range is refused naming it (not ``--tile`` or ``--memory-gb``)."""
    hh, ww = capture.hr_shape
    block = _int_option(options, "block", 8)
    if block > min(hh, ww):
        raise InputError("block", block, f"a block side of at most the {hh}x{ww} frame's smaller side ({min(hh, ww)})",
                         f"Use -p block={min(8, min(hh, ww))} (the default) or less than {min(hh, ww)}.")
    radius = _int_option(options, "search_radius", 7)
    check_range("search_radius", radius, high=max(hh, ww), what="the block-matching search radius",
                reason=f"the larger side of the {hh}x{ww} image: farther offsets hold no block",
                fix=f"Use -p search_radius={min(radius, max(hh, ww))} or less (default 7).")
    cagf, lr = _int_option(options, "cagf_radius", 4), max(hh, ww) // 4
    if not 1 <= cagf <= lr:
        raise InputError("cagf_radius", cagf, f"an integer in [1, {lr}] (window radius, LR pixels; at most the "
                         "sub-images' larger side)", f"Use -p cagf_radius={min(4, lr)}" + (
                             " (the paper's value)." if lr >= 4 else "."))
    try:
        sigma = float(options.get("psf_sigma", -1))
    except (TypeError, ValueError):
        return
    if sigma >= 0 and math.isfinite(sigma):
        PSF.gaussian(sigma).check_extent((hh, ww), option="psf_sigma", memory=False)


def check_tiling(capture: Capture, options: dict, *, tile: int | None = None, memory_gb: float | None = None,
                 workers: int = 1, margin: int | None = None) -> bool:
    """Whether ``capture`` runs in tiles (False: the frame fits the budget untiled), and every refusal of its tiling
    that needs no data: the margin's options against the frame (:func:`check_margin_options`), then the smallest tile
    against the budget of ``workers`` tiles, or ``tile`` against its margin. Only ``meta.json`` is read
    (``capture.hr_shape``, ``capture.psf_kernel()``), so a command can check before it starts a cluster."""
    budget, source = memory_budget(memory_gb)
    if tile is None and fits(capture.hr_shape, budget):
        return False
    check_margin_options(capture, options)  # a value past its range names its option, not --tile or --memory-gb
    parts = margin_parts(capture, options, side=tile or max(capture.hr_shape))  # before the warps: no warp reach
    if tile is None:
        tile_for_budget(capture.hr_shape, budget, margin=default_margin(**parts) if margin is None else margin,
                        workers=workers, source=source, margin_note=describe_margin(parts) if margin is None else None,
                        smaller=f"-p {margin_cause(parts)}" if margin is None and margin_cause(parts) else None)
    elif margin is None:
        check_cores_hold_margin(capture.hr_shape, int(tile), default_margin(**parts), parts)
    return True


def tile_margin(capture: Capture, options: dict, *, aperture_homographies, side: int) -> int:
    """The margin (HR pixels) of ``side`` tiles: NLSTR search + block, CAGF window, PSF radius, warp reach."""
    return default_margin(**margin_parts(capture, options, aperture_homographies=aperture_homographies, side=side))


def choose_layout(capture: Capture, options: dict, *, aperture_homographies, tile: int | None = None,
                  memory_gb: float | None = None, workers: int = 1, margin: int | None = None
                  ) -> TileLayout | None:
    """The tiles to reconstruct ``capture`` in, or ``None`` for one untiled run.

    ``tile`` (HR pixels) is the core side asked for; else ``memory_gb`` (or, when neither is given, the
    machine's memory limit) picks the largest tile that fits with ``workers`` tiles side by side; a frame
    that fits whole runs untiled unless ``tile`` asks for tiles. Tiles narrower than their margin are refused
    naming the option that makes the margin (``-p block``, ``search_radius``, ``cagf_radius``).
    """
    hr_shape = capture.hr_shape
    asked = tile
    if tile is None:
        budget, source = memory_budget(memory_gb)
        if fits(hr_shape, budget):
            return None
        first = margin if margin is not None else tile_margin(capture, options, aperture_homographies=aperture_homographies,
                                                               side=max(hr_shape))
        tile = tile_for_budget(hr_shape, budget, margin=first, workers=workers, source=source)
    parts = None
    if margin is None:
        parts = margin_parts(capture, options, aperture_homographies=aperture_homographies, side=tile)
        margin = default_margin(**parts)
    check_cores_hold_margin(hr_shape, int(tile), margin, parts, option="--tile" if asked is not None else "--memory-gb")
    return plan_tiles(hr_shape, int(tile), margin=margin)


def check_cores_hold_margin(hr_shape, tile: int, margin: int, parts: dict | None, *, option: str = "--tile") -> None:
    """Refuse ``tile`` x ``tile`` cores narrower than the blending overlap (the margin): name what makes the margin
    and the smallest ``--tile`` that works."""
    cores = [b - a for axis in (split_axis(int(hr_shape[0]), tile), split_axis(int(hr_shape[1]), tile))
             if len(axis) > 1 for a, b in axis]  # a frame one tile wide along an axis blends nothing there
    if not cores or min(cores) >= margin:
        return
    cause = margin_cause(parts) if parts is not None else None
    made = f" (the margin: {describe_margin(parts)})" if parts is not None else ""
    fix = f"Use --tile {_round_up_tile(margin)} or more" + (f", or a smaller -p {cause}" if cause else "")
    raise InputError(cause or option, f"{parts[cause]} with {option} {tile}" if cause else tile,
                     f"tiles wider than their blending overlap, {margin} HR px here{made}", fix + ".")


def _round_up_tile(value: int) -> int:
    return max(MIN_TILE, -(-int(value) // TILE_ALIGN) * TILE_ALIGN)
