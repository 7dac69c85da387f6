"""A quadratic smoothness (Tikhonov) prior for the ADMM solver: the simplest prior there is.

``R(X) = lambda/2 ||nabla X||^2``, with ``nabla`` the forward differences along the last
two axes (periodic boundary). Its proximal operator, the ``X``-step of ADMM (paper eq. 21-23
and 29 replaced by a closed form), is

    ``prox_{R/mu}(Z) = argmin_X R(X) + mu/2 ||X - Z||^2 = (mu + lambda nabla^T nabla)^{-1} mu Z``,

diagonal in the 2-D Fourier basis, where ``nabla^T nabla`` has the eigenvalues
``4 sin^2(pi k / H) + 4 sin^2(pi l / W)``. It shows that
:func:`capssim.reconstruct.solvers.admm.admm` needs no edit for a new prior, and it is a baseline
regularizer for tests and experiments; it is not part of the paper's method.
"""

from __future__ import annotations

import math

import torch

from capssim.errors import InputError

from ..solvers.interfaces import StageFactory


def laplacian_eigenvalues(shape: tuple[int, int], *, device=None, dtype=torch.float64) -> torch.Tensor:
    """``(H, W // 2 + 1)`` eigenvalues of ``nabla^T nabla`` (periodic) on the ``rfft2`` grid."""
    h, w = shape
    ky = torch.fft.fftfreq(h, device=device, dtype=dtype)
    kx = torch.fft.rfftfreq(w, device=device, dtype=dtype)
    return 4 * torch.sin(math.pi * ky)[:, None] ** 2 + 4 * torch.sin(math.pi * kx)[None, :] ** 2


class TikhonovPrior:
    """``R(X) = weight/2 ||nabla X||^2`` over images ``(..., H, W)`` (a :class:`~capssim.reconstruct.solvers.interfaces.Prior`)."""

    def __init__(self, weight: float):
        if not (weight >= 0 and math.isfinite(weight)):
            raise InputError("weight", weight, "a finite number >= 0 (the Tikhonov weight lambda)")
        self.weight = float(weight)

    def value(self, x: torch.Tensor) -> float:
        """``R(x)``."""
        dy = torch.roll(x, -1, dims=-2) - x
        dx = torch.roll(x, -1, dims=-1) - x
        return 0.5 * self.weight * float(dy.square().sum() + dx.square().sum())

    def proximal(self, z: torch.Tensor, mu: float) -> torch.Tensor:
        """``prox_{R/mu}(z)`` (module docstring), shape and dtype of ``z``."""
        eig = laplacian_eigenvalues(tuple(z.shape[-2:]), device=z.device)
        gain = (mu / (mu + self.weight * eig)).to(z.dtype)
        return torch.fft.irfft2(torch.fft.rfft2(z) * gain, s=tuple(z.shape[-2:]))

    # -- the Prior protocol ---------------------------------------------------------------
    def begin(self) -> None:
        """Nothing to reset: the prior keeps no state."""

    def estimate(self, z: torch.Tensor, *, mu: float, iteration: int,
                 stage: StageFactory) -> tuple[torch.Tensor, dict]:
        """``X = prox_{R/mu}(z)``; history field ``regularizer`` ``R(X)``."""
        with stage("tikhonov_prox"):
            x = self.proximal(z, mu)
        return x, {"regularizer": self.value(x)}

    def after_step(self, *, iteration: int, change: float) -> dict:
        return {}


__all__ = ["TikhonovPrior", "laplacian_eigenvalues"]
