"""``nlstr-denoiser``: NLSTR with its intensity part blended with a learned denoiser's (plug-and-play).
Not the paper's; the prior of ``caps-plus-cv``.

At ADMM iteration ``i`` of ``n`` (``Z = I - L``, ``(12, H, W)``, channel ``c = 3 p + k``)::

    X_nl = NLSTR(Z)                                  # paper section 3.3, eq. 21-23, 29
    X_dn = D(Z, sigma_i)                             # the learned denoiser, noise level sigma_i
    X    = X_nl + w (P X_dn - P X_nl)                # P: mean over the 4 analyzers of each colour

``P`` is :func:`~capssim.reconstruct.model.polarization_split.angle_mean`, the same split as the
``cagf-split`` data term: the analyzer mean (the intensity, ``S0 / 2`` of each colour) takes a share ``w``
of the denoiser's estimate, the polarization part ``(I - P) X`` stays NLSTR's, whose 12-channel groups
denoise the small differences between the analyzers better than the small network does (with the
denoiser's polarization part as well, DoLP PSNR fell by 3 dB on the textured astronaut; docs:
notes/beyond-the-paper.md). ``sigma_i`` falls log-linearly from ``denoiser_sigma_start`` at the first
iteration to ``denoiser_sigma_end`` at the last (the plug-and-play schedule of Zhang et al., "Plug-and-play
image restoration with deep denoiser prior", IEEE TPAMI 44(10) 2022).

``D`` is :class:`~capssim.reconstruct.networks.denoiser.NoiseLevelDenoiser`, trained by ``capssim train
examples/train-denoiser.yaml`` on rendered training scenes only; the shipped weights are
``reconstruct/weights/denoiser.pt``. It runs in tiles of :data:`TILE` pixels (bounded activations on
full frames) on the device of the run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import torch

from capssim.errors import InputError

from ..model.polarization_split import angle_mean
from ..networks import load_model, shipped_weights
from ..networks.tiling import apply_tiled
from ..solvers.interfaces import StageFactory
from .nlstr_prior import NLSTRPrior

#: the shipped weights of the denoiser (``reconstruct/weights/denoiser.pt``)
SHIPPED_DENOISER = "denoiser"
#: tile side (px) and halo of the denoiser's inference (its receptive radius is its depth, 7 px)
TILE, HALO = 512, 16


@dataclass(frozen=True)
class DenoiserParameters:
    """The ``nlstr-denoiser`` prior's own ``-p`` options (module docstring).

    ``denoiser_weights``: a model file of ``capssim train`` (network ``denoiser``), empty for the shipped one;
    ``denoiser_blend``: ``w`` in [0, 1]; ``denoiser_sigma_start`` / ``denoiser_sigma_end``: the denoiser's noise
    level (std on [0, 1]) at the first and the last ADMM iteration; ``denoiser_sigma_steps``: ``0`` spreads the fall
    over the run's iterations, ``N > 0`` over the first ``N`` (then ``denoiser_sigma_end``), so that iteration ``k``
    does not depend on the run's length (what held-out stopping needs); ``denoiser_precision``: the network's
    arithmetic (:func:`denoiser_dtype`).
    """

    denoiser_weights: str = ""
    denoiser_blend: float = 0.5
    denoiser_sigma_start: float = 0.05
    denoiser_sigma_end: float = 0.005
    denoiser_sigma_steps: int = 0
    denoiser_precision: str = "auto"

    def validate(self) -> None:
        if not 0.0 <= self.denoiser_blend <= 1.0:
            raise InputError("denoiser_blend", self.denoiser_blend, "a number in [0, 1]",
                             "0 is NLSTR alone, 1 takes the intensity from the denoiser; try 0.5.")
        for name in ("denoiser_sigma_start", "denoiser_sigma_end"):
            value = getattr(self, name)
            if not (0.0 < value <= 1.0 and math.isfinite(value)):
                raise InputError(name, value, "a noise level in (0, 1] (std on the [0, 1] scale)",
                                 "Try -p denoiser_sigma_start=0.05 -p denoiser_sigma_end=0.005.")
        if isinstance(self.denoiser_sigma_steps, bool) or not isinstance(self.denoiser_sigma_steps, int) \
                or self.denoiser_sigma_steps < 0:
            raise InputError("denoiser_sigma_steps", self.denoiser_sigma_steps,
                             "an integer >= 0 (0: the noise level falls over the whole run)",
                             "Try -p denoiser_sigma_steps=15, or 0.")
        if str(self.denoiser_precision).strip() not in PRECISIONS:
            raise InputError("denoiser_precision", repr(self.denoiser_precision), "one of " + ", ".join(PRECISIONS),
                             "Use -p denoiser_precision=auto (bfloat16 where the device computes it natively).")


#: ``-p denoiser_precision=NAME``: ``auto`` (bfloat16 where the device computes it natively, else float32),
#: ``float32`` or ``bfloat16``
PRECISIONS = ("auto", "float32", "bfloat16")


def denoiser_dtype(precision: str, device: torch.device) -> torch.dtype:
    """The network's arithmetic for ``precision`` on ``device``: ``auto`` is bfloat16 on a CUDA device that
    supports it or a CPU with native bfloat16 (AVX-512 BF16 / AMX, through oneDNN), float32 otherwise. The
    network predicts the noise (residual learning), so bfloat16 rounds only the residual: on a 512 px test
    image the output differs from float32 by an RMS of about 6e-4 (64 dB), at a quarter of its CPU time."""
    name = str(precision).strip()
    if name != "auto":
        return torch.bfloat16 if name == "bfloat16" else torch.float32
    device = torch.device(device)
    if device.type == "cuda":
        native = torch.cuda.is_bf16_supported()
    else:
        native = device.type == "cpu" and _cpu_has_native_bfloat16()
    return torch.bfloat16 if native else torch.float32


@lru_cache(maxsize=1)
def _cpu_has_native_bfloat16() -> bool:
    """oneDNN's own test (AVX-512 BF16 or AMX); False where this torch build cannot tell."""
    try:
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


@lru_cache(maxsize=4)
def _cached_denoiser(path: str, device: str, version: tuple) -> torch.nn.Module:
    model, _ = load_model(path, device=device, expect="denoiser", option="denoiser_weights")
    return model


def denoiser_model(weights: str, device: torch.device) -> torch.nn.Module:
    """The denoiser of the model file ``weights`` (empty: the shipped one) on ``device``, in eval mode; read
    once per file version (path, size, modification time), so a file trained again is read again."""
    path = Path(weights).expanduser() if str(weights).strip() else shipped_weights(SHIPPED_DENOISER)
    # a missing file has no version: load_model raises its error (naming the option), which is never cached
    version = (path.stat().st_size, path.stat().st_mtime_ns) if path.is_file() else ()
    return _cached_denoiser(str(path.resolve()), str(torch.device(device)), version)


def sigma_schedule(iteration: int, iterations: int, start: float, end: float) -> float:
    """``start`` at iteration 0, ``end`` at iteration ``iterations - 1``, log-linear between (and past it)."""
    t = min(iteration / max(iterations - 1, 1), 1.0)
    return math.exp((1.0 - t) * math.log(start) + t * math.log(end))


class NLSTRDenoiserPrior:
    """The :class:`~capssim.reconstruct.solvers.interfaces.Prior` of the module docstring.

    Parameters
    ----------
    nlstr : NLSTRPrior
        NLSTR with its block-matching schedule.
    denoiser : torch.nn.Module
        ``denoiser(noisy (N, C, H, W), sigma (N,)) -> (N, C, H, W)``.
    parameters : DenoiserParameters
        Blend and noise-level schedule.
    iterations : int
        ADMM iterations of the run (the schedule's length).
    """

    def __init__(self, nlstr: NLSTRPrior, denoiser: torch.nn.Module, parameters: DenoiserParameters,
                 iterations: int):
        self.nlstr, self.denoiser, self.parameters, self.iterations = nlstr, denoiser, parameters, int(iterations)
        self.dtype_used = None  # the network's arithmetic once it has run

    def begin(self) -> None:
        self.nlstr.begin()

    def denoise(self, z: torch.Tensor, sigma: float) -> torch.Tensor:
        """``D(z, sigma)`` for ``z`` ``(C, H, W)``, in tiles, in ``z``'s dtype."""
        level = torch.full((1,), sigma, dtype=torch.float32, device=z.device)
        self.dtype_used = dtype = denoiser_dtype(self.parameters.denoiser_precision, z.device)
        with torch.autocast(z.device.type, dtype=dtype, enabled=dtype != torch.float32):
            out = apply_tiled(lambda x: self.denoiser(x, level), (z[None].float(),), tile=TILE, halo=HALO, step=1)
        return out[0].to(z.dtype)

    def estimate(self, z: torch.Tensor, *, mu: float, iteration: int,
                 stage: StageFactory) -> tuple[torch.Tensor, dict]:
        x, fields = self.nlstr.estimate(z, mu=mu, iteration=iteration, stage=stage)
        p = self.parameters
        length = p.denoiser_sigma_steps or self.iterations
        sigma = sigma_schedule(iteration, length, p.denoiser_sigma_start, p.denoiser_sigma_end)
        if p.denoiser_blend == 0.0:  # NLSTR alone: the denoiser's share is nothing, it is not run
            return x, {**fields, "denoiser_sigma": sigma}
        with stage("denoiser"):
            learned = self.denoise(z, sigma)
            x = x + p.denoiser_blend * angle_mean(learned - x)  # P is linear: w (P X_dn - P X_nl)
        return x, {**fields, "denoiser_sigma": sigma}

    def after_step(self, *, iteration: int, change: float) -> dict:
        return self.nlstr.after_step(iteration=iteration, change=change)

    def record(self) -> dict:
        used = "not run" if self.dtype_used is None else str(self.dtype_used).removeprefix("torch.")
        return {**self.nlstr.record(), "denoiser_blend": self.parameters.denoiser_blend, "denoiser_dtype": used}


__all__ = ["DenoiserParameters", "NLSTRDenoiserPrior", "PRECISIONS", "SHIPPED_DENOISER", "denoiser_dtype", "denoiser_model",
           "sigma_schedule"]
