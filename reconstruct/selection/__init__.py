"""The selection layer: a method's data-driven choices, made once per frame before its solve (not the paper's).

:func:`~.holdout_selection.select` resolves ``caps-plus``'s choices (the ADMM iteration count, the polarization
filter of the final image and, where the prior has one, the learned denoiser's blend) from held-out raw pixels of
a window of the frame, and its data direction and start from the Stokes-consistency test of that window, and
returns them as :class:`~.holdout_selection.Choices`: plain option values. The solve then runs from those values
alone, and so does every tile of a tiled run and every rung and view of the error budget (they pass the values as
options). Where every choice is given as an option, nothing is selected.
"""

from .holdout_selection import (
    FALLBACK_ITERATIONS,
    HOLDOUT_MAX_ITERATIONS,
    HOLDOUT_PATIENCE,
    HOLDOUT_WINDOW,
    MIN_HELD_OUT,
    SELECTED_NOTHING,
    Choices,
    check_holdout_fraction,
    format_filter,
    parse_filter,
    select,
    selection_window,
)

__all__ = ["FALLBACK_ITERATIONS", "HOLDOUT_MAX_ITERATIONS", "HOLDOUT_PATIENCE", "HOLDOUT_WINDOW", "MIN_HELD_OUT",
           "SELECTED_NOTHING", "Choices", "check_holdout_fraction", "format_filter", "parse_filter", "select", "selection_window"]
