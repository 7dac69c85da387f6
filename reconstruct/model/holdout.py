"""Held-out raw pixels: a stopping rule for the iterative solvers that reads the scene (not the paper's;
``caps-plus``'s selection layer, :mod:`capssim.reconstruct.selection`).

A fixed random fraction of the raw pixels (every aperture, every Bayer site) is left out of the
reconstruction: its data weight is 0 (eq. 15), the fused initialization (eq. 24) does not see it, and the
demosaicked start sees it filled from its same-colour neighbours. After each solver iteration the image is
predicted at the held-out pixels through the sampling operator ``M`` (eq. 15) and compared with what they
recorded: the mean squared prediction error

    e(I) = sum_m w_m (y_m - (M I)_m)^2 / sum_m w_m     (m over the held-out samples)

is, in expectation, the error of ``I`` as the camera sees it plus the noise variance, which does not depend
on ``I`` (the held-out noise is independent of the pixels the solver saw). So its minimum over the iterations
estimates the iteration where the image is best, on any scene and at any noise level, without a noise
estimate: a cross-validation stopping rule (hold-out validation for early stopping; Prechelt, "Early
stopping - but when?", 1998; for iterative image reconstruction e.g. Yaman et al., "Self-supervised
learning of physics-guided reconstruction neural networks without fully sampled reference data", MRM 2020,
which partitions the measured samples the same way).

The solver keeps the best iterate and stops ``patience`` iterations after it
(:class:`HoldoutValidation`, the :class:`~capssim.reconstruct.solvers.interfaces.StoppingRule` protocol).

Which count a final solve with all the data runs (``rule``):

- ``min``: the iteration of the lowest ``e``.
- ``one-se``: the earliest iteration ``k >= min_iterations`` whose error is within one standard error of the
  lowest, ``mean_m(d_m) <= std_m(d_m) / sqrt(n)`` with ``d_m = w_m ((y_m - (M I_k)_m)^2 - (y_m - (M I_best)_m)^2)``
  the paired per-sample differences over the ``n`` held-out samples (the one-standard-error rule of
  cross-validation: Breiman, Friedman, Olshen, Stone, *Classification and Regression Trees*, 1984, 3.4.3; Hastie,
  Tibshirani, Friedman, *The Elements of Statistical Learning*, 2nd ed., 2009, 7.10). Near its minimum ``e`` is
  flat within its own noise, and the argmin lands late by chance; the rule takes the least-iterated count the
  held-out pixels cannot tell from it. It keeps every iteration's ``n`` sample errors (8 bytes each).

Units: raw values on the sensor's [0, 1] full scale; ``e`` in those units squared.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from capssim.conventions import N_CHANNELS, split_bayer
from capssim.errors import InputError

from .polarization_filter import choose_polarization_filter

__all__ = ["HOLDOUT_RULES", "HOLDOUT_SEED", "HoldoutValidation", "check_holdout_rule", "fill_held_out", "holdout_mask",
           "split_held_out"]

#: the counts a validation can name for the final solve (module docstring)
HOLDOUT_RULES = ("min", "one-se")

#: the seed of the held-out pixels: a run is reproducible, and every method that holds out sees the same pixels
HOLDOUT_SEED = 20261127


def holdout_mask(raw_shape: tuple[int, int, int], fraction: float, *, seed: int = HOLDOUT_SEED) -> np.ndarray:
    """``(4, H, W)`` bool, True at the held-out raw pixels: each pixel independently with probability
    ``fraction`` (in (0, 0.5]), from a fixed seed. An empty mask for ``fraction`` 0."""
    fraction = float(fraction)
    if not (0.0 <= fraction <= 0.5):
        raise InputError("holdout_fraction", fraction, "a number in [0, 0.5] (the share of raw pixels left out)",
                         "Use -p holdout_fraction=0.05.")
    rng = np.random.default_rng(seed)
    return rng.random(tuple(raw_shape)) < fraction


def fill_held_out(raw: np.ndarray, held_out: np.ndarray) -> np.ndarray:
    """``raw`` ``(4, H, W)`` with each held-out pixel replaced by the mean of its unheld same-colour neighbours
    (the 8 raw pixels two rows or columns away, the Bayer period); the plane's mean of unheld pixels where
    all 8 are held out. Used for the demosaicked start, which must not see the held-out values."""
    raw = np.asarray(raw, dtype=np.float32)
    held = np.asarray(held_out, dtype=bool)
    if not held.any():
        return raw
    keep = torch.from_numpy((~held).astype(np.float32))[:, None]
    values = torch.from_numpy(raw)[:, None] * keep
    kernel = torch.zeros(1, 1, 5, 5)
    kernel[0, 0, ::2, ::2] = 1.0
    kernel[0, 0, 2, 2] = 0.0
    total = F.conv2d(values, kernel, padding=2)[:, 0]
    count = F.conv2d(keep, kernel, padding=2)[:, 0]
    plane_mean = (values.sum(dim=(1, 2, 3)) / keep.sum(dim=(1, 2, 3)).clamp_min(1.0))[:, None, None]
    filled = torch.where(count > 0, total / count.clamp_min(1.0), plane_mean.expand_as(total))
    out = raw.copy()
    out[held] = filled.numpy()[held]
    return out


def split_held_out(weights: torch.Tensor, held_out: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The data weights ``(16, h, w)`` split by the raw mask ``held_out`` ``(4, H, W)``: ``(weights the solver
    keeps, weights of the held-out samples)``; the two sum to ``weights``."""
    lr = torch.as_tensor(split_bayer(np.asarray(held_out, dtype=bool), argument="held_out"),
                         dtype=weights.dtype, device=weights.device)
    return weights * (1.0 - lr), weights * lr


def check_holdout_rule(rule: str, *, name: str = "holdout_rule") -> str:
    """``rule`` if it is one of :data:`HOLDOUT_RULES`; :class:`InputError` naming ``name`` otherwise."""
    if rule not in HOLDOUT_RULES:
        raise InputError(name, repr(rule), "one of " + ", ".join(HOLDOUT_RULES),
                         "Use -p holdout_rule=min (the lowest held-out error) or -p holdout_rule=one-se.")
    return rule


class HoldoutValidation:
    """A :class:`~capssim.reconstruct.solvers.interfaces.StoppingRule`: the held-out prediction error ``e``
    (module docstring) after every iteration; the best iterate so far is kept, and the solver stops once
    ``patience`` iterations have not improved on it (never before ``min_iterations``).

    Parameters
    ----------
    forward : callable
        ``forward(image) -> (N, h, w)``: the observations predicted from an image (``M I``, eq. 15).
    images, weights : torch.Tensor
        ``(N, h, w)`` the recorded samples and the held-out weights (0 where not held out).
    patience : int
        Iterations without a new best after which the solver stops (>= 1).
    min_iterations : int
        Iterations always run (>= 0).
    refit : object, optional
        The problem with all the data, which the pipeline solves again for :attr:`chosen_iteration` iterations
        once this rule has stopped its run (:func:`capssim.reconstruct.pipeline.run.run_pipeline`); ``None``:
        the best iterate of this run is the result.
    rule : str
        Which count :attr:`chosen_iteration` names: ``min`` (:attr:`best_iteration`) or ``one-se`` (module
        docstring).
    choose_filter : bool
        Also choose the polarization filter of the final image on the best iterate
        (:func:`~capssim.reconstruct.model.polarization_filter.choose_polarization_filter`;
        ``polarization_filter_choice`` in :meth:`record`).
    """

    def __init__(self, forward, images: torch.Tensor, weights: torch.Tensor, *, patience: int = 5,
                 min_iterations: int = 3, refit=None, rule: str = "min", choose_filter: bool = False):
        if int(patience) < 1:
            raise InputError("patience", patience, "an integer >= 1", "Use -p patience=5.")
        check_holdout_rule(rule)
        self.forward, self.images, self.weights = forward, images, weights
        self.total = float(weights.sum())
        if self.total <= 0:
            raise InputError("holdout_fraction", "no held-out sample with a data weight",
                             "a fraction that holds out some usable pixels", "Use -p holdout_fraction=0.05.")
        self.patience, self.min_iterations, self.refit, self.rule = int(patience), int(min_iterations), refit, rule
        self.held = weights > 0
        self.sample_errors: list[torch.Tensor] = []  # rule one-se: each iterate's weighted squared errors
        self.best_image: torch.Tensor | None = None
        self.best_error, self.best_iteration, self.last_iteration = math.inf, 0, 0
        self.init_error = math.inf
        self.choose_filter, self._filter_choice = bool(choose_filter), None

    def error(self, image: torch.Tensor) -> float:
        """``e(image)``: the weighted mean squared prediction error at the held-out samples."""
        return float(self._weighted_errors(image).sum()) / self.total

    def held_out_errors(self, image: torch.Tensor) -> torch.Tensor:
        """``(n,)`` each held-out sample's weighted squared prediction error for ``image``, in a fixed order."""
        return self._weighted_errors(image)[self.held]

    def _weighted_errors(self, image: torch.Tensor) -> torch.Tensor:
        residual = self.images - self.forward(image)
        return self.weights * residual.square()

    def _measure(self, image: torch.Tensor) -> float:
        """:meth:`error` of an iterate, whose sample errors ``rule="one-se"`` keeps."""
        weighted = self._weighted_errors(image)
        if self.rule == "one-se":
            self.sample_errors.append(weighted[self.held].double())
        return float(weighted.sum()) / self.total

    def begin(self, init: torch.Tensor) -> dict:
        """Start a run from ``init`` (iteration 0, a candidate itself); its error, which the first
        :meth:`update` reports too."""
        self.sample_errors, self._filter_choice = [], None
        self.best_error, self.best_iteration, self.last_iteration = self._measure(init), 0, 0
        self.best_image = init.detach().clone()
        self.init_error = self.best_error
        return {"holdout_error_init": self.init_error}

    def update(self, iteration: int, image: torch.Tensor) -> dict:
        """After iteration ``iteration`` (1-based) produced ``image``: its error, kept if the best so far (the
        first iteration's fields also hold the start's error)."""
        e = self._measure(image)
        first = self.last_iteration == 0
        self.last_iteration = int(iteration)
        if e < self.best_error:
            self.best_error, self.best_iteration = e, int(iteration)
            self.best_image = image.detach().clone()
        fields = {"holdout_error": e, "holdout_best_iteration": self.best_iteration}
        return {"holdout_error_init": self.init_error, **fields} if first else fields

    @property
    def should_stop(self) -> bool:
        """True once ``patience`` iterations passed without a new best (and ``min_iterations`` ran)."""
        return (self.last_iteration >= self.min_iterations
                and self.last_iteration - self.best_iteration >= self.patience)

    @property
    def chosen_iteration(self) -> int:
        """The count a final solve with all the data runs: :attr:`best_iteration` (``rule="min"``), or the earliest
        count from ``min_iterations`` on whose paired error difference to it is within one standard error
        (``rule="one-se"``)."""
        best = self.best_iteration
        if self.rule == "min" or best <= self.min_iterations or len(self.sample_errors) <= best:
            return best
        reference = self.sample_errors[best]
        n = reference.numel()
        for k in range(self.min_iterations, best):
            diff = self.sample_errors[k] - reference
            if float(diff.mean()) <= float(diff.std()) / math.sqrt(n):
                return k
        return best

    def final(self, image: torch.Tensor) -> torch.Tensor:
        """The image the solver returns: the best iterate (``image`` if the rule never began)."""
        return image if self.best_image is None else self.best_image

    def record(self) -> dict:
        """What the method's record keeps: the count run (``iterations``: the chosen one where the problem is solved
        again, else that of the best iterate, which is the result), the count a final solve runs
        (``holdout_chosen_iteration``), the lowest held-out error, where it was and the iterations the
        validation run took."""
        chosen = self.chosen_iteration
        out = {"iterations": chosen if self.refit is not None else self.best_iteration,
               "holdout_best_iteration": self.best_iteration, "holdout_chosen_iteration": chosen,
               "holdout_rule": self.rule, "holdout_error": self.best_error,
               "holdout_iterations_run": self.last_iteration}
        if self.choose_filter and self.best_image is not None and self.best_image.shape[0] == N_CHANNELS:
            if self._filter_choice is None:
                self._filter_choice = choose_polarization_filter(self.held_out_errors, self.best_image)
            out["polarization_filter_choice"] = self._filter_choice
        return out
