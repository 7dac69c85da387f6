"""The capture folder: what simulate and render write, and what reconstruct and evaluate read.

Layout (README "Capture folder format")::

    CAPTURE/
      meta.json        geometry, CFA, DoFP layout, 16 homographies, PSF, sensor, seed, source
      caps_raw.tiff    (4, H, W)   aperture n behind a polarizer at 45*n deg, RGGB
      dofp_raw.tiff    (2H, 2W)    DoFP colour-polarization mosaic (optional)
      gt.tiff          (12, 2H, 2W) float32 ground truth (optional)
      recon/NAME.tiff  (12, 2H, 2W) float32, one per method, and recon/NAME.json
      recon/NAME.std.tiff, NAME.interval90.tiff, NAME.stokes-uncertainty.tiff
                       its error bars, with --uncertainty (capssim.reconstruct.uncertainty.maps)

Raw frames are float32 on [0, 1] for ``sensor.model == "none"``, else uint16 DN with
``sensor.black_level`` and ``sensor.white_level``.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tifffile

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.camera_setup import DEFAULT_DOFP_LAYOUT, CameraSetup
from capssim.camera.psf import PSF
from capssim.camera.rig import RigModel
from capssim.camera.sensor import Sensor, sensor_from_meta
from capssim.captures.capture_meta import (  # noqa: F401  (re-exported: the capture format's public names)
    CAPTURE_KINDS,
    SCHEMA,
    SCHEMA_VERSION,
    build_meta,
    software_versions,
    validate_meta,
)
from capssim.captures.capture_schema import MetaSchemaError
from capssim.conventions import (
    N_APERTURES,
    N_CHANNELS,
    cfa_pattern,
    dofp_layout,
    flip_to_rggb,
    mirror_layout,
    split_bayer,
)
from capssim.errors import CapssimError, CaptureFormatError, InputError
from capssim.files.imageio import atomic_directory, atomic_write_json, write_tiff
from capssim.files.schema import ConfigError, load_json_file
from capssim.runtime.resources import check_memory

log = logging.getLogger(__name__)


@dataclass
class Capture:
    """A capture in memory: the raw frames, their ``meta.json`` and optionally the ground truth.

    Parameters
    ----------
    meta : dict
        The ``meta.json`` dictionary (:func:`~capssim.captures.capture.build_meta`; checked by :func:`validate_meta`).
    caps_raw : numpy.ndarray
        ``(4, H, W)`` raw Bayer frames of the four apertures (DN, the sensor's dtype).
    dofp_raw : numpy.ndarray, optional
        ``(2H, 2W)`` raw frame of the DoFP colour-polarization camera.
    gt : numpy.ndarray, optional
        ``(12, 2H, 2W)`` float32 ground truth on [0, 1], channel ``c = 3 p + k``.
    path : pathlib.Path, optional
        The folder it was read from or written to.
    """

    meta: dict
    caps_raw: np.ndarray
    dofp_raw: np.ndarray | None = None
    gt: np.ndarray | None = None
    path: Path | None = field(default=None, compare=False)

    # geometry --------------------------------------------------------------------------
    @property
    def hr_shape(self) -> tuple[int, int]:
        g = self.meta["geometry"]
        return int(g["hr_height"]), int(g["hr_width"])

    @property
    def raw_shape(self) -> tuple[int, int]:
        g = self.meta["geometry"]
        return int(g["raw_height"]), int(g["raw_width"])

    @property
    def sensor(self) -> Sensor:
        return sensor_from_meta(self.meta["sensor"])

    @property
    def dofp_layout(self):
        return dofp_layout(self.meta.get("dofp_layout", DEFAULT_DOFP_LAYOUT))

    @property
    def cfa(self) -> str:
        """The Bayer pattern of the raw frames (``meta.json["cfa"]``; RGGB when absent)."""
        return cfa_pattern(self.meta.get("cfa", "RGGB"))

    @property
    def setup(self) -> CameraSetup:
        """The camera set-up (``meta.json["setup"]``, or derived from the old keys of an older file)."""
        return CameraSetup.from_meta(self.meta)

    @property
    def extinction_ratio(self) -> float | None:
        return self.meta.get("extinction_ratio")

    @property
    def rig(self) -> RigModel | None:
        """The true imperfect array of a simulated or rendered capture (``meta.json["rig"]``), or ``None``."""
        return None if self.meta.get("rig") is None else RigModel.from_dict(self.meta["rig"], where="meta.json rig")

    @property
    def geometry(self) -> ArrayGeometry:
        """The array geometry stored in ``meta.json`` (its 16 sub-image homographies checked against its 4)."""
        return ArrayGeometry.from_meta(self.meta)

    def aperture_homographies(self) -> np.ndarray:
        """``(4, 3, 3)`` stored HR reference -> aperture-HR homographies."""
        return self.geometry.aperture_homographies.copy()

    def with_aperture_homographies(self, homographies) -> "Capture":
        """The same capture with other stored warps ``(4, 3, 3)`` (HR reference -> aperture-HR) and the sub-image
        homographies derived from them; the frames are shared, not copied."""
        geometry = ArrayGeometry(np.asarray(homographies, dtype=np.float64), self.hr_shape)
        meta = copy.deepcopy(self.meta)
        meta["aperture_homographies"] = geometry.aperture_homographies.tolist()
        for entry, hom in zip(meta.get("lr_images") or [], geometry.lr_homographies):
            entry["homography"] = hom.tolist()
        return Capture(meta=meta, caps_raw=self.caps_raw, dofp_raw=self.dofp_raw, gt=self.gt, path=self.path)

    def true_lr_homographies(self) -> np.ndarray:
        """``(16, 3, 3)`` HR reference -> sub-image homographies, derived from the stored aperture ones."""
        return self.geometry.lr_homographies

    @property
    def psf(self) -> PSF:
        """The optical PSF stored in ``meta.json["psf"]``."""
        return PSF.from_spec(self.meta.get("psf"))

    def psf_kernel(self) -> np.ndarray:
        """``(k, k)`` PSF kernel on the HR grid."""
        return self.psf.kernel()

    def caps_float(self) -> np.ndarray:
        """``(4, H, W)`` float32 raw frames on [0, 1] full scale."""
        return self.sensor.to_float(self.caps_raw)

    def caps_saturated(self) -> np.ndarray:
        return self.sensor.saturation_mask(self.caps_raw)

    def lr_images(self) -> tuple[np.ndarray, np.ndarray]:
        """The 16 Bayer sub-images ``m = 4 n + q`` and their saturation masks (paper section 3.1, eq. 11).

        Returns
        -------
        images : numpy.ndarray
            ``(16, H/2, W/2)`` float32 on the sensor's [0, 1] scale.
        saturated : numpy.ndarray
            ``(16, H/2, W/2)`` bool, True at clipped pixels.
        """
        return split_bayer(self.caps_float()), split_bayer(self.caps_saturated(), argument="saturated")

    def dofp_float(self) -> np.ndarray:
        if self.dofp_raw is None:
            raise CaptureFormatError(f"{self.path or 'capture'}: no dofp_raw.tiff in this capture.")
        return self.sensor.to_float(self.dofp_raw)

    def dofp_saturated(self) -> np.ndarray:
        if self.dofp_raw is None:
            raise CaptureFormatError(f"{self.path or 'capture'}: no dofp_raw.tiff in this capture.")
        return self.sensor.saturation_mask(self.dofp_raw)

    def dofp_as_rggb(self) -> "Capture":
        """This capture with its DoFP mosaic read as an RGGB quad Bayer: rows and/or columns reversed
        (:func:`capssim.conventions.flip_to_rggb`, exact: the mosaic's sides are multiples of 4) and the
        polarizer cell mirrored alike. A result on its grid maps back with ``flip_to_rggb(result, cfa)``.
        The capture itself when its ``cfa`` is RGGB."""
        cfa = self.cfa
        if cfa == "RGGB" or self.dofp_raw is None:
            return self
        meta = dict(self.meta, cfa="RGGB", dofp_layout=[list(r) for r in mirror_layout(self.dofp_layout, cfa)])
        meta.pop("dofp_layout_name", None)
        if isinstance(meta.get("setup"), dict):  # the set-up block's layout follows the top level's
            meta["setup"] = {k: v for k, v in meta["setup"].items() if k != "dofp_layout"}
        return Capture(meta=meta, caps_raw=self.caps_raw, dofp_raw=flip_to_rggb(self.dofp_raw, cfa), gt=None,
                       path=self.path)


def _check_layout(name: str, shape: tuple, dtype, expected: tuple, sensor: Sensor | None) -> None:
    """A frame's ``shape`` and ``dtype`` against the geometry's ``expected`` shape and the sensor's
    storage (``sensor`` None: the float ground truth)."""
    if tuple(shape) != expected:
        raise CaptureFormatError(f"{name}: shape {tuple(shape)}, but meta.json geometry says {expected}.")
    if sensor is None:
        if not np.issubdtype(dtype, np.floating):
            raise CaptureFormatError(f"{name}: dtype {dtype}; the ground truth is stored as float on [0, 1].")
    elif sensor.model == "none":
        if dtype != np.float32:
            raise CaptureFormatError(f"{name}: dtype {dtype}; a capture with sensor 'none' stores float32.")
    elif dtype != np.uint16:
        raise CaptureFormatError(f"{name}: dtype {dtype}; a capture with sensor {sensor.model!r} stores uint16 DN.")


def _check_array(name: str, arr: np.ndarray, shape: tuple, sensor: Sensor | None) -> None:
    _check_layout(name, arr.shape, arr.dtype, shape, sensor)
    if (sensor is None or sensor.model == "none") and not np.all(np.isfinite(arr)):
        raise CaptureFormatError(f"{name}: holds NaN or inf values.")


def _read_frame(path: Path, name: str, shape: tuple, sensor: Sensor | None) -> np.ndarray:
    """The TIFF ``path / name``, its header's shape and dtype checked before a pixel is read (a forged
    or mismatched header allocates nothing) and its size against the memory limit."""
    file = path / name
    if not file.is_file():
        raise CaptureFormatError(f"{path}: meta.json lists {name} but the file is missing.")
    quiet = logging.getLogger("tifffile")
    level, quiet.level = quiet.level, logging.ERROR  # its warnings repeat the error below
    try:
        with tifffile.TiffFile(file) as tif:
            series = tif.series[0]
            _check_layout(f"{path.name}/{name}", series.shape, np.dtype(series.dtype), shape, sensor)
            check_memory("meta.json geometry", float(np.prod(shape, dtype=np.float64)) * series.dtype.itemsize,
                         what=f"reading {name}", fix="Check the geometry in meta.json.")
            array = series.asarray()
    except CapssimError:
        raise
    except Exception as exc:  # tifffile raises many kinds
        raise InputError(f"{path.name}/{name}", f"unreadable TIFF {str(file)!r} ({exc})", "a valid TIFF file") from None
    finally:
        quiet.level = level
    _check_array(f"{path.name}/{name}", array, shape, sensor)
    return array


def write_capture(path, capture: Capture, *, overwrite: bool = False) -> Path:
    """Write a capture folder atomically (built under a temporary name, then renamed).

    Parameters
    ----------
    path : str or pathlib.Path
        The folder to create.
    capture : Capture
        The capture; its ``meta.json`` and array shapes are checked first.
    overwrite : bool
        Replace an existing folder (otherwise an existing one is an error).

    Returns
    -------
    pathlib.Path
        ``path``; ``capture.path`` is set to it.
    """
    validate_meta(capture.meta)
    hh, ww = capture.hr_shape
    h, w = capture.raw_shape
    sensor = capture.sensor
    _check_array("caps_raw", capture.caps_raw, (N_APERTURES, h, w), sensor)
    if capture.dofp_raw is not None:
        _check_array("dofp_raw", capture.dofp_raw, (hh, ww), sensor)
    if capture.gt is not None and capture.gt.shape != (N_CHANNELS, hh, ww):
        raise CaptureFormatError(f"gt: shape {capture.gt.shape}; expected {(N_CHANNELS, hh, ww)}.")
    with atomic_directory(path, overwrite=overwrite) as tmp:
        write_tiff(tmp / "caps_raw.tiff", capture.caps_raw)
        if capture.dofp_raw is not None:
            write_tiff(tmp / "dofp_raw.tiff", capture.dofp_raw)
        if capture.gt is not None:
            write_tiff(tmp / "gt.tiff", capture.gt.astype(np.float32))
        atomic_write_json(tmp / "meta.json", capture.meta)
    capture.path = Path(path)
    return Path(path)


def read_meta(path) -> dict:
    path = Path(path)
    if not path.is_dir():
        raise InputError("capture", str(path), "an existing capture folder (with meta.json)",
                         "Create one with 'capssim simulate' or 'capssim render'.")
    meta_path = path / "meta.json"
    if not meta_path.is_file():
        raise CaptureFormatError(f"{path}: no meta.json; this is not a capture folder. See README 'Capture folder format'.")
    try:  # nesting, encoding and syntax guarded; a CaptureFormatError as well as a ConfigError
        meta = load_json_file(meta_path, kind="meta.json", example="docs: guides/captures.md")
    except ConfigError as exc:
        received = str(exc.received).replace("text that is not valid JSON", "corrupt JSON: text that is not valid")
        raise MetaSchemaError(exc.key_path, received, exc.valid, exc.fix, config_file=exc.config_file,
                              kind="meta.json") from None
    validate_meta(meta, path=meta_path)
    return meta


def read_capture(path, *, load_gt: bool = True, require_gt: bool = False) -> Capture:
    """Read and check a capture folder.

    Parameters
    ----------
    path : str or pathlib.Path
        The capture folder (``meta.json``, ``caps_raw.tiff``, optionally ``dofp_raw.tiff``, ``gt.tiff``).
    load_gt : bool
        Read ``gt.tiff`` when present.
    require_gt : bool
        Make a missing ``gt.tiff`` an error (scoring needs it).

    Returns
    -------
    Capture
        ``caps_raw`` ``(4, H, W)``, ``dofp_raw`` ``(2H, 2W)`` or None, ``gt`` ``(12, 2H, 2W)`` float32 or None.

    Raises
    ------
    CaptureFormatError
        A missing or invalid file, naming it and what is expected.
    """
    path = Path(path)
    meta = read_meta(path)
    files = meta["files"]
    sensor = sensor_from_meta(meta["sensor"])
    geo = meta["geometry"]
    hh, ww, h, w = geo["hr_height"], geo["hr_width"], geo["raw_height"], geo["raw_width"]

    caps = _read_frame(path, files["caps_raw"], (N_APERTURES, h, w), sensor)
    dofp = None if files.get("dofp_raw") is None else _read_frame(path, files["dofp_raw"], (hh, ww), sensor)
    gt = None
    if load_gt or require_gt:
        if files.get("gt") is None or not (path / files["gt"]).is_file():
            if require_gt:
                raise CaptureFormatError(f"{path}: no gt.tiff; scoring needs the ground truth. "
                                         "Captures from a real camera cannot be scored.")
        else:
            gt = _read_frame(path, files["gt"], (N_CHANNELS, hh, ww), None).astype(np.float32, copy=False)
    return Capture(meta=meta, caps_raw=caps, dofp_raw=dofp, gt=gt, path=path)


# -- reconstruction outputs -------------------------------------------------------------------
#: ``recon/NAME{suffix}.tiff`` files that belong to the reconstruction ``NAME`` (its error bars), by name
COMPANION_SUFFIXES = {"std": ".std", "interval90": ".interval90", "stokes": ".stokes-uncertainty"}


def write_reconstruction(capture_path, method: str, image: np.ndarray, record: dict, *,
                         companions: dict[str, np.ndarray] | None = None) -> tuple[Path, Path]:
    """Write ``recon/METHOD.tiff`` and ``recon/METHOD.json`` into a capture folder, atomically.

    Parameters
    ----------
    capture_path : str or pathlib.Path
        The capture folder.
    method : str
        The file stem, usually the method's name.
    image : numpy.ndarray
        ``(12, 2H, 2W)`` finite reconstruction (written as float32).
    record : dict
        The record of :func:`capssim.reconstruct.reconstruct` (JSON-serializable).
    companions : dict, optional
        ``{name: array}`` written as ``recon/METHOD{COMPANION_SUFFIXES[name]}.tiff`` (float32) before the record,
        which is written last: a folder with the record has every file it names.

    Returns
    -------
    tuple of pathlib.Path
        The TIFF and the JSON paths.
    """
    capture_path = Path(capture_path)
    meta = read_meta(capture_path)
    shape = (N_CHANNELS, meta["geometry"]["hr_height"], meta["geometry"]["hr_width"])
    image = np.asarray(image)
    if image.shape != shape:
        raise InputError("image", f"shape {image.shape}", f"shape {shape}")
    if not np.all(np.isfinite(image)):
        raise InputError("image", f"{int(np.sum(~np.isfinite(image)))} NaN/inf values", "a finite reconstruction")
    out_dir = capture_path / "recon"
    tiff, js = out_dir / f"{method}.tiff", out_dir / f"{method}.json"
    write_tiff(tiff, image.astype(np.float32))
    for name, array in (companions or {}).items():
        if name not in COMPANION_SUFFIXES:
            raise InputError("companions", repr(name), "one of " + ", ".join(COMPANION_SUFFIXES))
        write_tiff(out_dir / f"{method}{COMPANION_SUFFIXES[name]}.tiff", np.asarray(array, dtype=np.float32))
    for name, suffix in COMPANION_SUFFIXES.items():  # an earlier run's error bars do not describe this image
        if name not in (companions or {}):
            (out_dir / f"{method}{suffix}.tiff").unlink(missing_ok=True)
    atomic_write_json(js, record)
    return tiff, js


def list_reconstructions(capture_path) -> list[str]:
    """The reconstructions ``recon/NAME.tiff`` of a capture folder, by name (not their companion files)."""
    d = Path(capture_path) / "recon"
    if not d.is_dir():
        return []
    stems = {p.stem for p in d.glob("*.tiff")}
    companions = {s for s in stems for suffix in COMPANION_SUFFIXES.values()
                  if s.endswith(suffix) and s[: -len(suffix)] in stems}
    return sorted(stems - companions)
