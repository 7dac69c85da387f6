"""A resource guard: options that scale memory are checked against an estimate before allocating.

An estimate (bytes) is compared with a limit: ``CAPSSIM_MEMORY_LIMIT_GB`` when set (GiB; ``inf``
turns the guard off), otherwise :data:`MEMORY_FRACTION` of the memory the machine has available
now (``MemAvailable`` in ``/proc/meminfo``). Past the limit a
:class:`~capssim.errors.ResourceError` names the option, the estimate, the limit and how to
change either (docs: guides/limits.md).
"""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

from capssim.errors import InputError, ResourceError
from capssim.runtime.allocator import held_free_bytes

#: environment variable that sets the memory limit explicitly, in GiB (``inf``: no limit)
MEMORY_LIMIT_ENV = "CAPSSIM_MEMORY_LIMIT_GB"
#: share of the available memory one command may plan to use
MEMORY_FRACTION = 0.8


def available_memory_bytes() -> int | None:
    """Memory available to a new allocation now, in bytes (``None`` if the platform does not say): the
    system's (``MemAvailable``) plus the freed memory this process keeps for reuse
    (:func:`capssim.runtime.allocator.held_free_bytes`), which the system counts as used."""
    system = None
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    system = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    if system is None:
        try:
            system = int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
        except (AttributeError, ValueError, OSError):
            return None
    return system + held_free_bytes()


def memory_limit() -> tuple[float, str]:
    """The memory limit in bytes (``inf``: none) and where it comes from, for messages."""
    raw = os.environ.get(MEMORY_LIMIT_ENV)
    if raw is not None and raw.strip():
        try:
            gib = float(raw)
        except ValueError:
            gib = float("nan")
        if not gib > 0:
            raise InputError(MEMORY_LIMIT_ENV, repr(raw), "a positive number of GiB, or inf for no limit")
        return gib * 2**30, f"{MEMORY_LIMIT_ENV}={raw.strip()}"
    available = available_memory_bytes()
    if available is None:
        return math.inf, "no limit (available memory unknown)"
    return MEMORY_FRACTION * available, (f"{MEMORY_FRACTION:.0%} of the {format_bytes(available)} available; "
                                          f"set {MEMORY_LIMIT_ENV} to change it")


def format_bytes(n: float) -> str:
    """``n`` bytes in a short human form (``'1.5 GiB'``)."""
    if not math.isfinite(n):
        return "unbounded"
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} B"


def check_memory(option: str, estimate_bytes: float, *, what: str, fix: str) -> None:
    """Refuse (:class:`~capssim.errors.ResourceError`) an ``option`` whose ``what`` needs more than the limit.

    ``estimate_bytes``: the planned working set; ``fix``: which option to change, and how.
    """
    limit, source = memory_limit()
    if estimate_bytes > limit:
        raise ResourceError(option, estimate_bytes,
                            f"{what} needs about {format_bytes(estimate_bytes)}, more than the memory limit "
                            f"{format_bytes(limit)} ({source}). {fix}")


#: bytes per HR pixel a benchmark's scene holds at least (12 float64 channels, several copies)
SCENE_BYTES_PER_HR_PIXEL = 768


def check_scene_size(option: str, size: int, *, fix: str) -> None:
    """Refuse (:class:`~capssim.errors.ResourceError`) a ``size x size`` HR scene whose data alone would pass
    the memory limit (``bench reconstruct --size``, suite scenes): :data:`SCENE_BYTES_PER_HR_PIXEL` per pixel."""
    check_memory(option, float(size) ** 2 * SCENE_BYTES_PER_HR_PIXEL, what=f"a {size}x{size} scene", fix=fix)


def check_range(option: str, value: float, *, high: float, what: str, reason: str, fix: str) -> None:
    """Refuse an ``option`` past its documented sane range ``value <= high`` (time or memory would explode).

    ``what``: the quantity ``value`` measures; ``reason``: what ``high`` is.
    """
    if value > high:
        raise ResourceError(option, value, f"{what} is {value:g}, past the sane range: at most {high:g} "
                                           f"({reason}). {fix}")


def free_disk_bytes(path: str | os.PathLike) -> int | None:
    """Free bytes on the file system that holds ``path`` (or its nearest existing parent); ``None`` if unknown."""
    where = Path(path).absolute()
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        return shutil.disk_usage(where).free
    except OSError:
        return None


def check_disk(option: str, estimate_bytes: float, path: str | os.PathLike, *, what: str, fix: str) -> None:
    """Refuse (:class:`~capssim.errors.ResourceError`) an ``option`` whose output ``what`` would not fit on the
    disk that holds ``path``."""
    free = free_disk_bytes(path)
    if free is not None and estimate_bytes > free:
        raise ResourceError(option, estimate_bytes,
                            f"{what} would take about {format_bytes(estimate_bytes)} on disk, more than the "
                            f"{format_bytes(free)} free at {path}. {fix}")


def image_header_shape(path: str | os.PathLike) -> tuple[int, ...] | None:
    """The stored shape of a PNG or TIFF read from its header only (no pixel is decoded).

    PNG: ``(H, W)`` or ``(H, W, C)`` from the IHDR chunk; TIFF: the first series' shape (tifffile);
    other formats: PIL's lazy ``size``. ``None`` when the header cannot be read (the reader then
    reports the file itself).
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(26)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(head[25], 4)
            return (h, w) if channels == 1 else (h, w, channels)
        if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
            import logging

            import tifffile

            quiet = logging.getLogger("tifffile")
            level, quiet.level = quiet.level, logging.CRITICAL  # a probe: the reader reports a damaged file
            try:
                with tifffile.TiffFile(path) as tif:
                    return tuple(int(n) for n in tif.series[0].shape)
            finally:
                quiet.setLevel(level)
        from PIL import Image

        with Image.open(path) as img:
            w, h = img.size
            return (h, w, len(img.getbands()))
    except Exception:  # an unreadable header: the image reader gives the one-line error
        return None


def check_image_memory(option: str, path: str | os.PathLike, bytes_per_element: float, *, what: str,
                       fix: str) -> tuple[int, ...] | None:
    """Refuse (:class:`~capssim.errors.ResourceError`) an image whose header shape times ``bytes_per_element``
    (the working set a command builds per stored sample) passes the memory limit, before decoding it.

    Returns the header shape (``None`` if unknown)."""
    shape = image_header_shape(path)
    if shape is not None:
        shown = "x".join(map(str, shape))
        check_memory(option, float(math.prod(shape)) * bytes_per_element, what=f"{what} of {Path(path).name} ({shown})",
                     fix=fix)
    return shape


__all__ = ["MEMORY_FRACTION", "MEMORY_LIMIT_ENV", "SCENE_BYTES_PER_HR_PIXEL", "available_memory_bytes", "check_disk",
           "check_image_memory", "check_memory", "check_range", "check_scene_size", "format_bytes", "free_disk_bytes",
           "image_header_shape", "memory_limit"]
