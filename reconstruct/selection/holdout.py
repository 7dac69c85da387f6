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

Units: raw values on the sensor's [0, 1] full scale; ``e`` in those units squared.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from capssim.conventions import N_CHANNELS, split_bayer
from capssim.errors import InputError

from ..model.aperture_demosaic import fill_held_out  # noqa: F401  (re-exported: the start's fill of the held-out pixels)
from .polarization_filter import choose_polarization_filter

__all__ = ["HOLDOUT_SEED", "HoldoutValidation", "fill_held_out", "holdout_mask", "split_held_out"]

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


def split_held_out(weights: torch.Tensor, held_out: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The data weights ``(16, h, w)`` split by the raw mask ``held_out`` ``(4, H, W)``: ``(weights the solver
    keeps, weights of the held-out samples)``; the two sum to ``weights``."""
    lr = torch.as_tensor(split_bayer(np.asarray(held_out, dtype=bool), argument="held_out"),
                         dtype=weights.dtype, device=weights.device)
    return weights * (1.0 - lr), weights * lr


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
    choose_filter : bool
        Also choose the polarization filter of the final image on the best iterate
        (:func:`~capssim.reconstruct.selection.polarization_filter.choose_polarization_filter`;
        ``polarization_filter_choice`` in :meth:`record`).
    """

    def __init__(self, forward, images: torch.Tensor, weights: torch.Tensor, *, patience: int = 5,
                 min_iterations: int = 3, choose_filter: bool = False):
        if int(patience) < 1:
            raise InputError("patience", patience, "an integer >= 1", "Use -p patience=5.")
        self.forward, self.images, self.weights = forward, images, weights
        self.total = float(weights.sum())
        if self.total <= 0:
            raise InputError("holdout_fraction", "no held-out sample with a data weight",
                             "a fraction that holds out some usable pixels", "Use -p holdout_fraction=0.05.")
        self.patience, self.min_iterations = int(patience), int(min_iterations)
        self.held = weights > 0
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

    def begin(self, init: torch.Tensor) -> dict:
        """Start a run from ``init`` (iteration 0, a candidate itself); its error, which the first
        :meth:`update` reports too."""
        self._filter_choice = None
        self.best_error, self.best_iteration, self.last_iteration = self.error(init), 0, 0
        self.best_image = init.detach().clone()
        self.init_error = self.best_error
        return {"holdout_error_init": self.init_error}

    def update(self, iteration: int, image: torch.Tensor) -> dict:
        """After iteration ``iteration`` (1-based) produced ``image``: its error, kept if the best so far (the
        first iteration's fields also hold the start's error)."""
        e = self.error(image)
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

    def final(self, image: torch.Tensor) -> torch.Tensor:
        """The image the solver returns: the best iterate (``image`` if the rule never began)."""
        return image if self.best_image is None else self.best_image

    def record(self) -> dict:
        """What the method's record keeps: the count of the best iterate, which is the result (``iterations``,
        ``holdout_best_iteration``), the lowest held-out error and the iterations the validation run took."""
        out = {"iterations": self.best_iteration, "holdout_best_iteration": self.best_iteration,
               "holdout_error": self.best_error, "holdout_iterations_run": self.last_iteration}
        if self.choose_filter and self.best_image is not None and self.best_image.shape[0] == N_CHANNELS:
            if self._filter_choice is None:
                self._filter_choice = choose_polarization_filter(self.held_out_errors, self.best_image)
            out["polarization_filter_choice"] = self._filter_choice
        return out
