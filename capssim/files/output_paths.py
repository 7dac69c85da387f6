"""Output paths, resolved before any work, and file-system errors as one-line user errors.

Every command that writes checks its outputs here first (:func:`resolve_output`), so that a path a
result cannot be written to is refused *before* the computation, never after it:

* symbolic links are followed: a link to a folder (or to a place a folder can be made) is written
  through; a link loop is refused;
* a file where a folder is wanted (or a folder where a file is wanted) is refused;
* the nearest existing folder must accept a new entry (read-only, ``/sys``, no permission: refused).

An ``OSError`` while writing (a full disk, a read-only file system, a name too long) becomes an
:class:`~capssim.errors.InputError` naming the path and the error (:func:`write_error`); the atomic
writers of :mod:`capssim.files.imageio` remove their temporaries before raising it.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from pathlib import Path
from typing import Iterable, Iterator, Literal

from capssim.errors import InputError

#: what to do about an ``OSError`` of this errno while writing
_FIXES = {
    errno.ENOSPC: "Free some disk space, or choose an output on another disk.",
    errno.EDQUOT: "Free some of your disk quota, or choose an output on another disk.",
    errno.EROFS: "The file system is mounted read-only: choose an output on another disk.",
    errno.EACCES: "Choose a folder you can write to, or change its permissions.",
    errno.EPERM: "Choose a folder you can write to, or change its permissions.",
    errno.ENAMETOOLONG: "Choose a shorter name.",
    errno.ELOOP: "Remove the symbolic-link loop, or choose another path.",
    errno.EISDIR: "Remove or rename the folder in the way, or choose another path.",
    errno.ENOTDIR: "Remove or rename the file in the way, or choose another path.",
    errno.EEXIST: "Remove or rename what is in the way, or choose another path.",
    errno.EFBIG: "Choose an output on a file system that takes large files.",
}


def describe_os_error(exc: OSError) -> str:
    """``'No space left on device, ENOSPC'``: the errno's meaning and name (the text alone if it has none)."""
    code = exc.errno
    meaning = exc.strerror or (os.strerror(code) if code else str(exc) or type(exc).__name__)
    name = errno.errorcode.get(code) if code else None
    return f"{meaning}, {name}" if name else meaning


def write_error(path: str | os.PathLike, exc: OSError, *, argument: str = "output") -> InputError:
    """The one-line :class:`InputError` for ``exc``, raised while writing ``path`` (the final name, not a temporary).

    The error keeps ``path`` and the ``OSError`` (attributes ``path``, ``os_error``), so a writer of a whole
    folder can name the file in the final folder instead of its temporary."""
    error = InputError(argument, f"{str(path)!r} that could not be written ({describe_os_error(exc)})",
                       "a path where the result can be written", _FIXES.get(exc.errno, "Choose another path."))
    error.path, error.os_error = Path(path), exc
    return error


@contextlib.contextmanager
def writing(path: str | os.PathLike, *, argument: str = "output") -> Iterator[None]:
    """Turn an ``OSError`` raised in the block into :func:`write_error` of ``path`` (other errors pass)."""
    try:
        yield
    except OSError as exc:
        raise write_error(path, exc, argument=argument) from None


def follow_links(path: str | os.PathLike, *, argument: str = "-o/--output") -> Path:
    """``path`` with every symbolic link in it followed (a dangling link: the place it names); a loop is refused.

    A path without links is returned as given (relative stays relative), so messages show what the user typed.
    """
    path = Path(path)
    try:
        resolved = os.path.realpath(path, strict=True)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(argument, f"{str(path)!r}, a symbolic link that loops back on itself",
                             "a path to a folder or file, or a link to one", _FIXES[errno.ELOOP]) from None
        resolved = os.path.realpath(path)  # missing (or a dangling link): the place it names
    if Path(resolved) == path.absolute():
        return path
    return Path(resolved)


def check_writable_location(path: str | os.PathLike, *, argument: str = "-o/--output",
                            shown: str | None = None) -> Path:
    """Fail early (before any work) if ``path`` cannot be created: a parent is a file, or the
    nearest existing folder refuses a new entry (read-only, a system folder such as ``/sys``).

    Creates nothing that stays: the nearest existing folder is probed with a temporary folder.
    Returns ``path`` with its symbolic links followed (:func:`follow_links`); ``shown`` is how the
    messages name it (default: ``path`` as given, with the place a link names).
    """
    given = Path(path)
    path = follow_links(given, argument=argument)
    if shown is None:
        shown = repr(str(given)) + (f" (a link to {str(path)!r})" if path != given else "")
    probe_dir = None
    for folder in (path.absolute(), *path.absolute().parents):
        if folder.exists():
            if not folder.is_dir():
                raise InputError(argument, f"{shown}, under the existing file {str(folder)!r}",
                                 "a path whose parents are folders", "Choose another path.")
            probe_dir = folder
            break
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".capssim-probe-", dir=probe_dir))
    except OSError as exc:
        raise InputError(argument, f"{shown}, where {str(probe_dir)!r} refuses new files "
                         f"({exc.strerror or exc})", "a path in a folder you can write to",
                         "Choose another path.") from None
    return path


def resolve_output(path: str | os.PathLike, *, kind: Literal["folder", "file"] = "folder", overwrite: bool = False,
                   argument: str = "-o/--output") -> Path:
    """Check an output before any work; return where it will be written (symbolic links followed).

    Parameters
    ----------
    path : str or pathlib.Path
        The output the user named.
    kind : {"folder", "file"}
        What the command makes there.
    overwrite : bool
        Whether an existing output may be replaced (a folder without it is refused; a file with
        ``overwrite=False`` too).
    argument : str
        The option or argument named in the messages.

    Returns
    -------
    pathlib.Path
        Where the output will be written: ``path`` with its symbolic links followed.

    Raises
    ------
    InputError
        A link loop; a file where a folder is wanted or a folder where a file is wanted; an existing
        output without ``overwrite``; a parent that is a file; a place that refuses new entries.
    """
    if kind not in ("folder", "file"):
        raise ValueError(f"kind must be 'folder' or 'file', not {kind!r}")
    with writing(path, argument=argument):  # a name too long, a folder that cannot be read: one line
        return _resolve_output(Path(path), kind=kind, overwrite=overwrite, argument=argument)


def _resolve_output(given: Path, *, kind: str, overwrite: bool, argument: str) -> Path:
    target = follow_links(given, argument=argument)
    shown = repr(str(given)) + (f" (a link to {str(target)!r})" if target != given else "")
    if target.exists():  # what is in the way first: --overwrite replaces an output, never something else
        if kind == "file" and target.is_dir():
            raise InputError(argument, f"{shown}, an existing folder", "a file path",
                             "Remove or rename the folder in the way, or choose another path.")
        if kind == "folder" and not target.is_dir():
            raise InputError(argument, f"{shown}, an existing file", "a folder path",
                             "Remove or rename the file in the way, or choose another path.")
        if not overwrite:
            raise InputError(argument, f"existing path {shown}", "a path that does not exist yet",
                             f"Choose another {argument}, or pass --overwrite to replace it.")
    check_writable_location(target.parent if kind == "file" else target, argument=argument, shown=shown)
    return target


def check_files_in(folder: str | os.PathLike, names: Iterable[str], *, argument: str) -> None:
    """Before any work, refuse a folder in the way of a file a command will write into an existing ``folder``.

    ``names`` are relative paths (``"metrics.json"``, ``"recon/caps.tiff"``); each is checked with
    :func:`resolve_output` (a file, replaced if it exists). A ``folder`` that does not exist is left to
    the command's own input check.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return
    for name in names:
        target = folder / name
        for parent in reversed(target.relative_to(folder).parents[:-1]):  # recon/ must be a folder
            if (folder / parent).exists() and not (folder / parent).is_dir():
                raise InputError(argument, f"{str(folder / parent)!r}, an existing file", "a folder there",
                                 "Remove or rename the file in the way.")
        resolve_output(target, kind="file", overwrite=True, argument=argument)
