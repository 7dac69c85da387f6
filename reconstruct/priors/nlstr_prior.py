"""NLSTR as the prior of ADMM, with its adaptive block-matching schedule (paper section 4, 5.1).

:class:`NLSTRPrior` is the :class:`~capssim.reconstruct.solvers.interfaces.Prior` of CAPS: at each
ADMM iteration it gives the aggregated sparse estimate ``X`` of ``Z = I - L`` (eq. 21-23,
29) by :class:`~capssim.reconstruct.priors.nlstr.NonlocalSparseTensor`, and decides itself when to
redo the block matching of section 3.3.

Adaptive block matching (section 5.1, after the paper's ref. [59]): the first iteration
matches ``n_similar`` blocks; each matching lowers the count by ``n_similar_step``, down to
``n_similar_min``. After the iteration of a matching, the relative change ``delta`` of
``I`` in that iteration predicts how many iterations it takes to change ``I`` by
``rematch_change`` (relative); the next matching is scheduled that many iterations later
(at least ``rematch_min_gap``, at most ``rematch_max_gap``).

Dictionaries (eq. 21): Algorithm 1 recomputes them at every iteration (``dictionary_gap = 1``).
With ``dictionary_gap = g`` (default 5) they are recomputed at every matching and then every ``g``
iterations, and reused in between: the groups are the same and ``Z`` has changed little. This
saves about 40 % of the NLSTR time at no measurable cost (-0.002 to +0.08 dB mean and DoLP PSNR on
qiu-kettle and a rendered ``textured`` scene at 512 px, docs/notes/reconstruction-speed.md).

The thresholds of eq. 23 are ratios ``lambda_k / mu`` and ``eta_k / mu`` derived from the
cores themselves (section 4), so the estimate does not depend on ``mu``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch

from capssim.errors import InputError

from ..solvers.interfaces import StageFactory
from .nlstr import BlockMatches, NonlocalSparseTensor


@dataclass(frozen=True)
class MatchSchedule:
    """When NLSTR re-matches blocks, and how many (paper section 5.1 defaults)."""

    n_similar: int = 40
    n_similar_step: int = 5
    n_similar_min: int = 10
    rematch_change: float = 0.02
    rematch_min_gap: int = 2
    rematch_max_gap: int = 10
    dictionary_gap: int = 5

    def validate(self) -> None:
        if isinstance(self.dictionary_gap, bool) or not isinstance(self.dictionary_gap, int) \
                or self.dictionary_gap < 1:
            raise InputError("dictionary_gap", self.dictionary_gap,
                             "an integer >= 1 (iterations between dictionary updates; 1 = every iteration)")
        if not (self.rematch_change > 0 and math.isfinite(self.rematch_change)):
            raise InputError("rematch_change", self.rematch_change, "a finite positive number")
        if self.n_similar < 1 or self.n_similar_min < 1 or self.n_similar_step < 0:
            raise InputError("n_similar", (self.n_similar, self.n_similar_step, self.n_similar_min),
                             "n_similar >= 1, n_similar_step >= 0, n_similar_min >= 1")
        if self.n_similar_min > self.n_similar:  # the count only goes down, from n_similar to n_similar_min
            raise InputError("n_similar_min", self.n_similar_min, f"at most n_similar ({self.n_similar}): each "
                             "matching lowers the block count from n_similar down to n_similar_min",
                             f"Set -p n_similar_min={self.n_similar} or less, or raise n_similar.")
        if not 1 <= self.rematch_min_gap <= self.rematch_max_gap:
            raise InputError("rematch_min_gap", (self.rematch_min_gap, self.rematch_max_gap),
                             "1 <= rematch_min_gap <= rematch_max_gap")

    def next_gap(self, change: float) -> int:
        """Iterations until the next matching, from the relative change of the matching's iteration."""
        gap = math.ceil(self.rematch_change / max(change, 1e-12))
        return min(max(gap, self.rematch_min_gap), self.rematch_max_gap)

    def to_dict(self) -> dict:
        return asdict(self)


class NLSTRPrior:
    """The NLSTR step of ADMM (a :class:`~capssim.reconstruct.solvers.interfaces.Prior`).

    ``operator`` is the :class:`NonlocalSparseTensor` of the image shape; ``schedule`` says
    when to re-match. One instance serves several runs (:meth:`begin` resets the schedule).
    """

    def __init__(self, operator: NonlocalSparseTensor, schedule: MatchSchedule = MatchSchedule()):
        schedule.validate()
        self.operator = operator
        self.schedule = schedule
        self.begin()

    def record(self) -> dict:
        """What a method's record keeps of the prior: ``n_groups`` (reference blocks) and ``strips``."""
        return {"n_groups": self.operator.n_ref, "strips": len(self.operator.strips)}

    def begin(self) -> None:
        self._n_similar = self.schedule.n_similar
        self._matches: BlockMatches | None = None
        self._next_match = 0
        self._last_match = -1
        self._last_dictionaries = -1

    def estimate(self, z: torch.Tensor, *, mu: float, iteration: int,
                 stage: StageFactory) -> tuple[torch.Tensor, dict]:
        """``X`` ``(C, H, W)`` of ``z`` (eq. 21-23, 29), re-matching blocks when the schedule says so.

        History fields: ``n_similar`` (blocks per group), ``rematched`` (matched at this
        iteration), ``new_dictionaries`` (dictionaries computed at this iteration, not reused),
        ``zero_fraction`` (of the tensor cores). ``mu`` is not needed (module
        docstring).
        """
        rematched = self._matches is None or iteration >= self._next_match
        if rematched:
            with stage("nlstr_block_matching"):
                self._matches = self.operator.match(z, self._n_similar)
            self._last_match = iteration
            self._n_similar = max(self.schedule.n_similar_min, self._n_similar - self.schedule.n_similar_step)
        reuse = not rematched and iteration - self._last_dictionaries < self.schedule.dictionary_gap
        if not reuse:
            self._last_dictionaries = iteration
        with stage("nlstr_dictionaries_cores"):
            x, stats = self.operator.estimate(z, self._matches, reuse_bases=reuse)
        return x, {"n_similar": self._matches.n_similar, "rematched": bool(rematched),
                   "new_dictionaries": not reuse, "zero_fraction": stats["zero_fraction"]}

    def after_step(self, *, iteration: int, change: float) -> dict:
        """After a matching iteration: schedule the next matching; field ``next_match`` (1-based)."""
        if iteration != self._last_match:
            return {}
        self._next_match = iteration + self.schedule.next_gap(change)
        return {"next_match": self._next_match + 1}


__all__ = ["MatchSchedule", "NLSTRPrior"]
