"""How many CPU threads capssim's computations use (torch intra-op, OpenMP/MKL, OpenCV).

Every compute command takes ``--threads N``; without it the ``CAPSSIM_THREADS`` environment
variable (a count, or ``auto``), and without that the default, ``auto``, decide. :func:`set_threads`
applies the count to torch (``torch.set_num_threads``: its OpenMP and MKL pools) and OpenCV, and
exports it in ``CAPSSIM_THREADS`` and ``OMP_NUM_THREADS``/``MKL_NUM_THREADS`` so that the processes a
command starts (benchmark runs, Dask workers) inherit it.

Why the count matters: torch's OpenMP threads spin while they wait, so when another process holds a
core every parallel region waits for a descheduled thread. On 2 cores, ``caps`` with 2 threads is
about 1.5x faster than with 1 on a quiet machine and 3-20x slower as soon as one other CPU-bound
process runs; ``OMP_WAIT_POLICY=PASSIVE`` or a short ``GOMP_SPINCOUNT`` lose the quiet gain or keep
the busy loss. So ``auto`` starts every command on one thread, and a reconstruction re-decides at
each of its stages (:func:`adapt_threads`, called by the methods' stage timer): all the cores this
process may use while the other processes used less than half a core since the last decision (the
first decision: since this module was imported, the command's start-up), one fewer for each further
core they use. An explicit count is kept as given. Phases of small tensors
(the registration's L-BFGS on the raw images of a small capture) lose the most when the machine is
busy (16x): they run inside :func:`small_tensor_threads`, one thread whatever the count; the
registration of a large capture follows the governor under ``auto`` (:func:`registration_threads`).
Measurements:
``docs/notes/reconstruction-speed.md`` ("Threads on a shared machine", "Adaptive threads").
"""

from __future__ import annotations

import math
import operator
import os
import time
from contextlib import contextmanager
from typing import Iterator

import torch

from capssim.errors import InputError
from capssim.runtime.resources import check_range

#: the environment variable read when no ``--threads`` is given
ENV_VAR = "CAPSSIM_THREADS"
#: threads when neither ``--threads`` nor ``CAPSSIM_THREADS`` gives a count (``auto``): the count every
#: command starts with, steady on a shared machine; reconstructions then adapt (:func:`adapt_threads`)
DEFAULT_THREADS = 1
#: the value of ``CAPSSIM_THREADS`` (and the default) that lets reconstructions adapt their count
AUTO = "auto"
#: the largest thread count accepted: ``max(MAX_THREADS, 4 x available cores)`` (more only adds idle threads)
MAX_THREADS = 256
#: the thread variables child processes read at start-up (OpenMP, MKL, OpenBLAS)
CHILD_ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def cpu_ids() -> list[int]:
    """The CPUs this process may run on (its affinity mask; all of ``os.cpu_count()`` elsewhere)."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return list(range(os.cpu_count() or 1))


def available_cores() -> int:
    """How many CPU cores this process may run on (:func:`cpu_ids`)."""
    return len(cpu_ids())


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
    env = _environment_count()
    return DEFAULT_THREADS if env is None else _checked(env, ENV_VAR)


def _environment_count() -> str | None:
    """``$CAPSSIM_THREADS`` when it gives a count (not blank, not ``auto``), else None."""
    env = os.environ.get(ENV_VAR, "").strip()
    return None if not env or env.lower() == AUTO else env


def is_adaptive(threads: int | None = None) -> bool:
    """True when neither ``threads`` nor ``$CAPSSIM_THREADS`` gives a count (the default, ``auto``)."""
    return threads is None and _environment_count() is None


def set_threads(threads: int | None = None, *, renderer: bool = False) -> int:
    """Apply :func:`resolve_threads` ``(threads)`` to torch, OpenCV and child processes; return it.

    ``renderer``: also to Dr.Jit's thread pool (Mitsuba's LLVM variants), for the rendering commands.
    """
    global _governor
    count = resolve_threads(threads)
    adaptive = is_adaptive(threads)
    torch.set_num_threads(count)
    _set_opencv_threads(count)
    if renderer:
        import drjit  # not a project module: the renderer's JIT loads only for the rendering commands

        drjit.set_thread_count(count)
    os.environ[ENV_VAR] = AUTO if adaptive else str(count)
    for var in CHILD_ENV_VARS:
        os.environ[var] = str(count)
    _governor = ThreadGovernor(available_cores(), since=_startup_sample()) if adaptive else None
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
    global _cap
    before, outer_cap = torch.get_num_threads(), _cap
    count = max(1, min(int(threads), before))
    _cap = count if outer_cap is None else min(count, outer_cap)  # the governor stays under it
    if count != before:
        torch.set_num_threads(count)
    try:
        yield count
    finally:
        _cap = outer_cap
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


#: sub-images of at least this many pixels (128 x 128: a 512 px capture) make the registration's tensors
#: large enough to share between threads (30 % faster on 2 quiet cores; docs: notes/reconstruction-speed.md)
LARGE_REGISTRATION_PIXELS = 128 * 128


@contextmanager
def registration_threads(image_pixels: int) -> Iterator[int]:
    """Threads of a registration on images of ``image_pixels`` pixels: under ``auto`` and for large images,
    the governor's count, re-decided inside the phase (:func:`adapt_threads` at each evaluation);
    otherwise :func:`small_tensor_threads` (one thread). Yields the count at the start."""
    if _governor is not None and image_pixels >= LARGE_REGISTRATION_PIXELS:
        yield adapt_threads()
    else:
        with small_tensor_threads() as count:
            yield count


def busy_cpu_seconds(cpus, *, stat_path: str = "/proc/stat") -> float | None:
    """Seconds the CPUs ``cpus`` spent busy since boot (``/proc/stat``: user, nice, system, irq, softirq,
    steal), or None where that file cannot be read."""
    wanted = {f"cpu{c}" for c in cpus}
    try:
        with open(stat_path) as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    ticks = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    total = 0
    for line in lines:
        parts = line.split()
        if parts and parts[0] in wanted and len(parts) >= 9:
            user, nice, system, _idle, _iowait, irq, softirq, steal = (int(v) for v in parts[1:9])
            total += user + nice + system + irq + softirq + steal
    return total / ticks


def adaptive_count(other_cores: float, max_threads: int) -> int:
    """Threads for a process that may use ``max_threads`` cores while others keep ``other_cores`` busy:
    all of them under half a busy core, one fewer per further core, at least one."""
    return max(1, min(max_threads, max_threads - math.floor(other_cores + 0.5)))


class ThreadGovernor:
    """Adapts torch's thread count to what the other processes leave free (the ``auto`` default).

    :meth:`update` measures, since its last decision, the busy time of this process's CPUs from
    ``/proc/stat`` minus this process's own CPU time (``time.process_time``): the cores the others
    used. Decisions at least ``interval_s`` apart; none where ``/proc/stat`` is unreadable.
    """

    def __init__(self, max_threads: int, *, interval_s: float = 0.25, stat_path: str = "/proc/stat",
                 since: tuple[float, float | None, float] | None = None):
        self.max_threads = max(1, int(max_threads))
        self.interval_s = interval_s
        self.stat_path = stat_path
        self.cpus = cpu_ids()
        self.last = since if since is not None else self._sample()  # since: an earlier _sample()
        self.decisions: list[tuple[float, int]] = []  # (others' cores, threads chosen)

    def _sample(self) -> tuple[float, float | None, float]:
        return time.monotonic(), busy_cpu_seconds(self.cpus, stat_path=self.stat_path), time.process_time()

    def update(self) -> int:
        """Re-decide the thread count if ``interval_s`` has passed; return the count in use."""
        if time.monotonic() - self.last[0] < self.interval_s:
            return torch.get_num_threads()
        now = self._sample()
        if now[1] is None or self.last[1] is None:  # no /proc/stat
            return torch.get_num_threads()
        wall, busy, own = (a - b for a, b in zip(now, self.last))
        self.last = now
        others = max(0.0, (busy - own) / wall)
        count = adaptive_count(others, self.max_threads)
        if _cap is not None:
            count = min(count, _cap)
        self.decisions.append((round(others, 2), count))
        if count != torch.get_num_threads():
            torch.set_num_threads(count)
        return count


#: the load sample taken when this module was imported (the command's start-up), for the first governor
_import_sample = (time.monotonic(), busy_cpu_seconds(cpu_ids()), time.process_time())


def _startup_sample() -> tuple[float, float | None, float] | None:
    """The import-time sample, once: the first governor of a process measures the load over the start-up,
    so the first stages of a command (CAGF, the initialization) already run at the machine's count."""
    global _import_sample
    sample, _import_sample = _import_sample, None
    return sample


_governor: ThreadGovernor | None = None
_cap: int | None = None  # set by small_tensor_threads: the governor never goes above it


def adaptive_decisions() -> list[tuple[float, int]]:
    """The ``(other processes' cores, threads chosen)`` decisions of this process so far (``auto`` only)."""
    return list(_governor.decisions) if _governor is not None else []


def adapt_threads() -> int:
    """With the ``auto`` default, let the :class:`ThreadGovernor` re-decide the count (called at each stage
    of a reconstruction); otherwise nothing. Returns torch's thread count."""
    if _governor is not None:
        return _governor.update()
    return torch.get_num_threads()
