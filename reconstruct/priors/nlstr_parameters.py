"""The parameters of the nonlocal sparse tensor step (NLSTR, paper section 3.3; defaults of section 5.1).

Block geometry (``block`` side and ``stride`` in HR pixels), block-matching window (``search_radius``,
``match_components``), the adaptive shrinkage constants ``c1`` and ``c2`` (eq. 23) and their
``adaptive`` rule, the similarity weights' ``weight_bandwidth`` (eq. 19) and the working-set bound
``strip_mb`` (MiB). Used by :class:`capssim.reconstruct.priors.nlstr.NonlocalSparseTensor`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from capssim.errors import InputError

__all__ = ["NLSTRParameters"]


#: the largest shrinkage constants ``c1`` and ``c2`` (eq. 23) accepted: 1000x the paper's (section 5.1)
SHRINKAGE_MAX = {"c1": 2.0, "c2": 20.0}


@dataclass(frozen=True)
class NLSTRParameters:
    """Parameters of the nonlocal sparse tensor step (paper 5.1 defaults)."""

    block: int = 8
    stride: int = 4
    search_radius: int = 7
    match_components: int = 0  # block matching on this many principal components of the channels; 0: all
    c1: float = 0.002
    c2: float = 0.02
    adaptive: str = "element"
    weight_bandwidth: float = 1.0
    eps: float = 1e-8
    strip_mb: float = 64.0  # working-set bound of one strip of reference rows (MiB)

    @property
    def strip_bytes(self) -> int:
        """``strip_mb`` in bytes."""
        return int(self.strip_mb * 2**20)

    def validate(self) -> None:
        for name in ("block", "stride", "search_radius"):
            if isinstance(getattr(self, name), bool) or not isinstance(getattr(self, name), int):
                raise InputError(name, repr(getattr(self, name)), "an integer")
        if self.block < 2:
            raise InputError("block", self.block, "an integer >= 2 (block side in HR pixels)")
        if not 1 <= self.stride <= self.block:
            raise InputError("stride", self.stride, f"an integer in [1, block={self.block}]")
        if self.search_radius < 0:
            raise InputError("search_radius", self.search_radius, "an integer >= 0")
        if isinstance(self.match_components, bool) or not isinstance(self.match_components, int) \
                or self.match_components < 0:
            raise InputError("match_components", repr(self.match_components),
                             "an integer >= 0 (principal components of the channels for block matching; 0: all)")
        for name in ("c1", "c2", "weight_bandwidth", "strip_mb"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise InputError(name, v, "a finite positive number")
        for name, high in SHRINKAGE_MAX.items():  # beyond: NLSTR zeroes (nearly) every coefficient, the output darkens
            if getattr(self, name) > high:
                raise InputError(name, getattr(self, name), f"a number in (0, {high:g}] (1000x the paper's "
                                 f"{getattr(NLSTRParameters, name):g}; more zeroes the sparse estimate)",
                                 f"Try -p {name}={getattr(NLSTRParameters, name):g}.")
        if self.adaptive not in ("element", "block"):
            raise InputError("adaptive", self.adaptive, "'element' or 'block'")
