"""Limited-memory BFGS with a strong-Wolfe line search, on one flat torch tensor.

References: J. Nocedal, S. J. Wright, *Numerical Optimization*, 2nd ed., Springer 2006:
Algorithm 7.4 (the two-loop recursion, initial scaling ``gamma = s.y / y.y``, eq. 7.20),
Algorithms 3.5 and 3.6 (line search for the strong Wolfe conditions, eq. 3.7, and *zoom*),
eq. 3.59 (the cubic interpolant of two points with their slopes).

The decisions (first step ``min(1, 1 / |g|_1)``, curvature pairs kept only when ``s.y > 1e-10``,
extrapolation into ``[t + 0.01 (t - t_prev), 10 t]``, the zoom's safeguard 0.1 of the bracket from
its ends, a line search of at most 26 evaluations, the stopping tests) are those of
``torch.optim.LBFGS(line_search_fn="strong_wolfe")``, so both give the same iterates to rounding.
This implementation exists because the first ``torch.optim`` optimizer of a process imports
``torch._dynamo`` (about 1 s on one core), more than a whole registration's line searches.

Every scalar decision is taken on the host (``float``), as torch's optimizer does; the vectors
stay on their device.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

#: ``x -> (f(x), grad f(x))``: the value as a float, the gradient as a tensor shaped like ``x``.
Objective = Callable[[torch.Tensor], tuple[float, torch.Tensor]]

SUFFICIENT_DECREASE, CURVATURE = 1e-4, 0.9  # c1, c2 of the strong Wolfe conditions (N&W eq. 3.7)
MAX_LINE_SEARCH_EVALUATIONS = 25


def cubic_minimizer(t1: float, f1: float, g1: float, t2: float, f2: float, g2: float,
                    bounds: tuple[float, float] | None = None) -> float:
    """Minimiser of the cubic through ``(t1, f1)`` and ``(t2, f2)`` with slopes ``g1``, ``g2``
    (N&W eq. 3.59), clipped to ``bounds`` (default: between the two points); the middle of the
    bounds when the cubic has no minimum."""
    low, high = bounds if bounds is not None else (min(t1, t2), max(t1, t2))
    d1 = g1 + g2 - 3 * (f1 - f2) / (t1 - t2)
    d2_square = d1 * d1 - g1 * g2
    if d2_square < 0:
        return (low + high) / 2
    d2 = math.sqrt(d2_square)
    if t1 <= t2:
        t = t2 - (t2 - t1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
    else:
        t = t1 - (t1 - t2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
    return min(max(t, low), high)


class _Point:
    """One trial step ``t`` along the search direction: value, gradient, slope ``g.d``."""

    __slots__ = ("t", "f", "g", "slope")

    def __init__(self, t: float, f: float, g: torch.Tensor, slope: float):
        self.t, self.f, self.g, self.slope = t, f, g, slope


def strong_wolfe_search(objective: Objective, x: torch.Tensor, direction: torch.Tensor, start: _Point,
                        t: float, *, tolerance_change: float) -> tuple[_Point, int]:
    """Step along ``direction`` from ``x`` satisfying the strong Wolfe conditions (N&W Algorithms
    3.5-3.6). ``start`` is the point at ``t = 0``; ``t`` the first trial step. Returns the accepted
    point and the number of evaluations."""

    def trial(step: float) -> _Point:
        f, g = objective(x + step * direction)
        return _Point(step, f, g, float(g.dot(direction)))

    def sufficient(p: _Point) -> bool:
        return p.f <= start.f + SUFFICIENT_DECREASE * p.t * start.slope

    def flat_enough(p: _Point) -> bool:
        return abs(p.slope) <= -CURVATURE * start.slope

    new, previous, evaluations = trial(t), start, 1
    bracket = None
    while evaluations <= MAX_LINE_SEARCH_EVALUATIONS:
        if not sufficient(new) or (evaluations > 2 and new.f >= previous.f):
            bracket = [previous, new]
            break
        if flat_enough(new):
            return new, evaluations
        if new.slope >= 0:
            bracket = [previous, new]
            break
        step = cubic_minimizer(previous.t, previous.f, previous.slope, new.t, new.f, new.slope,
                               bounds=(new.t + 0.01 * (new.t - previous.t), 10 * new.t))
        previous, new = new, trial(step)
        evaluations += 1
    if bracket is None:  # no bracket within the budget: the better end of [0, t]
        return (start if start.f <= new.f else new), evaluations
    return _zoom(trial, bracket, evaluations, sufficient, flat_enough,
                 direction_scale=float(direction.abs().max()), tolerance_change=tolerance_change)


def _zoom(trial, bracket, evaluations, sufficient, flat_enough, *, direction_scale: float,
          tolerance_change: float) -> tuple[_Point, int]:
    """N&W Algorithm 3.6 with cubic trial steps kept 10 % of the bracket from its ends after one
    step of insufficient progress. ``bracket[low]`` is the lower of its two values."""
    low = 0 if bracket[0].f <= bracket[1].f else 1
    stalled = False
    while evaluations <= MAX_LINE_SEARCH_EVALUATIONS:
        a, b = bracket
        if abs(b.t - a.t) * direction_scale < tolerance_change:
            break
        t = cubic_minimizer(a.t, a.f, a.slope, b.t, b.f, b.slope)
        top, bottom = max(a.t, b.t), min(a.t, b.t)
        margin = 0.1 * (top - bottom)
        if min(top - t, t - bottom) < margin:
            if stalled or t >= top or t <= bottom:
                t = top - margin if abs(t - top) < abs(t - bottom) else bottom + margin
                stalled = False
            else:
                stalled = True
        else:
            stalled = False
        new = trial(t)
        evaluations += 1
        high = 1 - low
        if not sufficient(new) or new.f >= bracket[low].f:
            bracket[high] = new
        else:
            if flat_enough(new):
                bracket[low] = new
                return new, evaluations
            if new.slope * (bracket[high].t - bracket[low].t) >= 0:
                bracket[high] = bracket[low]
            bracket[low] = new
        low = 0 if bracket[0].f <= bracket[1].f else 1
    return bracket[low], evaluations


def _two_loop(gradient: torch.Tensor, steps: list[torch.Tensor], changes: list[torch.Tensor],
              gamma: float) -> torch.Tensor:
    """``-H g`` by the two-loop recursion (N&W Algorithm 7.4) with ``H0 = gamma I``."""
    q = -gradient
    rho = [1.0 / float(y.dot(s)) for s, y in zip(steps, changes)]
    alpha = [0.0] * len(steps)
    for i in range(len(steps) - 1, -1, -1):
        alpha[i] = float(steps[i].dot(q)) * rho[i]
        q = q - alpha[i] * changes[i]
    r = q * gamma
    for i in range(len(steps)):
        beta = float(changes[i].dot(r)) * rho[i]
        r = r + (alpha[i] - beta) * steps[i]
    return r


class Memory:
    """The curvature pairs ``(s, y)`` and the scale ``gamma`` of an L-BFGS run, to start a related
    problem (the next pyramid level) from them instead of from steepest descent."""

    def __init__(self):
        self.steps: list[torch.Tensor] = []
        self.changes: list[torch.Tensor] = []
        self.gamma = 1.0


def minimize_lbfgs(objective: Objective, x0: torch.Tensor, *, max_iterations: int, tolerance_grad: float,
                   tolerance_change: float, history_size: int = 20,
                   max_evaluations: int | None = None, memory: Memory | None = None) -> tuple[torch.Tensor, int, int]:
    """Minimise ``objective`` from ``x0`` (any shape; treated as one vector).

    Stops at ``max_iterations`` iterations or ``max_evaluations`` evaluations (default 1.25x the
    iterations), when the gradient's max-norm is at most ``tolerance_grad``, or when a step, its
    change of value or the directional derivative falls below ``tolerance_change``.
    ``memory``: curvature pairs to start from (a warm start: the first step is the quasi-Newton one,
    not steepest descent), updated in place; pairs of another shape are dropped.
    Returns ``(x, iterations, evaluations)``.
    """
    max_evaluations = max_iterations * 5 // 4 if max_evaluations is None else max_evaluations
    shape = x0.shape

    def flat_objective(x: torch.Tensor) -> tuple[float, torch.Tensor]:
        f, g = objective(x.reshape(shape))
        return f, g.reshape(-1)

    x = x0.detach().reshape(-1).clone()
    f, g = flat_objective(x)
    evaluations, iterations = 1, 0
    if float(g.abs().max()) <= tolerance_grad:
        return x.reshape(shape), iterations, evaluations
    memory = Memory() if memory is None else memory
    if memory.steps and memory.steps[0].shape != x.shape:
        memory.steps, memory.changes, memory.gamma = [], [], 1.0
    steps, changes, gamma = memory.steps, memory.changes, memory.gamma
    warm = bool(steps)
    direction = _two_loop(g, steps, changes, gamma) if warm else -g
    g_previous, t = g, 1.0
    while True:
        iterations += 1
        if iterations > 1:
            change, step = g - g_previous, direction * t
            curvature = float(change.dot(step))
            if curvature > 1e-10:
                if len(steps) == history_size:
                    del steps[0], changes[0]
                steps.append(step)
                changes.append(change)
                gamma = memory.gamma = curvature / float(change.dot(change))
            direction = _two_loop(g, steps, changes, gamma)
        g_previous, f_previous = g, f
        t = min(1.0, 1.0 / float(g.abs().sum())) if iterations == 1 and not warm else 1.0
        slope = float(g.dot(direction))
        if slope > -tolerance_change:
            break
        accepted, used = strong_wolfe_search(flat_objective, x, direction, _Point(0.0, f, g, slope), t,
                                             tolerance_change=tolerance_change)
        t, f, g = accepted.t, accepted.f, accepted.g
        x = x + t * direction
        evaluations += used
        if (iterations == max_iterations or evaluations >= max_evaluations
                or float(g.abs().max()) <= tolerance_grad
                or float((direction * t).abs().max()) <= tolerance_change
                or abs(f - f_previous) < tolerance_change):
            break
    return x.reshape(shape), iterations, evaluations
