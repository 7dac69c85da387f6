"""A parametric bootstrap through the forward model: the spread of a reconstruction under new noise.

From an estimate ``x_hat`` of the scene, draw ``N`` new measurements ``y*_i = sensor(A x_hat)`` with the
capture's own noise model and level (:func:`capssim.simulate.simulate_capture`, the project's one forward model),
reconstruct each one with the same method and take the spread of the ``N`` reconstructions ``x*_i``
(Efron and Tibshirani, "An Introduction to the Bootstrap", 1993, ch. 6: the parametric bootstrap). For a
camera-array method that estimated its warps, each replicate is reconstructed with the warps it was simulated
with, moved by the registration's own uncertainty (a random translation per aperture of ``registration_jitter``
HR px, the reference aperture fixed), so the spread also holds what a wrong warp does.

A replicate starts where the reconstruction ended (a warm start, :attr:`RunContext.start`): an iterative CAPS
method runs ``warm_iterations`` ADMM iterations from ``x_hat`` with the penalty it ended at, instead of its whole
schedule from its own start; methods without a solver run as they are.

The **equivariant** variant (``equivariant=True``) also moves ``x_hat`` before each simulation by a random flip
and a shift by a whole number of raw pixels (circular) and moves the replicate back afterwards, so that the
spread also sees how the method's errors depend on where the scene falls on the sampling grid.

A bootstrap sees the estimator's variance around ``x_hat``, not its bias (the prior's): its raw intervals
under-cover, and :mod:`.conformal` scales them on development captures where the truth is known.

The spread is accumulated over replicates as sums (no replicate is kept), for the 12 channels and, per colour,
for S0, DoLP and the doubled AoP (as its cosine and sine: the AoP's spread is circular).
"""

from __future__ import annotations

import logging
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from capssim.camera.sensor import NoNoiseSensor
from capssim.errors import InputError
from capssim.runtime.resources import check_range
from capssim.simulate import simulate_capture
from capssim.stokes.polarization import aop_deg, dolp, stokes_from_12

from ..registry import get_method

log = logging.getLogger(__name__)

__all__ = ["BootstrapMoments", "MAX_REPLICATES", "WARM_ITERATIONS", "bootstrap_moments", "capture_bootstrap",
           "check_noise", "check_replicates", "replicate_statistics"]

#: the most replicates one run may ask for (each is a reconstruction)
MAX_REPLICATES = 256
#: ADMM iterations of a warm-started replicate of an iterative method
WARM_ITERATIONS = 4
#: translation std (HR px) of the warps of a replicate, per axis and aperture, for warps the method estimated: a 2-D
#: Gaussian of this std moves a warp by 1.18 x 0.23 = 0.27 HR px at the median, the median registration error of
#: the ``dev`` suite's 12 captures (apertures 1-3: 0.275 HR px; per capture 0.02 to 1.3) (guides/reconstruction.md)
REGISTRATION_JITTER_HR_PX = 0.23
#: the largest jitter one may ask for (HR px)
MAX_REGISTRATION_JITTER_HR_PX = 4.0
#: DoLP is computed only where S0 exceeds this (on [0, 2]); 0 elsewhere
MIN_S0 = 1e-6


def check_replicates(replicates) -> int:
    """``replicates`` as an int in [2, :data:`MAX_REPLICATES`]; :class:`InputError` naming ``--uncertainty`` else."""
    try:
        count = int(replicates)
        if count != float(replicates):
            raise ValueError
    except (TypeError, ValueError):
        raise InputError("--uncertainty", repr(replicates), "a whole number of replicates",
                         "Use --uncertainty 8.") from None
    if count < 2:
        raise InputError("--uncertainty", count, "at least 2 replicates (a spread needs two)", "Use --uncertainty 8.")
    check_range("--uncertainty", count, high=MAX_REPLICATES, what="the number of replicates",
                reason="each replicate is a reconstruction", fix="Use --uncertainty 8.")
    return count


@dataclass
class BootstrapMoments:
    """Running sums of named statistics over replicates: ``mean`` and ``std`` (``ddof=1``) per name, float64."""

    sums: dict[str, np.ndarray] = field(default_factory=dict)
    squares: dict[str, np.ndarray] = field(default_factory=dict)
    count: int = 0

    def add(self, statistics: dict[str, np.ndarray]) -> None:
        for name, value in statistics.items():
            value = np.asarray(value, dtype=np.float64)
            if name not in self.sums:
                self.sums[name], self.squares[name] = np.zeros_like(value), np.zeros_like(value)
            self.sums[name] += value
            self.squares[name] += value * value
        self.count += 1

    def mean(self, name: str) -> np.ndarray:
        return self.sums[name] / self.count

    def std(self, name: str) -> np.ndarray:
        """The sample standard deviation (``ddof=1``) of ``name`` over the replicates."""
        n = self.count
        variance = (self.squares[name] - self.sums[name] ** 2 / n) / max(n - 1, 1)
        return np.sqrt(np.clip(variance, 0.0, None))


def bootstrap_moments(estimate, resimulate: Callable, reestimate: Callable, *, replicates: int, seed: int = 0,
                      statistics: Callable = lambda x: {"x": x}, transforms: Callable | None = None) -> BootstrapMoments:
    """The parametric bootstrap of any estimator: ``replicates`` times ``x*_i = reestimate(resimulate(x_hat))``.

    Parameters
    ----------
    estimate : array_like
        ``x_hat``, the estimate the new data are drawn from.
    resimulate : callable
        ``resimulate(x, rng) -> data``: new data from ``x`` (the forward model and its noise), drawing from ``rng``.
    reestimate : callable
        ``reestimate(data, start, index) -> x``: the estimator on the new data, warm-started at ``start``.
    replicates : int
        ``N`` (module docstring).
    seed : int
        Seeds the generator every draw comes from (``numpy.random.default_rng(seed)``).
    statistics : callable
        ``statistics(x) -> {name: array}``: what is accumulated of each replicate.
    transforms : callable, optional
        ``transforms(rng) -> (forward, backward)``: the equivariant variant's move of ``x_hat`` before the simulation
        and its inverse applied to the replicate; None: none.

    Returns
    -------
    BootstrapMoments
        The mean and std of each statistic over the replicates.
    """
    rng = np.random.default_rng(seed)
    moments = BootstrapMoments()
    for index in range(replicates):
        forward, backward = transforms(rng) if transforms is not None else (None, None)
        source = estimate if forward is None else forward(estimate)
        replicate = reestimate(resimulate(source, rng), source, index)
        moments.add(statistics(replicate if backward is None else backward(replicate)))
    return moments


def replicate_statistics(image12: np.ndarray) -> dict[str, np.ndarray]:
    """What the bootstrap accumulates of a ``(12, H, W)`` reconstruction: the 12 channels and, per colour
    ``(3, H, W)``, S0 (on [0, 2]), DoLP (0 where S0 <= :data:`MIN_S0`) and ``cos``/``sin`` of twice the AoP."""
    image12 = np.asarray(image12, dtype=np.float64)
    stokes = stokes_from_12(image12)  # (3 [S0, S1, S2], 3 [R, G, B], H, W)
    doubled = np.deg2rad(2.0 * aop_deg(stokes, axis=0))
    return {"channels": image12, "S0": stokes[0], "DoLP": dolp(stokes, axis=0, min_s0=MIN_S0),
            "cos2aop": np.cos(doubled), "sin2aop": np.sin(doubled)}


def check_noise(capture) -> None:
    """:class:`InputError` naming ``--uncertainty`` for a capture whose sensor has no noise model."""
    if isinstance(capture.sensor, NoNoiseSensor):
        raise InputError("--uncertainty", "a capture whose sensor has no noise model (meta.json setup.sensor "
                         "noise 'none')", "a capture with a gaussian or poisson-gaussian sensor",
                         "The bootstrap draws new noise from the capture's noise model: give the capture its sensor "
                         "(capssim simulate --noise gaussian --sigma S, or the sensor block of meta.json).")


def _jittered(homographies: np.ndarray, rng: np.random.Generator, jitter_hr_px: float) -> np.ndarray:
    """``homographies`` ``(4, 3, 3)`` with apertures 1-3 translated by ``N(0, jitter^2)`` HR px per axis."""
    moved = np.array(homographies, dtype=np.float64, copy=True)
    if jitter_hr_px > 0:
        shift = rng.normal(0.0, jitter_hr_px, size=(3, 2))
        translation = np.tile(np.eye(3), (3, 1, 1))
        translation[:, :2, 2] = shift
        moved[1:] = translation @ moved[1:]
    return moved


@contextmanager
def _replicate_warnings_muted():
    """capssim's warnings at ERROR level while the replicates run (restored afterwards)."""
    logger = logging.getLogger("capssim")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def grid_transforms(rng: np.random.Generator, *, max_shift_raw_px: int = 4):
    """The equivariant variant's random move: a flip (none, rows, columns or both) and a circular shift by a whole
    number of raw pixels (an even number of HR pixels, so the Bayer phase is kept); ``(forward, backward)``."""
    flips = [axis for axis, flip in ((-2, rng.random() < 0.5), (-1, rng.random() < 0.5)) if flip]
    shift = tuple(int(2 * s) for s in rng.integers(-max_shift_raw_px, max_shift_raw_px + 1, size=2))

    def forward(x):
        x = np.flip(x, axis=flips) if flips else x
        return np.ascontiguousarray(np.roll(x, shift, axis=(-2, -1)))

    def backward(x):
        x = np.roll(x, (-shift[0], -shift[1]), axis=(-2, -1))
        return np.ascontiguousarray(np.flip(x, axis=flips) if flips else x)

    return forward, backward


def _warm_options(spec, record: dict, warm_iterations: int) -> dict:
    """The options of a replicate: the run's own and its resolved choices; for a method with ADMM options, the
    count ``warm_iterations`` and the penalty the run ended at (``mu0``)."""
    options = {**(record.get("options") or {}), **(record.get("resolved_options") or {})}
    names = {option.name for option in (spec.options() if spec.options is not None else [])}
    history = record.get("history") or []
    if {"iterations", "mu0"} <= names and history and history[-1].get("mu") is not None:
        options.update({"iterations": int(warm_iterations), "mu0": float(history[-1]["mu"])})
    options.pop("track_psnr", None)
    return options


def capture_bootstrap(capture, method: str, estimate: np.ndarray, record: dict, *, replicates: int, seed: int = 0,
                      equivariant: bool = False, warm_iterations: int = WARM_ITERATIONS,
                      registration_jitter_hr_px: float | None = None, run: Callable,
                      **run_options) -> tuple[BootstrapMoments, dict]:
    """The bootstrap of ``method``'s reconstruction ``estimate`` ``(12, 2H, 2W)`` of ``capture`` (module docstring).

    Parameters
    ----------
    capture : Capture
        The capture that was reconstructed (its set-up gives the noise model, the PSF and the rig).
    method, estimate, record : str, numpy.ndarray, dict
        The method, its image and its record (its options, registration, resolved choices and history).
    replicates, seed, equivariant, warm_iterations : int, int, bool, int
        ``N``; the seed of every draw; the equivariant variant; the warm-started replicates' ADMM count.
    registration_jitter_hr_px : float, optional
        The std of each replicate's warp translation (HR px); None: :data:`REGISTRATION_JITTER_HR_PX` for warps the
        method estimated, 0 for true or calibrated warps and for DoFP methods. Replicates are simulated and solved
        with the warps the run used (its record's ``registration.aperture_homographies``).
    run : callable
        The dispatcher, ``run(capture, method, *, true_warps, start, **options) -> (MethodOutput, record)``.
    **run_options
        The dispatcher's own keywords as the run used them (device, calibration, physical projection).

    Returns
    -------
    (BootstrapMoments, dict)
        The moments of :func:`replicate_statistics` and the bootstrap's record.
    """
    check_noise(capture)
    spec = get_method(method)
    registration = record.get("registration") or {}
    used = spec.input_kind == "caps" and "aperture_homographies" in registration  # true, calibrated or estimated
    estimated = used and str(registration.get("source", "")).startswith("estimated")
    warps = np.asarray(registration["aperture_homographies"]) if used else capture.aperture_homographies()
    jitter = (REGISTRATION_JITTER_HR_PX if estimated else 0.0) if registration_jitter_hr_px is None \
        else float(registration_jitter_hr_px)
    options = _warm_options(spec, record, warm_iterations)

    def resimulate(x, rng):
        new = simulate_capture(np.clip(x, 0.0, None), capture.setup, seed=int(rng.integers(2**62)),
                               aperture_homographies=warps)
        return new.with_aperture_homographies(_jittered(warps, rng, jitter))  # the warps it is solved with

    def reestimate(new_capture, start, index):
        out, _ = run(new_capture, method, true_warps=spec.input_kind == "caps", start=start, **run_options,
                     **options)
        log.debug("%s: replicate %d of %d done", method, index + 1, replicates)
        return out.image

    with _replicate_warnings_muted():  # the run warned already of what each replicate would warn again
        moments = bootstrap_moments(np.asarray(estimate, dtype=np.float32), resimulate, reestimate,
                                    replicates=replicates, seed=seed, statistics=replicate_statistics,
                                    transforms=grid_transforms if equivariant else None)
    info = {"replicates": replicates, "seed": seed, "equivariant": bool(equivariant),
            "warps": f"the run's ({registration.get('source')}){', jittered' if jitter else ''}" if used
            else "the capture's stored warps" if spec.input_kind == "caps" else "none (DoFP)",
            "registration_jitter_hr_px": jitter, "replicate_options": options}
    return moments, info
