"""ADMM with adaptive parameters (paper section 4, eq. 20-30; Algorithm 1).

Iteration ``i`` (``L`` the Lagrangian multiplier, ``Z = I - L``):

1. the prior's estimate ``X`` of ``Z`` (:class:`~capssim.reconstruct.solvers.interfaces.Prior`): for
   CAPS the dictionaries (eq. 21) and tensor cores (eq. 22-23) of ``Z`` aggregated into
   ``X`` (eq. 29), with the prior's own block-matching schedule
   (:class:`capssim.reconstruct.priors.nlstr_prior.NLSTRPrior`);
2. ``mu_i = min(mu0 + grow_rate * floor(i / grow_step), 1)`` (eq. 27);
3. one gradient step on all channels together (eq. 28):
   ``I <- I - dt (mu G - D)`` with ``D`` the data term's descent direction
   (:class:`~capssim.reconstruct.solvers.interfaces.DataFidelity`; for CAPS the confidence-guided
   direction of eq. 26) and ``G = Z - X`` (eq. 25 with its bracket read as the per-pixel
   normalization of eq. 29, see docs/notes/solver.md);
4. ``L <- L - (I - X)`` (eq. 30).

The solver knows neither NLSTR nor the confidence data term: any pair of objects with
those two interfaces runs here (e.g. :class:`capssim.reconstruct.priors.tikhonov.TikhonovPrior`).
The data-only ablation (eq. 16) is :func:`capssim.reconstruct.solvers.descent.steepest_descent`.

The history records per iteration ``mu``, the prior's fields, the data term ``f(I)``, the
energies of eq. 24 around the step, the constraint and dual residuals and the objective
(see :func:`admm`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch

from capssim.errors import InputError
from capssim.runtime.resources import check_range

from .interfaces import (
    DataFidelity,
    Observer,
    Prior,
    Progress,
    StageFactory,
    StoppingRule,
    check_finite,
    check_initial_estimate,
    close_entry,
    divergence_bound,
    no_stage,
    relative_change,
)

#: the most iterations one run may ask for (a sane range: the paper uses 25; divergence tests a few thousand)
MAX_ITERATIONS = 10_000


@dataclass(frozen=True)
class ADMMParameters:
    """The penalty schedule of eq. 27 and the step of eq. 28 (paper section 5.1 defaults)."""

    iterations: int = 25
    mu0: float = 0.5
    grow_rate: float = 0.1
    grow_step: int = 5
    dt: float = 1.0

    def validate(self) -> None:
        if self.iterations < 0:
            raise InputError("iterations", self.iterations, "an integer >= 0")
        check_range("iterations", self.iterations, high=MAX_ITERATIONS, what="the number of iterations",
                    reason="the time grows with it; the paper uses 25", fix="Try --iterations 25.")
        for name in ("mu0", "dt"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise InputError(name, v, "a finite positive number")
        if self.mu0 > 1:
            raise InputError("mu0", self.mu0, "a number in (0, 1] (eq. 27 caps mu at 1)")
        if not (self.grow_rate >= 0 and math.isfinite(self.grow_rate)):
            raise InputError("grow_rate", self.grow_rate, "a finite number >= 0")
        if self.grow_step < 1:
            raise InputError("grow_step", self.grow_step, "an integer >= 1")

    def to_dict(self) -> dict:
        return asdict(self)


def mu_schedule(i: int, params: ADMMParameters) -> float:
    """Eq. 27: ``min(mu0 + grow_rate * fix(i / grow_step), 1.0)``."""
    return min(params.mu0 + params.grow_rate * (i // params.grow_step), 1.0)


def admm(data: DataFidelity, init: torch.Tensor, prior: Prior, params: ADMMParameters = ADMMParameters(), *,
         stage: StageFactory | None = None, progress: Progress | None = None,
         observer: Observer | None = None, stopping: StoppingRule | None = None) -> tuple[torch.Tensor, list[dict]]:
    """Run the ADMM of section 4 from ``init`` (``data.image_shape``); return the image and the history.

    ``stage(name)`` is an optional context-manager factory timing each step
    (``StageTimer.stage``). History entry ``i`` describes iteration ``i + 1`` and its
    result ``I^{i+1}``:

    * ``mu``, then the fields of ``prior.estimate`` (for NLSTR: ``n_similar``,
      ``rematched``, ``zero_fraction``);
    * ``data``: ``f(I^{i+1})``; ``change``: ``||I^{i+1} - I^i|| / ||I^i||``;
    * ``energy_before`` / ``energy_after``: eq. 24, ``f(I) + mu/2 ||I - L - X||^2``, before
      and after the gradient step of eq. 28 (same ``L``, ``X``);
    * ``primal_residual``: ``||I^{i+1} - X^{i+1}|| / sqrt(n)`` (the constraint ``I = X``);
    * ``dual_residual``: ``mu ||X^{i+1} - X^i|| / sqrt(n)``;
    * ``objective``: the combined residual ``(||I^{i+1} - X^{i+1}||^2 + ||X^{i+1} - X^i||^2) / n``
      (``X^0 = I^0``). The paper's eq. 18 has no fixed value to track: its weights
      ``lambda_k``, ``eta_k``, ``mu`` and the groups are re-derived at every iteration.
      The combined residual is the standard convergence measure of ADMM and is
      non-increasing for fixed parameters (Goldstein et al., SIAM J. Imaging Sci. 2014);
      it jumps only where ``mu`` steps up or the prior changes (e.g. re-matched blocks);
    * the fields of ``prior.after_step`` (for NLSTR: ``next_match`` after a matching).

    ``observer(i, image)`` may return extra fields for entry ``i`` (e.g. a PSNR when the
    ground truth is known; diagnostics only, never used by the algorithm).

    ``stopping`` (a :class:`~capssim.reconstruct.solvers.interfaces.StoppingRule`, optional) may end the run
    before ``params.iterations`` and chooses the iterate returned (e.g. the best by held-out validation);
    its fields join the history entries.
    """
    params.validate()
    check_initial_estimate(data, init)
    timed = stage or no_stage
    prior.begin()
    x = init.clone()
    bound = divergence_bound(init)
    lag = torch.zeros_like(x)
    history: list[dict] = []
    mu_prev = None
    xs_prev = x  # X^0 = I^0: ADMM starts at consensus
    n = x.numel()
    if stopping is not None:
        stopping.begin(init)
    for i in range(params.iterations):
        mu = mu_schedule(i, params)
        if mu_prev is not None and mu != mu_prev:
            lag.mul_(mu_prev / mu)  # scaled multiplier follows the penalty (Boyd et al. 2011, 3.4.1)
        entry: dict = {"iteration": i + 1, "mu": mu}
        z = x - lag
        xs, prior_fields = prior.estimate(z, mu=mu, iteration=i, stage=timed)
        entry.update(prior_fields)
        with timed("data_term"):
            direction, f_old = data.descent_direction(x)
        with timed("admm_update"):
            energy_before = f_old + 0.5 * mu * float((z - xs).square().sum())
            x_new = x - params.dt * (mu * (z - xs) - direction)
            change = relative_change(x_new, x)
        check_finite(x_new, iteration=i + 1, dt=params.dt, solver="ADMM", bound=bound)
        with timed("data_term"):
            f_new = data.value(x_new)
        with timed("admm_update"):
            entry.update({"data": f_new, "change": change, "energy_before": energy_before})
            entry["energy_after"] = f_new + 0.5 * mu * float((x_new - lag - xs).square().sum())
            lag = lag - (x_new - xs)
            primal = float((x_new - xs).square().sum())
            dual = float((xs - xs_prev).square().sum())
            entry["primal_residual"] = math.sqrt(primal / n)
            entry["dual_residual"] = mu * math.sqrt(dual / n)
            entry["objective"] = (primal + dual) / n
            xs_prev = xs
            entry.update(prior.after_step(iteration=i, change=change))
            x = x_new
            mu_prev = mu
        if close_entry(entry, x, history=history, iterations=params.iterations, solver="ADMM",
                       observer=observer, progress=progress, stopping=stopping):
            break
    return (x if stopping is None else stopping.final(x)), history


__all__ = ["ADMMParameters", "admm", "mu_schedule"]
