"""How good a reconstruction's error bars are: coverage and width of its 90 % intervals, and AUSE.

The error bars are the files ``capssim reconstruct --uncertainty N`` writes beside ``recon/METHOD.tiff``
(:mod:`capssim.reconstruct.uncertainty.maps`). :func:`score_uncertainty` scores them against the ground
truth in four groups (:data:`GROUPS`):

``12ch``
    the 12 intensity channels, pooled (values on [0, 1] of full scale);
``S0``, ``DoLP``, ``AoP``
    per colour, pooled over R, G, B (S0 on [0, 2], DoLP on [0, 1], AoP in degrees), with the metrics' own
    conventions (:mod:`capssim.eval.metrics`): the same border crop; DoLP scored where the *ground truth* has
    ``S0 > min_s0``; AoP where it also has ``DoLP > min_dolp`` (the AoP mask of the metrics).

For each group:

coverage
    the fraction of scored values whose ground truth lies inside the 90 % interval ``[lower, upper]``
    (AoP: inside the wrapped interval, :func:`~capssim.reconstruct.uncertainty.maps.aop_inside`); a calibrated
    interval covers about :data:`NOMINAL_COVERAGE`;
mean width
    the mean of ``upper - lower`` in the group's units (AoP: degrees);
AUSE
    the area under the sparsification error (Ilg et al., "Uncertainty estimates and multi-hypotheses
    networks for optical flow", ECCV 2018): the sparsification curve is the RMSE of the values left after
    removing the fraction ``f`` (:data:`SPARSIFICATION_FRACTIONS`, 0 to 0.99 by 0.01) with the largest
    standard deviation, the oracle curve the same removing the largest actual ``|error|``; both divided by
    the RMSE at ``f = 0``; AUSE is the area between them (trapezoid rule over ``f``). 0 when the standard
    deviations rank the errors as the errors themselves do; near the area under the oracle's curve when they
    are unrelated to them. :func:`sparsification` computes it (one argsort per curve).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from capssim.errors import InputError
from capssim.reconstruct.uncertainty.maps import NOMINAL_COVERAGE, UncertaintyMaps, aop_inside, stokes_plane
from capssim.stokes.polarization import angle_difference_deg, aop_deg, dolp, stokes_from_12

from . import metrics as M

__all__ = ["GROUPS", "NOMINAL_COVERAGE", "SPARSIFICATION_FRACTIONS", "WIDTH_UNITS", "GroupScore", "Sparsification",
           "ScoredValues", "UncertaintyScores", "score_uncertainty", "scored_values", "sparsification",
           "uncertainty_table"]

#: the groups scored, in report order
GROUPS = ("12ch", "S0", "DoLP", "AoP")
#: the unit of each group's interval width
WIDTH_UNITS = {"12ch": "full scale [0, 1]", "S0": "S0 scale [0, 2]", "DoLP": "DoLP [0, 1]", "AoP": "degrees"}
#: the fractions ``f`` of removed values of the sparsification curves: 0, 0.01, ..., 0.99
SPARSIFICATION_FRACTIONS = np.arange(100) / 100.0


@dataclass
class Sparsification:
    """The sparsification curves of one group (Ilg et al. 2018), each ``(F,)`` over ``fractions``.

    ``curve[i]`` is the RMSE of the values left after removing the fraction ``fractions[i]`` with the largest
    standard deviation, ``oracle[i]`` the same removing the largest ``|error|``; both divided by the RMSE of
    all values (so both start at 1). ``ause`` is the area between them (dimensionless).
    """

    fractions: np.ndarray
    curve: np.ndarray
    oracle: np.ndarray
    ause: float


@dataclass
class GroupScore:
    """Coverage (fraction in [0, 1]), mean interval width (the group's :data:`WIDTH_UNITS`) and sparsification of
    one group; ``None`` where nothing was scored (``scored == 0``) or the RMSE of all values is 0 (no AUSE)."""

    coverage: float | None
    mean_width: float | None
    scored: int
    sparsification: Sparsification | None = None

    @property
    def ause(self) -> float | None:
        """The AUSE, or None when the curves are undefined."""
        return None if self.sparsification is None else self.sparsification.ause


@dataclass
class UncertaintyScores:
    """:func:`score_uncertainty`'s result: a :class:`GroupScore` per name of :data:`GROUPS`, and the settings
    (``border``, ``min_s0``, ``min_dolp``, ``convention``) they were scored with."""

    groups: dict[str, GroupScore]
    settings: dict[str, Any] = field(default_factory=dict)
    nominal_coverage: float = NOMINAL_COVERAGE

    def to_dict(self, *, with_curves: bool = True) -> dict[str, Any]:
        """JSON-ready: ``nominal_coverage``, ``settings``, ``fractions`` and per group ``coverage``,
        ``mean_width``, ``width_unit``, ``ause``, ``scored`` and (``with_curves``) ``sparsification``, ``oracle``."""
        out: dict[str, Any] = {"nominal_coverage": self.nominal_coverage, "settings": dict(self.settings)}
        if with_curves:
            out["fractions"] = [float(f) for f in SPARSIFICATION_FRACTIONS]
        groups = {}
        for name, g in self.groups.items():
            entry = {"coverage": g.coverage, "mean_width": g.mean_width, "width_unit": WIDTH_UNITS[name],
                     "ause": g.ause, "scored": g.scored}
            if with_curves:
                sp = g.sparsification
                entry["sparsification"] = None if sp is None else [float(v) for v in sp.curve]
                entry["oracle"] = None if sp is None else [float(v) for v in sp.oracle]
            groups[name] = entry
        out["groups"] = groups
        return out


def _remaining_rmse(squared_error: np.ndarray, key: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """RMSE of the ``kept[i]`` values with the smallest ``key`` (the largest ones removed), for each ``i``."""
    order = np.argsort(key, kind="stable")
    cumulative = np.cumsum(squared_error[order])
    return np.sqrt(cumulative[kept - 1] / kept)


def sparsification(abs_error, std, *, fractions=SPARSIFICATION_FRACTIONS) -> Sparsification | None:
    """The sparsification and oracle curves and the AUSE of values with errors ``abs_error`` and standard
    deviations ``std`` (Ilg et al. 2018).

    Parameters
    ----------
    abs_error : array_like
        ``|estimate - truth|`` of each value, any shape (flattened), in the group's units.
    std : array_like
        The standard deviation of each value, the same shape, in the same units.
    fractions : array_like
        Increasing fractions in ``[0, 1)`` of values removed, starting at 0 (default 0, 0.01, ..., 0.99).

    Returns
    -------
    Sparsification or None
        None when there is no value or the RMSE of all values is 0 (the normalization is undefined).
    """
    err = np.abs(np.asarray(abs_error, dtype=np.float64)).ravel()
    sd = np.asarray(std, dtype=np.float64).ravel()
    f = np.asarray(fractions, dtype=np.float64)
    if err.shape != sd.shape:
        raise InputError("std", f"{sd.size} values", f"one per error value ({err.size})")
    if f.ndim != 1 or f.size < 2 or f[0] != 0 or np.any(np.diff(f) <= 0) or f[-1] >= 1:
        raise InputError("fractions", f"{f.size} values from {f.min(initial=0):g} to {f.max(initial=0):g}",
                         "increasing fractions from 0 to below 1")
    n = err.size
    squared = err ** 2
    if n == 0 or not squared.sum() > 0:
        return None
    kept = n - np.floor(f * n + 1e-9).astype(np.int64)  # at least 1: f < 1
    curve = _remaining_rmse(squared, sd, kept)
    oracle = _remaining_rmse(squared, err, kept)
    curve, oracle = curve / curve[0], oracle / oracle[0]
    gap = curve - oracle
    ause = float(np.sum(0.5 * (gap[1:] + gap[:-1]) * np.diff(f)))
    return Sparsification(fractions=f, curve=curve, oracle=oracle, ause=ause)


class ScoredValues(NamedTuple):
    """One group's scored values, 1-D over its scored pixels."""

    truth: np.ndarray
    error: np.ndarray  # estimate - truth (AoP: wrapped to [-90, 90) degrees)
    std: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


def _stokes_maps(stokes: np.ndarray, quantity: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(std, lower, upper)`` of ``quantity``, each ``(3 [R, G, B], H, W)``, from the 27 planes of ``stokes``."""
    return tuple(stokes[[stokes_plane(quantity, s, k) for k in range(3)]] for s in ("std", "lower", "upper"))


def _group_values(est: np.ndarray, gt: np.ndarray, maps: dict[str, np.ndarray], *, min_s0: float | None,
                  min_dolp: float | None) -> dict[str, ScoredValues]:
    """The scored values of every group from cropped float64 ``(12, H, W)`` images and cropped maps."""
    st_e, st_g = stokes_from_12(est), stokes_from_12(gt)
    guard = min_s0 if min_s0 is not None else 0.0  # the metrics' DoLP dark guard
    d_e, d_g = dolp(st_e, min_s0=guard, fill=0.0), dolp(st_g, min_s0=guard, fill=0.0)
    a_e, a_g = aop_deg(st_e), aop_deg(st_g)
    dolp_mask = M.ground_truth_mask(st_g, min_s0=min_s0)
    aop_mask = M.ground_truth_mask(st_g, min_s0=min_s0, dolp_gt=d_g, min_dolp=min_dolp)
    if not np.any(np.hypot(st_g[1], st_g[2]) > 0):
        aop_mask[:] = False  # as the metrics: AoP is undefined where the ground truth is unpolarized everywhere
    interval = maps["interval90"]
    out = {"12ch": ScoredValues(gt.ravel(), (est - gt).ravel(), maps["std"].ravel(), interval[0].ravel(),
                           interval[1].ravel())}
    every = np.ones(st_g.shape[1:], dtype=bool)
    for name, truth, error, mask in (("S0", st_g[0], st_e[0] - st_g[0], every),
                                     ("DoLP", d_g, d_e - d_g, dolp_mask),
                                     ("AoP", a_g, angle_difference_deg(a_e, a_g), aop_mask)):
        std, lower, upper = _stokes_maps(maps["stokes"], name)
        out[name] = ScoredValues(truth[mask], error[mask], std[mask], lower[mask], upper[mask])
    return out


def _check_values(name: str, values: ScoredValues) -> None:
    """Refuse non-finite, negative standard deviations or ``upper < lower`` at a group's scored pixels."""
    for what, array in (("std", values.std), ("lower", values.lower), ("upper", values.upper)):
        file = "stokes-uncertainty" if name != "12ch" else "std" if what == "std" else "interval90"
        bad = int(np.count_nonzero(~np.isfinite(array)))
        if bad:
            raise InputError(f"recon/METHOD.{file}.tiff ({name} {what})", f"{bad} NaN/inf values at scored pixels",
                             "finite values",
                             "Run 'capssim reconstruct CAPTURE -m METHOD --uncertainty N' again.")
    if np.any(values.std < 0):
        raise InputError(f"{name} std", f"{int(np.count_nonzero(values.std < 0))} negative values",
                         "standard deviations >= 0")
    if np.any(values.upper < values.lower):
        raise InputError(f"{name} interval", f"{int(np.count_nonzero(values.upper < values.lower))} upper bounds "
                         "below their lower bounds", "lower <= upper")


def _score_group(name: str, values: ScoredValues) -> GroupScore:
    """Coverage, mean width and sparsification of one group's values."""
    n = int(values.truth.size)
    if n == 0:
        return GroupScore(None, None, 0)
    if name == "AoP":
        inside = aop_inside(values.truth, values.lower, values.upper)
    else:
        inside = (values.lower <= values.truth) & (values.truth <= values.upper)
    width = values.upper.astype(np.float64) - values.lower
    return GroupScore(float(np.mean(inside)), float(np.mean(width)), n, sparsification(values.error, values.std))


def _check_maps(maps: UncertaintyMaps, hr_shape: tuple[int, int]) -> None:
    """Refuse maps that are not :class:`UncertaintyMaps` or lie on another grid than the estimate's."""
    if not isinstance(maps, UncertaintyMaps):
        raise InputError("maps", type(maps).__name__, "an UncertaintyMaps (capssim.reconstruct.uncertainty.maps)",
                         "Read them with read_uncertainty(capture_path, method).")
    if maps.std.shape[-2:] != tuple(hr_shape):
        raise InputError("maps", f"HR grid {maps.std.shape[-2:]}", f"the estimate's grid {tuple(hr_shape)}",
                         "Score the error bars of this very reconstruction.")


def score_uncertainty(estimate, gt, maps: UncertaintyMaps, *, convention: str | M.Convention = "capssim",
                      min_s0: float | None = None, min_dolp: float | None = None,
                      border: int | None = None) -> UncertaintyScores:
    """Coverage and width of the 90 % intervals and AUSE of a reconstruction's error bars, per group.

    Parameters
    ----------
    estimate : array_like
        ``(12, H, W)`` float reconstruction on [0, 1] (channel ``c = 3 p + k``).
    gt : array_like
        ``(12, H, W)`` float ground truth on the same grid.
    maps : UncertaintyMaps
        The reconstruction's error bars on that grid (:func:`~capssim.reconstruct.uncertainty.maps.read_uncertainty`).
    convention : str or Convention
        The metric convention whose border crop and masks apply (:func:`capssim.eval.metrics.score`).
    min_s0, min_dolp : float, optional
        The ground-truth thresholds of the DoLP (``S0 > min_s0``) and AoP (and ``DoLP > min_dolp``) masks;
        default: the convention's (capssim: 0.02 and 0.05).
    border : int, optional
        Pixels cropped on each side; default: the convention's (capssim: 8).

    Returns
    -------
    UncertaintyScores
        A :class:`GroupScore` per name of :data:`GROUPS` and the settings used.

    Raises
    ------
    InputError
        Mismatched shapes, non-finite images or error bars (at scored pixels), negative standard deviations,
        an interval with ``upper < lower``, a border that leaves no pixel.
    """
    values, settings = scored_values(estimate, gt, maps, convention=convention, min_s0=min_s0, min_dolp=min_dolp,
                                     border=border)
    return UncertaintyScores({name: _score_group(name, values[name]) for name in GROUPS}, settings)


def scored_values(estimate, gt, maps: UncertaintyMaps, *, convention: str | M.Convention = "capssim",
                  min_s0: float | None = None, min_dolp: float | None = None,
                  border: int | None = None) -> tuple[dict[str, "ScoredValues"], dict]:
    """The scored values of every group (:func:`score_uncertainty`'s pixels, checked) and the settings used.

    Parameters
    ----------
    estimate, gt, maps, convention, min_s0, min_dolp, border
        As :func:`score_uncertainty`.

    Returns
    -------
    (dict, dict)
        ``{group: ScoredValues}`` (1-D ``truth``, ``error``, ``std``, ``lower``, ``upper`` over the group's scored
        pixels; AoP errors wrapped to [-90, 90) degrees) and the settings (convention, border, thresholds).
    """
    conv = M.get_convention(convention)
    est, truth = M.check_pair(estimate, gt)
    conv, b, s0_guard, dolp_min = M.resolve_settings(conv, min_s0=min_s0, min_dolp=min_dolp, border=border)
    _check_maps(maps, truth.shape[-2:])
    crop = {"matlab": conv.matlab_crop}
    est_c, gt_c = M.crop_border(est, b, **crop), M.crop_border(truth, b, **crop)
    if gt_c.shape[-1] <= 0 or gt_c.shape[-2] <= 0:
        raise InputError("border", b, f"fewer pixels than half the image side ({truth.shape[-2]}x{truth.shape[-1]})",
                         "Pass a smaller border.")
    cropped = {name: M.crop_border(array, b, **crop) for name, array in maps.arrays().items()}
    values = _group_values(est_c, gt_c, cropped, min_s0=s0_guard, min_dolp=dolp_min)
    for name, group in values.items():
        _check_values(name, group)
    return values, {"convention": conv.name, "border": b, "min_s0": s0_guard, "min_dolp": dolp_min}


def uncertainty_table(records: list[dict], methods: list[str]) -> str | None:
    """A Markdown table of the error bars of a suite's cases (their ``uncertainty`` entries): per method, the mean over
    the cases of each group's coverage, the 12 channels' mean width and AUSE, and the bootstrap's time; None when no
    case has error bars."""
    rows = []
    for method in methods:
        entries = [r["uncertainty"] for r in records if r.get("method") == method
                   and isinstance(r.get("uncertainty"), dict) and "groups" in r["uncertainty"]]
        if not entries:
            continue

        def mean(group: str, key: str):
            values = [e["groups"][group][key] for e in entries if e["groups"][group][key] is not None]
            return float(np.mean(values)) if values else None

        cells = [f"{v:.3f}" if v is not None else "n/a" for v in (mean(g, "coverage") for g in GROUPS)]
        width, ause = mean("12ch", "mean_width"), mean("12ch", "ause")
        seconds = float(np.mean([e.get("time_s") or 0.0 for e in entries]))
        rows.append(f"| {method} | {len(entries)} | " + " | ".join(cells)
                    + f" | {width:.4f} | {'n/a' if ause is None else f'{ause:.3f}'} | {seconds:.1f} |")
    if not rows:
        return None
    head = ("| method | cases | " + " | ".join(f"{g} coverage" for g in GROUPS)
            + " | 12ch width | 12ch AUSE | bootstrap s |\n|---|---:|" + "---:|" * (len(GROUPS) + 3))
    return head + "\n" + "\n".join(rows)
