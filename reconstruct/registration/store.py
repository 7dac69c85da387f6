"""A capture's estimated warps, registered once and stored with the capture (issue 20, "register once").

Every CAPS method that estimates its warps asks :func:`stored_or_computed` for them. The first
asks the registration (:mod:`capssim.reconstruct.registration`) and stores its result in
``CAPTURE/registration/<mode>-<key>.json``; every later method and run that asks for the same
registration reads it back. The key is a SHA-256 of everything the warps depend on:

- the registration's input: the 16 Bayer sub-images ``(16, H/2, W/2)`` as the method passes them
  (float32, so ``caps_raw.tiff`` *and* the ``meta.json`` sensor levels that scale it), their
  saturation mask and the HR shape;
- the registration mode and every field of its
  :class:`~capssim.reconstruct.registration.parameters.RegistrationParameters`;
- the registration's source code (``reconstruct/registration/*.py`` but this store, ``capssim/camera/array_geometry.py``,
  ``capssim/camera/homography.py``), so that a change to the method is never answered from an old result.

A changed raw file, other sensor levels, another mode or option, or new registration code gives
another key and registers again. The file holds that identity, the four aperture homographies
``(4, 3, 3)`` (HR reference -> aperture-HR, as in ``meta.json``) and the registration's record;
it is written atomically. A file that cannot be read, or whose identity differs from the one
asked for, is ignored (and replaced); so are warps that cannot be this capture's
(:func:`warps_problem`: singular, not normalised, a horizon across the image, or an aperture that
sees less than half the reference grid), with a warning naming the file: they are recomputed. A capture folder that cannot be written (read-only) is
registered without storing, with one warning per folder.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import numpy as np

from capssim.camera import array_geometry, homography
from capssim.camera.rig_checks import check_homographies
from capssim.errors import CapssimError, InputError
from capssim.files.imageio import atomic_write_json

from .parameters import RegistrationParameters

log = logging.getLogger(__name__)

#: the folder inside a capture that holds the stored registrations
STORE_FOLDER = "registration"
#: version of the stored file's layout; a file of another version is registered again
FORMAT_VERSION = 1
#: hex digits of the key in the file name (the full key is inside the file)
NAME_KEY_DIGITS = 16
#: least fraction of the HR reference grid stored warps must map inside each aperture's frame
MIN_OVERLAP = 0.5
#: largest area scale (and smallest, its inverse) stored warps may have
MAX_SCALE = 4.0

_warned_read_only: set[str] = set()
_repeated_warnings: set[str] = set()  # keys whose stored warnings this process has logged again


@functools.lru_cache(maxsize=1)
def registration_code_sha256() -> str:
    """SHA-256 of the registration's source files (read once per process)."""
    folder = Path(__file__).resolve().parent
    files = sorted(p for p in folder.glob("*.py") if p.name != Path(__file__).name)  # the registration room
    files += [Path(array_geometry.__file__), Path(homography.__file__)]
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def input_sha256(images: np.ndarray, saturated: np.ndarray | None, hr_shape) -> str:
    """SHA-256 of the registration's input: sub-images (as float32), saturation mask (bool), HR shape."""
    digest = hashlib.sha256()
    arr = np.ascontiguousarray(images, dtype=np.float32)
    digest.update(repr(("images", arr.shape)).encode())
    digest.update(arr.tobytes())
    if saturated is not None:
        sat = np.ascontiguousarray(saturated, dtype=bool)
        digest.update(repr(("saturated", sat.shape)).encode())
        digest.update(sat.tobytes())
    digest.update(repr(("hr_shape", tuple(int(v) for v in hr_shape))).encode())
    return digest.hexdigest()


def registration_identity(images: np.ndarray, saturated: np.ndarray | None, hr_shape, *, mode: str,
                          parameters: RegistrationParameters) -> dict:
    """What stored warps must match to be reused (JSON-ready), with its ``key``: a SHA-256 of the rest."""
    identity = {"format": FORMAT_VERSION, "mode": mode, "parameters": dataclasses.asdict(parameters),
                "input_sha256": input_sha256(images, saturated, hr_shape),
                "hr_shape": [int(v) for v in hr_shape], "code_sha256": registration_code_sha256()}
    identity["key"] = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()
    return identity


def store_path(capture_folder: str | Path, identity: dict) -> Path:
    """``CAPTURE/registration/<mode>-<key prefix>.json``."""
    return Path(capture_folder) / STORE_FOLDER / f"{identity['mode']}-{identity['key'][:NAME_KEY_DIGITS]}.json"


def load_registration(path: Path, identity: dict) -> tuple[np.ndarray, dict] | None:
    """The stored ``(aperture homographies (4, 3, 3), record)`` at ``path`` if it matches ``identity``;
    None when there is no file or it is unreadable, of another identity or holds invalid warps."""
    if not path.is_file():
        return None
    try:
        stored = json.loads(path.read_text())
        aperture = np.asarray(stored["aperture_homographies"], dtype=np.float64)
        record = dict(stored["record"])
        same = {k: stored["identity"].get(k) for k in identity} == identity
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        log.warning("registration store: ignoring %s (%s: %s); registering again", path, type(exc).__name__, exc)
        return None
    if not same:
        log.warning("registration store: %s was stored for another input, mode or code; registering again", path)
        return None
    problem = warps_problem(aperture, identity["hr_shape"])
    if problem is not None:
        log.warning("registration store: %s holds invalid warps (%s); recomputed", path, problem)
        return None
    return aperture, record


def warps_problem(aperture: np.ndarray, hr_shape) -> str | None:
    """Why stored aperture homographies ``(4, 3, 3)`` cannot be the warps of this capture, or None.

    They must be finite, normalised (``h33 = 1``, as the registration writes them), invertible, with
    their horizon outside the ``hr_shape`` grid, and map at least :data:`MIN_OVERLAP` of the grid
    inside the aperture's frame at a local scale within ``[1/MAX_SCALE, MAX_SCALE]``.
    """
    if aperture.shape != (4, 3, 3) or not np.all(np.isfinite(aperture)):
        return f"shape {aperture.shape} or non-finite values, not 4 finite 3x3 matrices"
    if not np.allclose(aperture[:, 2, 2], 1.0, rtol=0.0, atol=1e-6):
        return f"h33 = {aperture[:, 2, 2].tolist()}, not 1"
    try:
        check_homographies(aperture, hr_shape, where="aperture_homographies")
    except InputError as exc:
        return str(exc).split(";")[0]
    hh, ww = (int(v) for v in hr_shape)
    ys, xs = np.meshgrid(np.linspace(0, hh - 1, 17), np.linspace(0, ww - 1, 17), indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    for n, mat in enumerate(aperture):
        q = mat @ pts
        x, y = q[0] / q[2], q[1] / q[2]
        inside = float(np.mean((x >= -0.5) & (x <= ww - 0.5) & (y >= -0.5) & (y <= hh - 0.5)))
        cx, cy = (ww - 1) / 2, (hh - 1) / 2  # the local area scale at the centre (a unit square's image)
        sq = mat @ np.array([[cx, cx + 1, cx, cx + 1], [cy, cy, cy + 1, cy + 1], [1, 1, 1, 1]])
        sx, sy = sq[0] / sq[2], sq[1] / sq[2]
        scale = abs((sx[1] - sx[0]) * (sy[2] - sy[0]) - (sx[2] - sx[0]) * (sy[1] - sy[0]))
        if inside < MIN_OVERLAP or not (1 / MAX_SCALE <= scale <= MAX_SCALE):
            return (f"aperture {n} sees {inside:.0%} of the reference grid at scale {scale:.3g}; a camera array's "
                    f"apertures overlap by >= {MIN_OVERLAP:.0%} at scale 1/{MAX_SCALE:g}..{MAX_SCALE:g}")
    return None


def save_registration(path: Path, identity: dict, aperture: np.ndarray, record: dict) -> bool:
    """Write the registration atomically; False (and one warning per folder) where the folder refuses it."""
    content = {"identity": identity, "stored": datetime.now(timezone.utc).isoformat(timespec="seconds"),
               "aperture_homographies": np.asarray(aperture, dtype=np.float64), "record": record}
    try:
        atomic_write_json(path, content)
    except (OSError, CapssimError) as exc:
        folder = str(path.parent.parent)
        if folder not in _warned_read_only:
            _warned_read_only.add(folder)
            log.warning("registration store: cannot write in %s (%s); the warps are computed without storing them, "
                        "so every method registers again", folder, getattr(exc, "strerror", None) or exc)
        return False
    return True


def stored_or_computed(capture_folder: str | Path | None, compute: Callable[[], tuple[np.ndarray, dict]], *,
                       images: np.ndarray, saturated: np.ndarray | None, hr_shape, mode: str,
                       parameters: RegistrationParameters, reuse: bool = True) -> tuple[np.ndarray, dict]:
    """The aperture homographies ``(4, 3, 3)`` and registration record for this input: stored ones if any
    match, else ``compute()``'s (then stored).

    ``compute`` returns ``(aperture homographies, record)``. ``capture_folder`` None (an in-memory
    capture) computes without storing; ``reuse=False`` computes and replaces the stored file. The
    returned record gains ``store`` (``reused`` | ``computed`` | ``computed, not stored``), ``key``,
    ``reused_from`` (the file read, or None) and ``stored_in`` (the file written, or None).
    """
    identity = registration_identity(images, saturated, hr_shape, mode=mode, parameters=parameters)
    path = None if capture_folder is None else store_path(capture_folder, identity)
    stored = load_registration(path, identity) if (path is not None and reuse) else None
    if stored is not None:
        aperture, record = stored
        record.update(store="reused", key=identity["key"], reused_from=str(path), stored_in=None)
        log.info("registration (%s): reused %s (computed in %.1f s)", mode, path, record.get("time_s") or 0.0)
        if identity["key"] not in _repeated_warnings:  # once per process: every record keeps them
            _repeated_warnings.add(identity["key"])
            for message in record.get("warnings", []):
                log.warning("%s (stored registration)", message)
        return aperture, record
    aperture, record = compute()
    _repeated_warnings.add(identity["key"])  # the registration logged its warnings itself
    written = path is not None and save_registration(path, identity, aperture, record)
    record = dict(record, store="computed" if written else "computed, not stored", key=identity["key"],
                  reused_from=None, stored_in=str(path) if written else None)
    log.info("registration (%s): computed in %.1f s%s", mode, record.get("time_s") or 0.0,
             f", stored in {path}" if written else "")
    return aperture, record
