"""What every reconstruction method receives besides the capture, and what it returns.

:class:`RunContext` (device, stage timer, options, registration and calibration choices) goes in;
:class:`MethodOutput` (the ``(12, 2H, 2W)`` image and its record) comes out. The dispatcher
(:mod:`capssim.reconstruct.registry`) builds the one and checks the other; the pieces that methods
share (observation model, DoFP method body) read and write them without depending on the dispatcher.
"""

from __future__ import annotations

import time
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np
import torch

from capssim.runtime.threads import adapt_threads

from .calibration_model import CalibrationModel

__all__ = ["MethodOutput", "RunContext", "StageTimer", "no_stage", "stage_factory"]


@dataclass
class StageTimer:
    """Wall time per named stage, in seconds; synchronizes CUDA so GPU time is counted."""

    device: torch.device = torch.device("cpu")
    stages: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        else:
            adapt_threads()  # the default 'auto' thread count follows the machine's load, stage by stage
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            self.stages[name] = self.stages.get(name, 0.0) + time.perf_counter() - t0


def no_stage(name: str) -> AbstractContextManager:
    """A stage factory (``stage(name)``, as :meth:`StageTimer.stage`) that times nothing."""
    return nullcontext()


def stage_factory(timer: StageTimer | None) -> Callable[[str], AbstractContextManager]:
    """``timer.stage``, or a stage that times nothing when ``timer`` is None (the array functions called
    outside a method, e.g. ``capssim demosaic`` or a test)."""
    return timer.stage if timer is not None else no_stage


@dataclass
class RunContext:
    """What every method receives besides the capture."""

    device: torch.device
    timer: StageTimer
    options: dict = field(default_factory=dict)
    true_warps: bool = False
    registration: str = "local-correlation"  # reconstruct.registration.REGISTRATION_MODES
    reuse_registration: bool = True  # reconstruct.registration.store: False registers again (and re-stores)
    progress: Callable[[int, int, str], None] | None = None
    calibration: CalibrationModel | None = None  # reconstruct.calibration_model: the array's model (None: ideal)
    #: a warm start ``(12, 2H, 2W)`` float32: the solver of an iterative method starts here instead of at its own start
    #: (the bootstrap's replicates, :mod:`capssim.reconstruct.uncertainty`); methods without a solver ignore it
    start: np.ndarray | None = None

    def report(self, done: int, total: int, message: str = "") -> None:
        if self.progress is not None:
            self.progress(done, total, message)


@dataclass
class MethodOutput:
    """A method's result: ``image`` ``(12, 2H, 2W)`` float32 and what it records.

    ``unobserved`` ``(12, 2H, 2W)`` bool marks the pixels without a usable observation
    (saturated or out of view), or is ``None`` when the method cannot tell; a function returning
    that array is evaluated after the method's wall time is taken (it is a report, not the method).
    """

    image: np.ndarray
    params: dict = field(default_factory=dict)
    history: list[dict] = field(default_factory=list)
    extra: dict = field(default_factory=dict)
    unobserved: np.ndarray | Callable[[], np.ndarray] | None = None
    #: the error bars of ``--uncertainty`` (:class:`capssim.reconstruct.uncertainty.maps.UncertaintyMaps`), or None
    uncertainty: object | None = None

    def companions(self) -> dict[str, np.ndarray] | None:
        """The arrays written beside the image (``write_reconstruction``'s ``companions``): the error bars, or None."""
        return None if self.uncertainty is None else self.uncertainty.arrays()
