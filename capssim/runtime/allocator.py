"""Keep freed memory for reuse during iterative phases (glibc ``malloc``; a no-op elsewhere).

glibc serves every allocation above its mmap threshold (at most 32 MiB) with a fresh ``mmap`` and
returns it to the system on ``free``. An iterative solver that allocates the same large
temporaries at every iteration, such as a ``(12, 1024, 1024)`` float32 image (48 MiB), then pays
the kernel's page faults and page zeroing for every one of them: at 1024 px that was most of the
data-term and ADMM-update time of ``caps``. Inside :func:`reuse_freed_memory` large blocks come
from the heap instead and freed ones are reused; on exit the defaults are restored and the free
heap pages are handed back (``malloc_trim``). ``CAPSSIM_REUSE_FREED_MEMORY=0`` in the environment
turns it off. Measurements: docs/notes/reconstruction-speed.md.

The memory kept this way is the process's own: :func:`held_free_bytes` says how much, and the memory guard
(:func:`capssim.runtime.resources.available_memory_bytes`) counts it as available, since the system's
``MemAvailable`` does not (at 1024² a ``caps`` run holds about 1 GiB of freed heap when NLSTR re-checks
its 0.7 GiB working set).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from contextlib import contextmanager
from functools import lru_cache
from typing import Iterator

#: set to 0 to leave the allocator as it is
ENV_VAR = "CAPSSIM_REUSE_FREED_MEMORY"
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
#: glibc's defaults of ``M_MMAP_MAX`` (mmapped blocks allowed at once) and ``M_TRIM_THRESHOLD`` (bytes)
DEFAULT_MMAP_MAX, DEFAULT_TRIM_THRESHOLD = 65536, 128 * 1024
#: free heap memory kept at the top of the heap while active (never given back in between)
KEEP_BYTES = 2**31 - 1


@lru_cache(maxsize=1)
def _glibc():
    """The C library if it is glibc with ``mallopt`` and ``malloc_trim``, else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018  (glibc only)
        libc.mallopt.argtypes, libc.mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
        libc.malloc_trim.argtypes, libc.malloc_trim.restype = (ctypes.c_size_t,), ctypes.c_int
        return libc
    except (OSError, AttributeError):
        return None


@contextmanager
def reuse_freed_memory(enabled: bool = True) -> Iterator[bool]:
    """Within the block, large allocations reuse freed heap memory instead of fresh ``mmap`` calls.

    Yields whether the switch is active (False off glibc or when ``enabled`` is False). It is
    process-wide; a nested block leaves the switching to the outermost active one.
    """
    libc = _glibc() if enabled and os.environ.get(ENV_VAR, "1") != "0" else None
    if libc is None or _State.active:
        yield _State.active
        return
    _State.active = True
    libc.mallopt(M_MMAP_MAX, 0)
    libc.mallopt(M_TRIM_THRESHOLD, KEEP_BYTES)
    try:
        yield True
    finally:
        _State.active = False
        libc.mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)
        libc.mallopt(M_TRIM_THRESHOLD, DEFAULT_TRIM_THRESHOLD)
        libc.malloc_trim(0)


class _State:
    active = False


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]


def held_free_bytes() -> int:
    """Bytes this process has freed but glibc keeps in its heap for reuse (``mallinfo2().fordblks``, glibc
    2.33 and later); 0 elsewhere. Some of it may be fragments too small for a large request: an estimate."""
    libc = _glibc()
    mallinfo2 = getattr(libc, "mallinfo2", None) if libc is not None else None
    if mallinfo2 is None:
        return 0
    mallinfo2.argtypes, mallinfo2.restype = (), _MallInfo2
    return int(mallinfo2().fordblks)


__all__ = ["held_free_bytes", "reuse_freed_memory"]
