"""Steepest descent on the data term alone (paper eq. 16): the ``caps-no-nlstr`` ablation.

``I <- I + dt D`` with ``D`` the data term's descent direction
(:class:`~capssim.reconstruct.solvers.interfaces.DataFidelity`; for CAPS the confidence-guided
direction of eq. 16), from the same initialization and with the same step ``dt`` and
iteration count as :func:`capssim.reconstruct.solvers.admm.admm`, so that the ablation ("No
NLSTR", section 5.2) differs from CAPS by the prior only.
"""

from __future__ import annotations

import torch

from .admm import ADMMParameters, mu_schedule
from .interfaces import (
    DataFidelity,
    Observer,
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


def steepest_descent(data: DataFidelity, init: torch.Tensor, params: ADMMParameters = ADMMParameters(), *,
                     stage: StageFactory | None = None, progress: Progress | None = None,
                     observer: Observer | None = None, stopping: StoppingRule | None = None
                     ) -> tuple[torch.Tensor, list[dict]]:
    """``params.iterations`` steps of eq. 16 from ``init``; return the image and the history.

    Only ``iterations`` and ``dt`` of ``params`` act. History entry ``i`` holds, for
    iteration ``i + 1``: ``mu`` (eq. 27, recorded only, so that the entries line up with
    ADMM's), ``data`` ``f(I^{i+1})``, ``change`` ``||I^{i+1} - I^i|| / ||I^i||``,
    ``energy_before`` ``f(I^i)``, ``energy_after`` and ``objective`` ``f(I^{i+1})``, then the
    ``observer``'s fields. The steps are timed as ``data_term`` and ``admm_update``, the
    stages of :func:`~capssim.reconstruct.solvers.admm.admm`. ``stopping`` acts as in ADMM.
    """
    params.validate()
    check_initial_estimate(data, init)
    timed = stage or no_stage
    x = init.clone()
    bound = divergence_bound(init)
    history: list[dict] = []
    if stopping is not None:
        stopping.begin(init)
    for i in range(params.iterations):
        entry: dict = {"iteration": i + 1, "mu": mu_schedule(i, params)}
        with timed("data_term"):
            direction, f_old = data.descent_direction(x)
        with timed("admm_update"):
            x_new = x + params.dt * direction
            change = relative_change(x_new, x)
        check_finite(x_new, iteration=i + 1, dt=params.dt, solver="steepest descent", bound=bound)
        with timed("data_term"):
            f_new = data.value(x_new)
        entry.update({"data": f_new, "change": change, "energy_before": f_old, "energy_after": f_new,
                      "objective": f_new})
        x = x_new
        if close_entry(entry, x, history=history, iterations=params.iterations, solver="steepest descent",
                       observer=observer, progress=progress, stopping=stopping):
            break
    return (x if stopping is None else stopping.final(x)), history


__all__ = ["steepest_descent"]
