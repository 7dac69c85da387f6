"""The uncertainty of a reconstruction as arrays and files: what ``--uncertainty N`` writes beside ``recon/METHOD.tiff``.

Three files, float32, on the HR grid ``(2H, 2W)`` (docs: guides/reconstruction.md, "Error bars"):

``recon/METHOD.std.tiff`` ``(12, 2H, 2W)``
    the calibrated standard deviation of each of the 12 channels (the bootstrap's spread times the
    calibration's scale, so that ``estimate +- z90 * std`` is the 90 % interval);
``recon/METHOD.interval90.tiff`` ``(2, 12, 2H, 2W)``
    the lower (``[0]``) and upper (``[1]``) bounds of the 90 % interval of each channel;
``recon/METHOD.stokes-uncertainty.tiff`` ``(27, 2H, 2W)``
    S0, DoLP and AoP per colour: plane ``9 q + 3 s + k`` holds quantity ``q`` of :data:`STOKES_QUANTITIES`
    (S0 on [0, 2], DoLP on [0, 1], AoP in degrees), statistic ``s`` of :data:`STOKES_STATISTICS` (``std``,
    ``lower``, ``upper``) and colour ``k`` (R, G, B). AoP wraps around at 180 degrees: its ``lower`` is in
    [0, 180) and its ``upper`` is ``lower + width`` with ``width`` in [0, 180], so ``upper`` may pass 180; an angle
    ``a`` lies in the interval when ``(a - lower) mod 180 <= upper - lower`` (:func:`aop_inside`); its ``std``
    is the circular standard deviation of the doubled angle, halved, in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from capssim.captures.capture import COMPANION_SUFFIXES
from capssim.conventions import N_CHANNELS
from capssim.errors import InputError
from capssim.files.imageio import read_tiff

__all__ = ["STOKES_QUANTITIES", "STOKES_STATISTICS", "UNCERTAINTY_FILES", "UncertaintyMaps", "aop_inside",
           "read_uncertainty", "stokes_layout", "stokes_plane", "uncertainty_paths"]

#: the quantities of ``stokes-uncertainty.tiff``, in plane order
STOKES_QUANTITIES = ("S0", "DoLP", "AoP")
#: the statistics of each quantity, in plane order
STOKES_STATISTICS = ("std", "lower", "upper")
#: the colours of each statistic, in plane order
STOKES_COLOURS = ("R", "G", "B")
#: the file suffixes (``recon/METHOD{suffix}.tiff``) by name
UNCERTAINTY_FILES = COMPANION_SUFFIXES
#: the interval's nominal coverage
NOMINAL_COVERAGE = 0.90


def stokes_plane(quantity: str, statistic: str, colour: int | str) -> int:
    """The plane of ``stokes-uncertainty.tiff`` holding ``quantity``'s ``statistic`` of ``colour`` (0-2 or R/G/B)."""
    k = STOKES_COLOURS.index(colour) if isinstance(colour, str) else int(colour)
    return 9 * STOKES_QUANTITIES.index(quantity) + 3 * STOKES_STATISTICS.index(statistic) + k


def stokes_layout() -> list[str]:
    """The name of every plane of ``stokes-uncertainty.tiff``, e.g. ``"DoLP lower G"`` (written in the record)."""
    return [f"{q} {s} {k}" for q in STOKES_QUANTITIES for s in STOKES_STATISTICS for k in STOKES_COLOURS]


def aop_inside(angle_deg, lower_deg, upper_deg):
    """True where the angle ``angle_deg`` (degrees, any range) lies in the wrapped AoP interval ``[lower, upper]``."""
    return np.mod(np.asarray(angle_deg) - lower_deg, 180.0) <= (np.asarray(upper_deg) - lower_deg) + 1e-9


@dataclass
class UncertaintyMaps:
    """A reconstruction's error bars: ``std`` ``(12, 2H, 2W)``, ``interval90`` ``(2, 12, 2H, 2W)`` (lower, upper) and
    ``stokes`` ``(27, 2H, 2W)`` (module docstring), float32, with their ``record`` (method, replicates, calibration)."""

    std: np.ndarray
    interval90: np.ndarray
    stokes: np.ndarray
    record: dict = field(default_factory=dict)

    def __post_init__(self):
        hh, ww = np.shape(self.std)[-2:]
        for name, shape in (("std", (N_CHANNELS, hh, ww)), ("interval90", (2, N_CHANNELS, hh, ww)),
                            ("stokes", (27, hh, ww))):
            value = np.asarray(getattr(self, name), dtype=np.float32)
            if value.shape != shape:
                raise InputError(f"uncertainty {name}", f"shape {value.shape}", f"shape {shape}")
            setattr(self, name, value)

    def arrays(self) -> dict[str, np.ndarray]:
        """``{file name: array}`` as in :data:`UNCERTAINTY_FILES`."""
        return {"std": self.std, "interval90": self.interval90, "stokes": self.stokes}


def uncertainty_paths(capture_path, method: str) -> dict[str, Path]:
    """``{name: recon/METHOD{suffix}.tiff}`` of a capture folder."""
    recon = Path(capture_path) / "recon"
    return {name: recon / f"{method}{suffix}.tiff" for name, suffix in UNCERTAINTY_FILES.items()}


def read_uncertainty(capture_path, method: str) -> UncertaintyMaps | None:
    """The uncertainty files of ``method`` in a capture folder, or None when it has none (a run without
    ``--uncertainty``); :class:`InputError` when some are missing or have the wrong shape."""
    paths = uncertainty_paths(capture_path, method)
    present = [p.is_file() for p in paths.values()]
    if not any(present):
        return None
    if not all(present):
        missing = ", ".join(str(p.name) for p, ok in zip(paths.values(), present) if not ok)
        raise InputError(f"recon/{method} uncertainty files", f"{missing} missing",
                         "all three of .std, .interval90 and .stokes-uncertainty",
                         f"Run 'capssim reconstruct CAPTURE -m {method} --uncertainty 8' again.")
    arrays = {name: read_tiff(path, argument=f"recon/{path.name}") for name, path in paths.items()}
    interval = arrays["interval90"]
    if interval.ndim == 3 and interval.shape[0] == 2 * N_CHANNELS:  # a TIFF keeps pages: (2, 12) comes back as 24
        arrays["interval90"] = interval.reshape(2, N_CHANNELS, *interval.shape[1:])
    return UncertaintyMaps(**arrays)
