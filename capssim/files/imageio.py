"""File input/output with clear errors and atomic writes (temp file, then rename).

Nothing a user wrote is ever half-written: files go to ``NAME.tmp-XXXX`` next to the
target and are renamed into place; folders are built under a temporary name and renamed.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import socket
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np

from capssim.conventions import POLARIZER_ANGLES_DEG
from capssim.errors import InputError
from capssim.files.output_paths import (  # check_writable_location moved there; still imported from here
    check_writable_location,  # noqa: F401
    follow_links,
    resolve_output,
    write_error,
    writing,
)

log = logging.getLogger(__name__)

GT_IMAGE_SUFFIXES = (".png", ".tif", ".tiff")


# -- atomic writing -------------------------------------------------------------------------
#: temporary names are ``.NAME.tmp-HOST-PID-XXXX`` (HOST: a short hash of the host name), so a later
#: run can tell a dead writer's leftover (same host, PID no longer running) from a live writer's
_HOST_TAG = hashlib.blake2b(socket.gethostname().encode(), digest_size=3).hexdigest()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _tmp_prefix(path: Path) -> str:
    return f".{path.name}.tmp-{_HOST_TAG}-{os.getpid()}-"


def _pid_running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and folders a killed writer of ``path`` left next to it.

    Only ``.NAME.tmp-HOST-PID-XXXX`` and ``.NAME.old-PID`` siblings of this host whose PID is
    no longer running are removed, so a concurrent writer's temporaries are never touched.
    Returns what was removed.
    """
    path = Path(path)
    removed: list[Path] = []
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return removed
    tmp_head, old_head = f".{path.name}.tmp-{_HOST_TAG}-", f".{path.name}.old-"
    for entry in entries:
        if entry.name.startswith(tmp_head):
            pid_text = entry.name[len(tmp_head):].split("-", 1)[0]
        elif entry.name.startswith(old_head):
            pid_text = entry.name[len(old_head):]
        else:
            continue
        if not pid_text.isdigit() or int(pid_text) == os.getpid() or _pid_running(int(pid_text)):
            continue
        target = Path(entry.path)
        if entry.is_dir(follow_symlinks=False):
            shutil.rmtree(target, ignore_errors=True)
        else:
            target.unlink(missing_ok=True)
        removed.append(target)
        log.info("removed %s (left by a writer that no longer runs)", target)
    return removed


def _tmp_sibling(path: Path) -> Path:
    remove_stale_temporaries(path)
    try:
        fd, name = tempfile.mkstemp(prefix=_tmp_prefix(path), dir=path.parent)
    except OSError as exc:
        raise write_error(path, exc, argument="output file") from None
    os.close(fd)
    os.chmod(name, 0o666 & ~_umask())
    return Path(name)


def check_output_free(path: str | os.PathLike, *, overwrite: bool = False, argument: str = "-o/--output") -> Path:
    """Fail early (before any work) if the folder ``path`` exists and ``overwrite`` is not set, or cannot be
    written; returns where it will be written (:func:`capssim.files.output_paths.resolve_output`: links followed)."""
    return resolve_output(path, kind="folder", overwrite=overwrite, argument=argument)


def check_output_file(path: str | os.PathLike, *, argument: str) -> Path:
    """Fail early (before any work) if the file ``path`` cannot be written (a folder, or an unwritable place);
    an existing file is replaced. Returns where it will be written (links followed)."""
    return resolve_output(path, kind="file", overwrite=True, argument=argument)


def _make_parent(path: Path, argument: str) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise write_error(path, exc, argument=argument) from None


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    path = follow_links(path, argument="output file")  # a link to a file is written through, not replaced
    _make_parent(path, "output file")
    tmp = _tmp_sibling(path)
    try:
        with writing(path):
            with open(tmp, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def append_line_durably(path: str | os.PathLike, line: bytes) -> None:
    """Append ``line`` (one JSON line, say, newline included) to ``path``: one ``write`` on an
    ``O_APPEND`` descriptor, then ``fsync``. A kill leaves every earlier line whole and at most
    this one cut short."""
    with writing(path):
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            view = memoryview(line)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.bool_,)):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def file_sha256(path: str | os.PathLike, *, chunk: int = 1 << 20) -> str:
    """sha256 hex digest of a file's bytes, read in ``chunk``-byte blocks (datasets' manifests, benchmark keys)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def write_tiff(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write a TIFF atomically (zlib-compressed, deterministic bytes)."""
    import tifffile

    path = follow_links(path, argument="output file")  # a link to a file is written through, not replaced
    _make_parent(path, "output file")
    tmp = _tmp_sibling(path)
    try:
        with writing(path):
            tifffile.imwrite(tmp, np.ascontiguousarray(array), compression="zlib", photometric="minisblack",
                             metadata=None, software=None)
            os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or grey (H, W) image; floats are taken as [0, 1]."""
    import cv2

    img = np.asarray(image)
    if np.issubdtype(img.dtype, np.floating):
        img = np.round(np.clip(np.nan_to_num(img), 0, 1) * 255).astype(np.uint8)
    if img.ndim == 3:
        img = img[..., ::-1]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise OSError(f"could not encode PNG for {path}")
    atomic_write_bytes(path, buf.tobytes())


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Build a folder under a temporary name; rename it to ``path`` only if the block succeeds.

    An existing ``path`` is an error unless ``overwrite``; then it is replaced only after
    the new folder is complete. Temporaries a killed earlier writer of ``path`` left are removed
    (:func:`remove_stale_temporaries`).
    """
    path = check_output_free(path, overwrite=overwrite)
    _make_parent(path, "-o/--output")
    remove_stale_temporaries(path)
    with writing(path, argument="-o/--output"):
        tmp = Path(tempfile.mkdtemp(prefix=_tmp_prefix(path), dir=path.parent))
        os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
    except (OSError, InputError) as exc:  # a file could not be written: name the output, not the temporary
        shutil.rmtree(tmp, ignore_errors=True)
        os_error = exc if isinstance(exc, OSError) else getattr(exc, "os_error", None)
        inside = _inside(getattr(exc, "path", None) or getattr(os_error, "filename", None), tmp)
        if os_error is None or inside is None:
            raise
        raise write_error(path / inside, os_error, argument="-o/--output") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _rename_into_place(tmp, path)


def _inside(name, folder: Path) -> str | None:
    """``name`` relative to ``folder`` (None when it is not inside it)."""
    try:
        return str(Path(os.fsdecode(name)).relative_to(folder)) if name else None
    except (ValueError, TypeError):
        return None


def _rename_into_place(tmp: Path, path: Path) -> None:
    """The complete folder ``tmp`` renamed to ``path`` (an old ``path`` replaced); on an error nothing is left behind
    and an old ``path`` is put back."""
    old = path.parent / f".{path.name}.old-{os.getpid()}" if path.exists() else None
    try:
        with writing(path, argument="-o/--output"):
            if old is not None:
                os.replace(path, old)
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and not path.exists():
            os.replace(old, path)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


# -- reading --------------------------------------------------------------------------------
def read_tiff(path: str | os.PathLike, *, argument: str = "path") -> np.ndarray:
    import tifffile

    path = Path(path)
    if not path.is_file():
        raise InputError(argument, str(path), "an existing TIFF file")
    try:
        return tifffile.imread(path)
    except Exception as exc:  # tifffile raises many kinds
        raise InputError(argument, f"unreadable TIFF {str(path)!r} ({exc})", "a valid TIFF file") from exc


def read_image(path: str | os.PathLike, *, argument: str = "path") -> tuple[np.ndarray, int]:
    """Read a PNG/TIFF as stored: ``(H, W)`` or ``(H, W, C)`` RGB order, plus its bit depth."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(argument, str(path), "an existing image file")
    if path.suffix.lower() in (".tif", ".tiff"):
        img = read_tiff(path, argument=argument)
    else:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(argument, f"unreadable image {str(path)!r}", "a valid PNG or TIFF file")
        if img.ndim == 3:
            img = img[..., :3][..., ::-1] if img.shape[2] >= 3 else img
    if img.dtype == np.uint8:
        bits = 8
    elif img.dtype == np.uint16:
        bits = 16
    elif np.issubdtype(img.dtype, np.floating):
        bits = 0
    else:
        raise InputError(argument, f"{str(path)!r} of dtype {img.dtype}", "8-bit, 16-bit or float images")
    return np.ascontiguousarray(img), bits


def _normalise(img: np.ndarray, bits: int) -> np.ndarray:
    if bits == 0:
        return img.astype(np.float32)
    return (img.astype(np.float64) / (2**bits - 1)).astype(np.float32)


def read_gt_scene(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Ground truth ``(12, H, W)`` float32 on [0, 1] plus a description of the source.

    ``path`` is a folder with ``0.png 45.png 90.png 135.png`` (8- or 16-bit RGB, TIFF also
    accepted), or a 12-channel float TIFF shaped ``(12, H, W)`` or ``(H, W, 12)``.
    """
    path = Path(path)
    if path.is_dir():
        images, depths, files = [], set(), []
        for angle in POLARIZER_ANGLES_DEG:
            found = [path / f"{angle}{s}" for s in GT_IMAGE_SUFFIXES if (path / f"{angle}{s}").is_file()]
            if not found:
                raise InputError("gt", f"folder {str(path)!r} without {angle}.png",
                                 "a folder holding 0.png 45.png 90.png 135.png (or .tif/.tiff)")
            img, bits = read_image(found[0], argument="gt")
            if img.ndim != 3 or img.shape[2] != 3:
                raise InputError("gt", f"{found[0].name} with shape {img.shape}", "an RGB image (H, W, 3)")
            images.append(img)
            depths.add(bits)
            files.append(found[0].name)
        shapes = {im.shape for im in images}
        if len(shapes) != 1:
            raise InputError("gt", f"images of different sizes {sorted(shapes)}", "four images of one size")
        if len(depths) != 1:
            raise InputError("gt", f"mixed bit depths {sorted(depths)}", "four images of one bit depth (8 or 16)")
        bits = depths.pop()
        stack = np.stack([_normalise(im, bits) for im in images])  # (4, H, W, 3)
        gt = np.ascontiguousarray(stack.transpose(0, 3, 1, 2).reshape(12, *stack.shape[1:3]))
        info = {"type": "polarizer-images", "path": str(path), "files": files, "bit_depth": bits}
    elif path.is_file():
        arr, bits = read_image(path, argument="gt")
        if arr.ndim == 3 and arr.shape[0] == 12:
            gt = arr
        elif arr.ndim == 3 and arr.shape[2] == 12:
            gt = np.moveaxis(arr, 2, 0)
        else:
            raise InputError("gt", f"{str(path)!r} with shape {arr.shape}",
                             "a 12-channel TIFF shaped (12, H, W) or (H, W, 12)")
        gt = np.ascontiguousarray(_normalise(gt, bits))
        info = {"type": "tiff-12ch", "path": str(path), "bit_depth": bits}
    else:
        raise InputError("gt", str(path), "an existing folder of four polarizer images or a 12-channel TIFF")
    if not np.all(np.isfinite(gt)):
        raise InputError("gt", f"{int(np.sum(~np.isfinite(gt)))} NaN/inf values", "finite values")
    return gt, info


def centre_crop(image: np.ndarray, size: int | tuple[int, int]) -> np.ndarray:
    """Centred crop of the last two axes to ``size`` (int for square)."""
    h, w = image.shape[-2:]
    ch, cw = (size, size) if isinstance(size, int) else size
    if ch > h or cw > w or ch <= 0 or cw <= 0:
        raise InputError("crop", f"{ch}x{cw}", f"a size between 1 and the image size {h}x{w}")
    top, left = (h - ch) // 2, (w - cw) // 2
    return np.ascontiguousarray(image[..., top:top + ch, left:left + cw])
