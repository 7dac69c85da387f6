"""A method's ``-p`` options checked before any work: the method run on a capture with no data up to its first look
at it (``capssim reconstruct`` and a suite's per-method ``options`` are checked so before the first case)."""

from __future__ import annotations

import logging

import torch

from capssim.errors import CapssimError

from .registry import get_method
from .run_context import RunContext, StageTimer

__all__ = ["check_method_options"]

log = logging.getLogger(__name__)


class _OptionsParsed(BaseException):
    """Raised by :class:`_ProbeCapture` at a method's first look at the capture: its options are parsed by then.
    A BaseException, so that no ``except Exception`` of a method swallows it."""


class _ProbeCapture:
    """A capture with no data: any attribute stops the method (:class:`_OptionsParsed`)."""

    def __getattr__(self, name):
        raise _OptionsParsed(name)


def check_method_options(name: str, options: dict) -> bool:
    """Run method ``name`` with ``options`` up to its first look at the capture, on a capture with no data: every
    method has parsed and checked its options by then, so an option it refuses is raised here, before any work
    (``capssim reconstruct`` and a suite's per-method ``options`` are checked so before the first case).

    Returns
    -------
    bool
        True when the options were checked; False for a method that looks at the capture before its options (it
        reports them when it runs).

    Raises
    ------
    CapssimError
        The method's own one-line error (an unknown option, a value out of range).
    """
    cpu = torch.device("cpu")
    context = RunContext(device=cpu, timer=StageTimer(cpu), options=dict(options or {}))
    try:
        with torch.no_grad():
            get_method(name).function(_ProbeCapture(), context=context)
    except _OptionsParsed:
        return True
    except CapssimError:
        raise
    except Exception:  # noqa: BLE001 - not an option error: the method reports it when it runs
        log.debug("options of %s not checked ahead", name, exc_info=True)
    return False
