"""How many CPU threads capssim's computations use (torch intra-op, OpenMP/MKL, OpenCV).

Every compute command takes ``--threads N``; without it the ``CAPSSIM_THREADS`` environment
variable, and without that :data:`DEFAULT_THREADS` (1), decide. :func:`set_threads` applies the
count to torch (``torch.set_num_threads``: its OpenMP and MKL pools) and OpenCV, and exports it in
``CAPSSIM_THREADS`` and ``OMP_NUM_THREADS``/``MKL_NUM_THREADS`` so that the processes a command
starts (benchmark runs, Dask workers) inherit it.

Why one thread by default: torch's OpenMP threads spin while they wait, so when another process
holds a core every parallel region waits for a descheduled thread. On 2 cores, ``caps`` with 2
threads is about 1.6x faster than with 1 on a quiet machine and 7-20x slower as soon as one other
CPU-bound process runs; with ``OMP_WAIT_POLICY=PASSIVE`` or a short ``GOMP_SPINCOUNT`` it is no faster
than 1 thread when quiet, or still 2x slower when busy. ``--threads N`` (N = the cores) is for a
machine nothing else uses. Phases of small tensors (the registration's L-BFGS on raw-size images)
gain nothing from a second thread and lose the most when the machine is busy (16x): they run inside
:func:`small_tensor_threads`, one thread whatever the count. Measurements:
``docs/notes/reconstruction-speed.md`` ("Threads on a shared machine").
"""

from __future__ import annotations

import operator
import os
from contextlib import contextmanager
from typing import Iterator

import torch

from capssim.errors import InputError
from capssim.resources import check_range

#: the environment variable read when no ``--threads`` is given
ENV_VAR = "CAPSSIM_THREADS"
#: threads when neither ``--threads`` nor ``CAPSSIM_THREADS`` says: steady on a shared machine
DEFAULT_THREADS = 1
#: the largest thread count accepted: ``max(MAX_THREADS, 4 x available cores)`` (more only adds idle threads)
MAX_THREADS = 256
#: the thread variables child processes read at start-up (OpenMP, MKL, OpenBLAS)
CHILD_ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity mask; ``os.cpu_count()`` elsewhere)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _checked(value, argument: str) -> int:
    """``value`` (an int, or its text) as an int >= 1, else an :class:`InputError` naming ``argument``."""
    error = InputError(argument, repr(value), "an integer >= 1", "Give a whole number of threads, e.g. --threads 1.")
    if isinstance(value, bool):
        raise error
    try:
        count = int(value.strip()) if isinstance(value, str) else operator.index(value)
    except (TypeError, ValueError):
        raise error from None
    if count < 1:
        raise error
    check_range(argument, count, high=max(MAX_THREADS, 4 * available_cores()), what="the thread count",
                reason=f"{available_cores()} cores here; more threads than that only take turns",
                fix="Give at most the number of cores, e.g. --threads 1.")
    return count


def resolve_threads(threads: int | None = None) -> int:
    """The thread count to use: ``threads`` if given, else ``$CAPSSIM_THREADS``, else :data:`DEFAULT_THREADS`.

    An explicit count (option or variable) is used as given, even above the core count. A count that is not an
    integer >= 1 is an :class:`~capssim.errors.InputError` naming where it came from; one above
    ``max(MAX_THREADS, 4 x cores)`` a :class:`~capssim.errors.ResourceError`.
    """
    if threads is not None:
        return _checked(threads, "--threads")
    env = os.environ.get(ENV_VAR, "").strip()
    if env:
        return _checked(env, ENV_VAR)
    return DEFAULT_THREADS


def set_threads(threads: int | None = None, *, renderer: bool = False) -> int:
    """Apply :func:`resolve_threads` ``(threads)`` to torch, OpenCV and child processes; return it.

    ``renderer``: also to Dr.Jit's thread pool (Mitsuba's LLVM variants), for the rendering commands.
    """
    count = resolve_threads(threads)
    torch.set_num_threads(count)
    _set_opencv_threads(count)
    if renderer:
        import drjit  # not a project module: the renderer's JIT loads only for the rendering commands

        drjit.set_thread_count(count)
    os.environ[ENV_VAR] = str(count)
    for var in CHILD_ENV_VARS:
        os.environ[var] = str(count)
    return count


def _set_opencv_threads(count: int) -> None:
    import cv2  # not a project module: OpenCV loads only for the commands that compute

    cv2.setNumThreads(count)


@contextmanager
def small_tensor_threads(threads: int = 1) -> Iterator[int]:
    """Run the block with at most ``threads`` torch threads (default 1); restore the count after.

    For phases of small tensors (registration, per-image filters), whose parallel regions are too
    short to share between threads and stall when another process holds a core. Yields the count
    used. Nested uses and exceptions restore the outer count.
    """
    before = torch.get_num_threads()
    count = max(1, min(int(threads), before))
    if count != before:
        torch.set_num_threads(count)
    try:
        yield count
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)
