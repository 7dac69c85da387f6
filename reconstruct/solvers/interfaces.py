"""What the iterative solvers ask of the model: a data-fidelity term and a prior.

The solvers (:func:`capssim.reconstruct.solvers.admm.admm`, paper section 4, eq. 20-30, and
:func:`capssim.reconstruct.solvers.descent.steepest_descent`, eq. 16) are written against these two
protocols only, as deepinv keeps its optimizers apart from its physics and priors: a new
prior or data term needs no edit of a solver.

* :class:`DataFidelity`: the data part of the objective (eq. 18), its value ``f(I)`` and a
  descent direction ``D`` (``-grad f``, or a preconditioned one such as the
  confidence-guided direction of eq. 16 / 26);
* :class:`Prior`: the ``X``-step of ADMM, an estimate ``X`` of ``Z = I - L`` (eq. 21-23 and
  29 for NLSTR; the proximal operator of ``R / mu`` for a plain regularizer ``R``), with
  the fields it adds to the solver's history and its own schedule between iterations.

The module also holds the checks and the record keeping both solvers share.
"""

from __future__ import annotations

import logging
import math
from contextlib import AbstractContextManager
from typing import Callable, Protocol

import torch

from capssim.errors import InputError

from ..run_context import no_stage

log = logging.getLogger(__name__)

#: ``stage(name)`` -> a context manager timing one step (``StageTimer.stage``)
StageFactory = Callable[[str], AbstractContextManager]
#: ``progress(done, total, message)``
Progress = Callable[[int, int, str], None]
#: ``observer(iteration, image)`` -> extra history fields (diagnostics only)
Observer = Callable[[int, torch.Tensor], "dict | None"]


class DataFidelity(Protocol):
    """The data term ``f`` of the objective, for images of shape :attr:`image_shape`."""

    @property
    def image_shape(self) -> tuple[int, ...]:
        """Shape of the unknown image, e.g. ``(C, H, W)``."""
        ...

    def value(self, x: torch.Tensor) -> float:
        """``f(x)``."""
        ...

    def descent_direction(self, x: torch.Tensor) -> tuple[torch.Tensor, float]:
        """A descent direction ``D`` of ``f`` at ``x`` (shape of ``x``) and ``f(x)``."""
        ...


class Prior(Protocol):
    """The prior's step of ADMM: ``X`` from ``Z = I - L`` (eq. 21-23 and 29 for NLSTR).

    A prior may keep state between the iterations of one run (e.g. NLSTR's block-matching
    schedule); :meth:`begin` starts a new run.
    """

    def begin(self) -> None:
        """Forget the previous run (the solver calls it before its first iteration)."""
        ...

    def estimate(self, z: torch.Tensor, *, mu: float, iteration: int,
                 stage: StageFactory) -> tuple[torch.Tensor, dict]:
        """``X`` (shape of ``z``) for ADMM iteration ``iteration`` (0-based) with penalty ``mu``.

        For a regularizer ``R`` this is ``prox_{R/mu}(z) = argmin_X R(X) + mu/2 ||X - z||^2``.
        Returns ``X`` and the fields the prior adds to the iteration's history entry (e.g.
        its regularizer value). ``stage(name)`` times the prior's own steps.
        """
        ...

    def after_step(self, *, iteration: int, change: float) -> dict:
        """Called once the image is updated; ``change`` is ``||I^{i+1} - I^i|| / ||I^i||``.

        Returns further history fields (e.g. when the prior will next re-match blocks).
        """
        ...


class StoppingRule(Protocol):
    """When an iterative solver stops, and which iterate it returns (e.g. the held-out validation of
    :class:`capssim.reconstruct.selection.holdout.HoldoutValidation`). Without one a solver runs its iteration
    count and returns the last iterate."""

    def begin(self, init: torch.Tensor) -> dict:
        """Start a run from ``init``; what it measured of ``init`` (reported again by the first :meth:`update`)."""
        ...

    def update(self, iteration: int, image: torch.Tensor) -> dict:
        """After iteration ``iteration`` (1-based) produced ``image``; fields for its history entry
        (:func:`close_entry` adds them)."""
        ...

    @property
    def should_stop(self) -> bool:
        """True when the solver should stop after the iteration just reported."""
        ...

    def final(self, image: torch.Tensor) -> torch.Tensor:
        """The image the solver returns, given its last iterate ``image``."""
        ...


def check_initial_estimate(data: DataFidelity, init: torch.Tensor) -> None:
    """:class:`InputError` unless ``init`` has the data term's image shape and finite values."""
    if tuple(init.shape) != tuple(data.image_shape):
        raise InputError("init", f"shape {tuple(init.shape)}", f"shape {data.image_shape}")
    if not bool(torch.isfinite(init).all()):
        raise InputError("init", "non-finite values", "a finite initial estimate")


#: an iterate whose largest magnitude exceeds this many times ``max(1, max|init|)`` has diverged
#: (images are on [0, 1] of full scale; a converging solver overshoots by far less)
DIVERGENCE_FACTOR = 10.0


class DivergenceError(InputError, FloatingPointError):
    """A solver's iterates left the bounded range (or became non-finite): an option is outside its stable range
    (a :class:`~capssim.errors.InputError`, and a ``FloatingPointError`` as before).

    ``argument`` names the option to change (``dt`` unless the caller knows better).
    """

    def __init__(self, argument: str, received: object, *, solver: str, iteration: int, peak: float, bound: float,
                 fix: str):
        self.solver, self.iteration, self.peak, self.bound = solver, iteration, peak, bound
        super().__init__(argument, received, f"a value under which {solver} converges ({solver} diverged at "
                         f"iteration {iteration}: the image reached |I| = {peak:.3g}, over the bound {bound:.3g})",
                         fix)


def divergence_bound(init: torch.Tensor) -> float:
    """The magnitude past which an iterate counts as diverged: ``DIVERGENCE_FACTOR * max(1, max|init|)``."""
    return DIVERGENCE_FACTOR * max(1.0, float(init.abs().max()))


def check_finite(x: torch.Tensor, *, iteration: int, dt: float, solver: str, bound: float = math.inf) -> None:
    """:class:`DivergenceError` if iteration ``iteration`` (1-based) produced non-finite values or ``|x| > bound``."""
    peak = float(x.abs().max()) if x.numel() else 0.0
    if not peak <= bound:  # also true for NaN
        raise DivergenceError("dt", dt, solver=solver, iteration=iteration, peak=peak, bound=bound,
                              fix="Reduce dt (the paper's default is 1.0), or return the options changed "
                                  "from their defaults to them, or check the observations.")


def relative_change(new: torch.Tensor, old: torch.Tensor) -> float:
    """``||new - old|| / ||old||`` (the denominator floored at 1e-12)."""
    return float(torch.linalg.vector_norm(new - old)) / max(float(torch.linalg.vector_norm(old)), 1e-12)


def close_entry(entry: dict, image: torch.Tensor, *, history: list[dict], iterations: int, solver: str,
                observer: Observer | None, progress: Progress | None, stopping: StoppingRule | None = None) -> bool:
    """Add the stopping rule's and the observer's fields to ``entry``, append it to ``history``, log and report
    progress; True when ``stopping`` says the solver should stop after this iteration."""
    step = entry["iteration"]
    if stopping is not None:
        entry.update(stopping.update(step, image) or {})
    if observer is not None:
        entry.update(observer(step, image) or {})
    history.append(entry)
    log.debug("%s %d/%d %s", solver, step, iterations, entry)
    if progress is not None:
        progress(step, iterations, f"objective {entry['objective']:.4g}")
    return stopping is not None and stopping.should_stop


__all__ = ["DIVERGENCE_FACTOR", "DataFidelity", "DivergenceError", "Observer", "Prior", "Progress", "StageFactory", "StoppingRule", "check_finite",
           "check_initial_estimate", "close_entry", "divergence_bound", "no_stage", "relative_change"]
