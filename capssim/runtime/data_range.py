"""Out-of-range data: one warning per image, with the count of the values affected.

Raw frames, mosaics and ground truths are on ``[black, white]`` (0 .. 1 of full scale once
normalized). Values outside that range are used as they are by every method (float frames carry no
saturation mask), so a frame with negative values or at 50x full scale gives a result without any
sign of trouble. :func:`warn_out_of_range` counts them and logs ONE warning naming the image, the
counts and the extreme value; it changes no value.
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = ["out_of_range_counts", "warn_out_of_range"]

log = logging.getLogger("capssim.runtime.data_range")


def out_of_range_counts(array, *, low: float, high: float | None) -> tuple[int, int, float, float]:
    """``(n_below, n_above, min, max)`` of the finite values of ``array`` (any shape) outside
    ``[low, high]`` (``high`` None: no upper bound)."""
    values = np.asarray(array)
    if values.size == 0 or not np.issubdtype(values.dtype, np.number):
        return 0, 0, 0.0, 0.0
    lo, hi = float(np.nanmin(values)), float(np.nanmax(values))
    below = int(np.count_nonzero(values < low)) if lo < low else 0
    above = int(np.count_nonzero(values > high)) if high is not None and hi > high else 0
    return below, above, lo, hi


def warn_out_of_range(name: str, array, *, low: float = 0.0, high: float | None = 1.0, unit: str = "full scale",
                      below_means: str = "below black", above_means: str = "above full scale",
                      consequence: str = "used as they are") -> tuple[int, int]:
    """Log one WARNING naming ``name`` if values of ``array`` lie outside ``[low, high]``; returns
    ``(n_below, n_above)``. ``unit`` says what ``high`` is (for the message); ``consequence`` what
    the command does with them."""
    below, above, lo, hi = out_of_range_counts(array, low=low, high=high)
    if below or above:
        total = int(np.asarray(array).size)
        parts = []
        if below:
            parts.append(f"{below} of {total} values {below_means} ({low:g}; lowest {lo:.4g})")
        if above:
            parts.append(f"{above} of {total} values {above_means} ({high:g}; highest {hi:.4g}, "
                         f"{hi / high:.3g}x {unit})" if high else f"{above} of {total} values above {high:g}")
        log.warning("%s: %s: out of range, %s", name, "; ".join(parts), consequence)
    return below, above
