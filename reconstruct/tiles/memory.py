"""How much memory a CAPS reconstruction takes, and the tile size that fits a budget.

The model is affine in the HR pixel count, fitted to ``capssim bench reconstruct --device cpu``
(issue 35: 0.93 GB at 512², 2.7 GB at 1024², 10.0 GB at 2048²): :data:`BASE_BYTES` for the
process (torch, the method's modules) and :data:`BYTES_PER_HR_PIXEL` for the observations, the
ADMM state and NLSTR's working set (:meth:`NonlocalSparseTensor.working_set_bytes` holds its own
share, a few hundred bytes per pixel). A tiled run also holds the whole frame once
(:data:`FRAME_BYTES_PER_HR_PIXEL`); tiles that run side by side (``--workers``) share the rest.
"""

from __future__ import annotations

import math

from capssim.errors import InputError, ResourceError
from capssim.runtime.resources import format_bytes, memory_limit

from .geometry import MIN_TILE, TILE_ALIGN

__all__ = ["BASE_BYTES", "BYTES_PER_HR_PIXEL", "FRAME_BYTES_PER_HR_PIXEL", "MIN_REGISTRATION_SIDE",
           "REGISTRATION_BYTES_PER_HR_PIXEL", "estimate_bytes", "fits", "memory_budget", "registration_bytes",
           "tile_for_budget"]

#: memory of the process before the frame (interpreter, torch, the method's modules), bytes
BASE_BYTES = 0.35 * 2**30
#: memory per HR pixel of one CAPS reconstruction (observations, ADMM state, NLSTR working set), bytes
BYTES_PER_HR_PIXEL = 2450.0
#: memory per HR pixel of the whole frame that a tiled run holds besides its tiles (the raw frames, the blended
#: frame and its weights, the masks, the physical projection's temporaries), bytes
FRAME_BYTES_PER_HR_PIXEL = 200.0
#: peak memory of the registration per HR pixel of the frame it registers (4.53 GB for 2560x2048, measured with
#: ``resource.getrusage`` around ``estimate_lr_homographies``; docs/notes/full-frames.md), bytes
REGISTRATION_BYTES_PER_HR_PIXEL = 850.0
#: the smallest window side a frame is registered on (HR pixels)
MIN_REGISTRATION_SIDE = 256


def registration_bytes(hr_shape) -> float:
    """Peak bytes of registering an ``hr_shape`` ``(rows, cols)`` frame (:data:`REGISTRATION_BYTES_PER_HR_PIXEL`)."""
    rows, cols = (int(v) for v in hr_shape)
    return BASE_BYTES + REGISTRATION_BYTES_PER_HR_PIXEL * rows * cols


def estimate_bytes(hr_shape) -> float:
    """Peak bytes of one CAPS-family reconstruction of an ``hr_shape`` ``(rows, cols)`` HR frame."""
    rows, cols = (int(v) for v in hr_shape)
    return BASE_BYTES + BYTES_PER_HR_PIXEL * rows * cols


def memory_budget(memory_gb: float | None) -> tuple[float, str]:
    """The budget in bytes and where it comes from: ``--memory-gb`` (GiB), else the machine's limit
    (:func:`capssim.runtime.resources.memory_limit`: ``CAPSSIM_MEMORY_LIMIT_GB`` or 80 % of the free memory)."""
    if memory_gb is None:
        return memory_limit()
    if not (isinstance(memory_gb, (int, float)) and math.isfinite(memory_gb) and memory_gb > 0):
        raise InputError("--memory-gb", repr(memory_gb), "a positive, finite number of GiB (e.g. --memory-gb 4)")
    return float(memory_gb) * 2**30, f"--memory-gb {memory_gb:g}"


def fits(hr_shape, budget_bytes: float, *, workers: int = 1) -> bool:
    """True when ``workers`` reconstructions of ``hr_shape`` fit in ``budget_bytes`` side by side."""
    return workers * estimate_bytes(hr_shape) <= budget_bytes


def tile_for_budget(hr_shape, budget_bytes: float, *, margin: int, workers: int = 1,
                    source: str = "--memory-gb", margin_note: str | None = None, smaller: str | None = None) -> int:
    """The largest tile core side (HR pixels, a multiple of 4) whose window fits the budget.

    Parameters
    ----------
    hr_shape : tuple of int
        The frame, HR pixels.
    budget_bytes : float
        Memory for the run: the frame (:data:`FRAME_BYTES_PER_HR_PIXEL`) and ``workers`` tiles, bytes.
    margin : int
        The tile margin, HR pixels (the window is the core plus ``2 margin`` per side at most).
    workers : int
        Tiles reconstructed at the same time.
    source : str
        Where the budget comes from, for the error message.
    margin_note : str, optional
        What the margin is made of, for the error message (``block 8 + search_radius 7 + ...``).
    smaller : str, optional
        The option that makes most of the margin (``-p block``), suggested in the error message.

    Returns
    -------
    int
        The core side; the frame's larger side when the whole frame fits.

    Raises
    ------
    ResourceError
        When even a :data:`MIN_TILE` tile does not fit.
    """
    frame = FRAME_BYTES_PER_HR_PIXEL * int(hr_shape[0]) * int(hr_shape[1])
    per_tile = (budget_bytes - frame) / max(1, int(workers))
    side = math.sqrt(max(0.0, (per_tile - BASE_BYTES) / BYTES_PER_HR_PIXEL)) - 2 * margin
    side = int(side // TILE_ALIGN) * TILE_ALIGN
    if side < MIN_TILE:
        need = frame + workers * estimate_bytes((MIN_TILE + 2 * margin, MIN_TILE + 2 * margin))
        raise ResourceError("--memory-gb", budget_bytes,
                            f"the {hr_shape[0]}x{hr_shape[1]} frame and {workers} tile(s) of the smallest size "
                            f"({MIN_TILE} px + {margin} px margins"
                            f"{': ' + margin_note if margin_note else ''}) need "
                            f"about {format_bytes(need)}, more than the budget {format_bytes(budget_bytes)} "
                            f"({source}). Give at least --memory-gb {math.ceil(need / 2**30 * 10) / 10:g}, "
                            + (f"or a smaller {smaller}." if smaller else "or fewer --workers."))
    return min(side, max(int(v) for v in hr_shape))
