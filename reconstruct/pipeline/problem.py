"""What the first stages of the CAPS pipeline hand to the rest: one or more reconstruction problems.

The front end of a configuration (registration and operator, :mod:`.front_end` for ``caps``, the
cascade's in ``capssim.reconstruct.methods.caps_iccp``) returns a :class:`FrontEnd`: its
:class:`Problem` values (``caps``: one, the 12 channels from the 16 observations; ``caps-iccp``: three,
one per colour, 4 channels each) and what the record keeps of them. The data term, prior and solver
stages (:mod:`.run`) treat every problem alike.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from capssim.operators.base import LinearOperator

from ..model.rearrange import Observations

__all__ = ["FrontEnd", "Problem"]


@dataclass
class Problem:
    """One reconstruction problem: ``obs.n_channels`` channels of the output from ``obs.count`` observations.

    ``obs``: the data term's observations ``(N, h, w)`` (weights 0 at saturated or out-of-view pixels);
    ``operator``: the sampling operator ``M`` ``(N, H, W) -> (N, h, w)`` (paper eq. 15);
    ``homographies`` ``(N, 3, 3)``: HR reference -> observation pixels (CAGF, eq. 12-14, and the
    initialization); ``seen``: the observations as CAGF and the initialization see them (flat-field
    corrected; ``obs`` itself when the operator has no flat field); ``mixing`` ``(N, C)``: what each
    observation sees of the channels (a calibrated analyzer; ``None``: channel ``c(m)`` alone);
    ``unmix`` ``(C, C)``: the analyzer the fused initialization is unmixed by (``None``: ideal);
    ``channels``: the output channels (of the 12, ``c = 3 p + k``) it reconstructs, in order;
    ``label``: its name in progress messages (``""`` for a single problem); ``history_fields``: what
    each of its history entries also records (e.g. ``{"colour": "R"}``); ``init``: the initial estimate
    ``(C, H, W)`` the front end provides (``None``: the pipeline fuses the observations); ``derived``: maps
    computed from the observations, kept by key so that the front end and the data term compute each once
    (the analyzers' agreement of ``cagf-agree`` and ``init=agree``); ``stopping``: the solver's
    :class:`~capssim.reconstruct.solvers.interfaces.StoppingRule` (``None``: the iteration count).
    """

    obs: Observations
    operator: LinearOperator
    homographies: np.ndarray
    seen: Observations
    mixing: np.ndarray | None = None
    unmix: np.ndarray | None = None
    channels: slice = field(default_factory=lambda: slice(None))
    label: str = ""
    history_fields: dict = field(default_factory=dict)
    init: object = None
    derived: dict = field(default_factory=dict)
    stopping: object = None

    @property
    def hr_shape(self) -> tuple[int, int]:
        """``(H, W)`` of the HR grid (pixels)."""
        return tuple(self.operator.input_shape[1:])

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """``(C, H, W)`` of the unknown image of this problem."""
        return (self.obs.n_channels, *self.hr_shape)


@dataclass
class FrontEnd:
    """A front end's result: the problems, the registration and PSF records, and the method's own record.

    ``params`` are added to the record's ``params`` (e.g. ``channels``), ``extra`` to the record itself
    (e.g. ``field_of_view_weight_fraction``); ``geometry`` is the array geometry the problems were built
    with (:class:`capssim.camera.array_geometry.ArrayGeometry`, or ``None``).
    """

    problems: list[Problem]
    registration: dict
    psf: dict
    params: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    geometry: object = None
