"""ADMM with adaptive parameters (paper section 4, eq. 20-30; Algorithm 1).

Iteration ``i`` (``L`` the Lagrangian multiplier, ``Z = I - L``):

1. dictionaries (eq. 21) and tensor cores (eq. 22-23) of ``Z``, aggregated into ``X``
   (eq. 29), by :class:`reconstruct.nlstr.NonlocalSparseTensor`; block matching is
   redone only when the adaptive rule below says so, with 5 fewer similar blocks each time;
2. ``mu_i = min(mu0 + grow_rate * floor(i / grow_step), 1)`` (eq. 27);
3. one gradient step on all channels together (eq. 28):
   ``I <- I - dt (mu G - D)`` with ``D`` the confidence-guided data direction (eq. 26,
   :class:`reconstruct.data_term.ConfidenceDataTerm`) and ``G = Z - X`` (eq. 25 with its
   bracket read as the per-pixel normalization of eq. 29: with the plain overlap count
   the step would be 16x larger and ``dt = 1`` diverges);
4. ``L <- L - (I - X)`` (eq. 30).

Adaptive block matching (section 5.1, after the paper's ref. [59]): after the first
iteration following a matching, the relative change ``delta`` of ``I`` between two
successive iterations predicts how many iterations it takes to change ``I`` by
``rematch_change`` (relative); the next matching is scheduled that many iterations later
(at least ``rematch_min_gap``, at most ``rematch_max_gap``).

Without NLSTR (``nlstr=None``, the ``caps-no-nlstr`` ablation) the iteration is the plain
confidence-guided steepest descent of eq. 16: ``I <- I + dt D``.

The history records per iteration: ``mu``, the number of similar blocks, whether blocks
were re-matched, the data term ``f(I)``, the regularizer terms of eq. 20 at the new
cores, the constraint residual ``||I - X||`` and the objective (see :func:`admm`).
"""

from __future__ import annotations

import logging
import math
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from typing import Callable

import torch

from capssim.errors import InputError
from capssim.reconstruct.data_term import ConfidenceDataTerm
from capssim.reconstruct.nlstr import NonlocalSparseTensor

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ADMMParameters:
    """Paper section 5.1 defaults."""

    iterations: int = 25
    mu0: float = 0.5
    grow_rate: float = 0.1
    grow_step: int = 5
    dt: float = 1.0
    n_similar: int = 40
    n_similar_step: int = 5
    n_similar_min: int = 10
    rematch_change: float = 0.02
    rematch_min_gap: int = 2
    rematch_max_gap: int = 10

    def validate(self) -> None:
        if self.iterations < 0:
            raise InputError("iterations", self.iterations, "an integer >= 0")
        for name in ("mu0", "dt", "rematch_change"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise InputError(name, v, "a finite positive number")
        if not (self.grow_rate >= 0 and math.isfinite(self.grow_rate)):
            raise InputError("grow_rate", self.grow_rate, "a finite number >= 0")
        if self.grow_step < 1:
            raise InputError("grow_step", self.grow_step, "an integer >= 1")
        if self.n_similar < 1 or self.n_similar_min < 1 or self.n_similar_step < 0:
            raise InputError("n_similar", (self.n_similar, self.n_similar_step, self.n_similar_min),
                             "n_similar >= 1, n_similar_step >= 0, n_similar_min >= 1")
        if not 1 <= self.rematch_min_gap <= self.rematch_max_gap:
            raise InputError("rematch_min_gap", (self.rematch_min_gap, self.rematch_max_gap),
                             "1 <= rematch_min_gap <= rematch_max_gap")

    def to_dict(self) -> dict:
        return asdict(self)


def mu_schedule(i: int, params: ADMMParameters) -> float:
    """Eq. 27: ``min(mu0 + grow_rate * fix(i / grow_step), 1.0)``."""
    return min(params.mu0 + params.grow_rate * (i // params.grow_step), 1.0)


def _norm(t: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm(t))


def admm(data: ConfidenceDataTerm, init: torch.Tensor, nlstr: NonlocalSparseTensor | None,
         params: ADMMParameters = ADMMParameters(), *, stage=None,
         progress: Callable[[int, int, str], None] | None = None,
         observer: Callable[[int, torch.Tensor], dict | None] | None = None) -> tuple[torch.Tensor, list[dict]]:
    """Run the ADMM of section 4 from ``init`` ``(C, H, W)``; return the image and the history.

    ``stage(name)`` is an optional context-manager factory timing each step
    (``StageTimer.stage``). History entry ``i`` describes iteration ``i + 1`` and its
    result ``I^{i+1}``:

    * ``mu``, ``n_similar``, ``rematched`` (block matching redone at this iteration);
    * ``data``: ``f(I^{i+1}) = 1/2 sum_m ||w (y_m - M_m I^{i+1})||^2``;
    * ``energy_before`` / ``energy_after``: eq. 24, ``f(I) + mu/2 ||I - L - X||^2``, before
      and after the gradient step of eq. 28 (same ``L``, ``X``);
    * ``primal_residual``: ``||I^{i+1} - X^{i+1}|| / sqrt(n)`` (the constraint ``I = X``);
    * ``dual_residual``: ``mu ||X^{i+1} - X^i|| / sqrt(n)``;
    * ``objective``: the combined residual ``(||I^{i+1} - X^{i+1}||^2 + ||X^{i+1} - X^i||^2) / n``
      (``X^0 = I^0``). The paper's eq. 18 has no fixed value to track: its weights
      ``lambda_k``, ``eta_k``, ``mu`` and the groups are re-derived at every iteration.
      The combined residual is the standard convergence measure of ADMM and is
      non-increasing for fixed parameters (Goldstein et al., SIAM J. Imaging Sci. 2014);
      it jumps only where ``mu`` steps up or blocks are re-matched. For
      ``caps-no-nlstr`` the objective is the data term ``f``.
    * ``zero_fraction`` of the tensor cores, ``change`` ``||I^{i+1} - I^i|| / ||I^i||``.

    ``observer(i, image)`` may return extra fields for entry ``i`` (e.g. a PSNR when the
    ground truth is known; diagnostics only, never used by the algorithm).
    """
    params.validate()
    if tuple(init.shape) != data.image_shape:
        raise InputError("init", f"shape {tuple(init.shape)}", f"shape {data.image_shape}")
    if not bool(torch.isfinite(init).all()):
        raise InputError("init", "non-finite values", "a finite initial estimate")
    timed = stage or (lambda name: nullcontext())
    x = init.clone()
    lag = torch.zeros_like(x)
    history: list[dict] = []
    n_similar = params.n_similar
    matches = None
    next_match = 0
    last_match = -1
    mu_prev = None
    xs_prev = x  # X^0 = I^0: ADMM starts at consensus
    n = x.numel()
    for i in range(params.iterations):
        mu = mu_schedule(i, params)
        if mu_prev is not None and mu != mu_prev:
            lag.mul_(mu_prev / mu)  # scaled multiplier follows the penalty (Boyd et al. 2011, 3.4.1)
        entry: dict = {"iteration": i + 1, "mu": mu}
        if nlstr is not None:
            z = x - lag
            rematched = matches is None or i >= next_match
            if rematched:
                with timed("nlstr_block_matching"):
                    matches = nlstr.match(z, n_similar)
                last_match = i
                n_similar = max(params.n_similar_min, n_similar - params.n_similar_step)
            with timed("nlstr_dictionaries_cores"):
                xs, st = nlstr.estimate(z, matches)
            entry.update({"n_similar": matches.n_similar, "rematched": bool(rematched),
                          "zero_fraction": st["zero_fraction"]})
        with timed("data_term"):
            direction, f_old = data.descent_direction(x)
        with timed("admm_update"):
            if nlstr is not None:
                energy_before = f_old + 0.5 * mu * float((z - xs).square().sum())
                x_new = x - params.dt * (mu * (z - xs) - direction)
            else:
                energy_before = f_old
                x_new = x + params.dt * direction
            change = _norm(x_new - x) / max(_norm(x), 1e-12)
        if not bool(torch.isfinite(x_new).all()):
            raise FloatingPointError(f"ADMM diverged at iteration {i + 1} (non-finite values); "
                                     f"reduce dt (now {params.dt}) or check the observations")
        with timed("data_term"):
            f_new = data.value(x_new)
        with timed("admm_update"):
            entry.update({"data": f_new, "change": change, "energy_before": energy_before})
            if nlstr is not None:
                entry["energy_after"] = f_new + 0.5 * mu * float((x_new - lag - xs).square().sum())
                lag = lag - (x_new - xs)
                primal = float((x_new - xs).square().sum())
                dual = float((xs - xs_prev).square().sum())
                entry["primal_residual"] = math.sqrt(primal / n)
                entry["dual_residual"] = mu * math.sqrt(dual / n)
                entry["objective"] = (primal + dual) / n
                xs_prev = xs
                if i == last_match:
                    gap = math.ceil(params.rematch_change / max(change, 1e-12))
                    next_match = i + min(max(gap, params.rematch_min_gap), params.rematch_max_gap)
                    entry["next_match"] = next_match + 1
            else:
                entry["energy_after"] = f_new
                entry["objective"] = f_new
            x = x_new
            mu_prev = mu
        if observer is not None:
            entry.update(observer(i + 1, x) or {})
        history.append(entry)
        log.debug("ADMM %d/%d %s", i + 1, params.iterations, entry)
        if progress is not None:
            progress(i + 1, params.iterations, f"objective {entry['objective']:.4g}")
    return x, history


__all__ = ["ADMMParameters", "admm", "mu_schedule"]
