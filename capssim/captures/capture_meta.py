"""A capture's ``meta.json``: building it (:func:`build_meta`) and checking it (:func:`validate_meta`).

The fields (docs: guides/captures.md, "Capture folder format"): the geometry and the 16 sub-image
homographies, the conventions, the camera set-up (the ``"setup"`` block of
:class:`capssim.camera.camera_setup.CameraSetup`, and the keys the readers use: ``sensor``, ``psf``,
``dofp_layout``, ``extinction_ratio``, ``rig``), the seed, the source and the software versions.
"""

from __future__ import annotations

import json
import platform

import numpy as np

from capssim import __version__
from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.camera_setup import DEFAULT_DOFP_LAYOUT, CameraSetup, setup_contradiction
from capssim.camera.psf import PSF
from capssim.camera.rig import RigModel
from capssim.camera.rig_checks import check_homographies
from capssim.camera.sensor import sensor_from_meta
from capssim.captures.capture_schema import CAPTURE_KINDS, MetaSchemaError, check_meta_schema
from capssim.conventions import (
    BAYER_OFFSETS,
    BAYER_SITE_COLOUR,
    BAYER_SITES,
    COLOURS,
    LR_IMAGE_CHANNELS,
    N_APERTURES,
    N_LR_IMAGES,
    POLARIZER_ANGLES_DEG,
    SR_FACTOR,
    dofp_layout,
)
from capssim.errors import CaptureFormatError, InputError, UnknownNameError

SCHEMA = "capssim.capture"  # the file format's name (not the module's: it stays when code moves)
SCHEMA_VERSION = 1


def software_versions() -> dict:
    import torch

    versions = {"capssim": __version__, "python": platform.python_version(), "numpy": np.__version__,
                "torch": torch.__version__}
    for mod in ("mitsuba", "drjit"):
        try:
            import importlib.metadata as md

            versions[mod] = md.version(mod)
        except Exception:  # not installed
            pass
    return versions


def build_meta(*, kind: str, hr_shape: tuple[int, int], aperture_homographies: np.ndarray, setup: CameraSetup,
               psf: dict | None = None, seed: int | None = None, source: dict | None = None,
               extra: dict | None = None, has_gt: bool = True, has_dofp: bool = True) -> dict:
    """The ``meta.json`` dictionary of a capture (schema version 1).

    Parameters
    ----------
    kind : str
        ``simulated``, ``rendered`` or ``real`` (:data:`CAPTURE_KINDS`).
    hr_shape : tuple of int
        ``(2H, 2W)``, HR pixels.
    aperture_homographies : numpy.ndarray or ArrayGeometry
        ``(4, 3, 3)`` HR reference -> aperture (x=col, y=row).
    setup : CameraSetup
        Written as the ``"setup"`` block and as the keys the readers use (``sensor``, ``dofp_layout``,
        ``extinction_ratio``, ``rig`` when not ideal).
    psf : dict, optional
        ``meta.json["psf"]``, the blur between ``gt.tiff`` and the raw frames (default: the set-up's
        PSF; a render, whose ground truth is already blurred, writes ``none``).
    seed, source, extra : optional
        The seed, the ground truth's provenance, and extra top-level keys.
    has_gt, has_dofp : bool
        Whether ``gt.tiff`` / ``dofp_raw.tiff`` are listed in ``files``.

    Returns
    -------
    dict
        The ``meta.json`` mapping.
    """
    if kind not in CAPTURE_KINDS:
        raise InputError("kind", kind, f"one of {CAPTURE_KINDS}")
    if not isinstance(setup, CameraSetup):
        raise InputError("setup", type(setup).__name__, "a capssim.camera.camera_setup.CameraSetup")
    hh, ww = (int(v) for v in hr_shape)
    geometry = (aperture_homographies if isinstance(aperture_homographies, ArrayGeometry)
                else ArrayGeometry(aperture_homographies, (hh, ww)))
    hn, hm = geometry.aperture_homographies, geometry.lr_homographies
    cell = dofp_layout(setup.dofp_layout)
    lr = []
    for m in range(N_LR_IMAGES):
        n, q = divmod(m, 4)
        lr.append({
            "index": m, "aperture": n, "polarizer_deg": POLARIZER_ANGLES_DEG[n], "bayer_site": BAYER_SITES[q],
            "colour": COLOURS[BAYER_SITE_COLOUR[q]], "channel": LR_IMAGE_CHANNELS[m],
            "bayer_offset_rowcol": list(BAYER_OFFSETS[q]), "homography": hm[m].tolist(),
        })
    meta = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "kind": kind,
        "geometry": {"hr_height": hh, "hr_width": ww, "raw_height": hh // 2, "raw_width": ww // 2,
                     "sub_height": hh // 4, "sub_width": ww // 4, "sr_factor": SR_FACTOR,
                     "n_apertures": N_APERTURES},
        "conventions": {"channel_order": "c = 3*p + k, p over (0,45,90,135) deg, k over (R,G,B)",
                        "homography_coordinates": "(x=col, y=row), pixel centres on integers",
                        "homography_direction": "HR reference pixel -> target pixel"},
        "cfa": "RGGB",
        "polarizer_angles_deg": list(POLARIZER_ANGLES_DEG),
        "setup": setup.to_meta(),
        "extinction_ratio": setup.extinction_ratio,
        "dofp_layout": [list(r) for r in cell],
        "dofp_layout_name": setup.dofp_layout,
        "aperture_homographies": hn.tolist(),
        "lr_images": lr,
        "psf": setup.psf.to_spec() if psf is None else psf,
        "sensor": setup.sensor.to_meta(),
        "files": {"caps_raw": "caps_raw.tiff"},
        "seed": seed,
        "source": source or {},
        "software": software_versions(),
    }
    if setup.rig is not None and not setup.rig.is_ideal:
        meta["rig"] = setup.rig.to_dict()
    if has_dofp:
        meta["files"]["dofp_raw"] = "dofp_raw.tiff"
    if has_gt:
        meta["files"]["gt"] = "gt.tiff"
    if extra:
        meta.update(extra)
    return meta


def _require(meta: dict, key: str, where: str = "meta.json"):
    if key not in meta:
        raise CaptureFormatError(f"{where}: missing key {key!r}. See README 'Capture folder format'.")
    return meta[key]


def _found(value) -> str:
    """What a ``meta.json`` field holds, for a message: its JSON type and a short excerpt."""
    kind = {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}.get(
        type(value), "a number")
    text = json.dumps(value, default=str)
    return f"{kind} {text[:60] + '...' if len(text) > 60 else text}"


def _expect(value, ok: bool, where: str, valid: str):
    if not ok:
        raise CaptureFormatError(f"{where}: got {_found(value)}; expected {valid}. "
                                 "See README 'Capture folder format'.")
    return value


def _matrices(value, shape: tuple, where: str) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``, or a :class:`CaptureFormatError`."""
    valid = f"{' x '.join(map(str, shape))} finite numbers (nested lists)"
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = None
    _expect(value, array is not None and array.shape == shape and bool(np.all(np.isfinite(array))), where, valid)
    return array


def _validate_sensor(sensor: dict) -> None:
    try:
        sensor_from_meta(sensor)
    except (InputError, UnknownNameError) as exc:
        raise CaptureFormatError(f"meta.json sensor: {exc} See README 'Capture folder format'.") from None
    except (TypeError, ValueError) as exc:  # unknown keys, values of the wrong type
        raise CaptureFormatError(f"meta.json sensor: got {_found(sensor)} ({exc}); expected the fields of "
                                 f"model {sensor['model']!r}. See README 'Capture folder format'.") from None


def validate_meta(meta: dict, *, path=None) -> None:
    """Check a ``meta.json`` dictionary: its schema (:mod:`capssim.captures.capture_schema`), then its values.

    Parameters
    ----------
    meta : dict
        The parsed ``meta.json``.
    path : str or pathlib.Path, optional
        The file it was read from, named in the messages.

    Raises
    ------
    CaptureFormatError
        Naming the first problem: the field, what it holds and what is valid.
    """
    _expect(meta, isinstance(meta, dict), "meta.json", "a JSON object")
    if meta.get("schema") != SCHEMA:
        raise CaptureFormatError(f"meta.json: schema is {meta.get('schema')!r}; expected {SCHEMA!r}.")
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise CaptureFormatError(f"meta.json: schema_version {version!r} is not supported; expected {SCHEMA_VERSION}.")
    check_meta_schema(meta, path=path)  # every field's JSON type and range, and the fields that must agree
    geo = meta["geometry"]
    if geo["hr_height"] != 2 * geo["raw_height"] or geo["hr_width"] != 2 * geo["raw_width"]:
        raise CaptureFormatError("meta.json geometry: hr size must be twice the raw size.")
    if geo["raw_height"] % 2 or geo["raw_width"] % 2:
        raise CaptureFormatError("meta.json geometry: raw height and width must be even (RGGB cells).")
    stored = _matrices(_require(meta, "aperture_homographies"), (N_APERTURES, 3, 3), "meta.json aperture_homographies")
    try:  # invertible (a horizon across the image is refused where the warps are used: --true-warps)
        check_homographies(stored, (geo["hr_height"], geo["hr_width"]), where="aperture_homographies", horizon=False)
    except InputError as exc:
        raise MetaSchemaError(exc.argument, exc.received, exc.valid, exc.fix, config_file=path,
                              kind="meta.json") from None
    lr = meta["lr_images"]
    if len(lr) != N_LR_IMAGES:
        raise CaptureFormatError(f"meta.json: lr_images must list 16 images; got {len(lr)}.")
    for m, entry in enumerate(lr):
        _matrices(_require(entry, "homography", f"meta.json lr_images[{m}]"), (3, 3),
                  f"meta.json lr_images[{m}].homography")
    ArrayGeometry.from_meta(meta)
    _validate_sensor(meta["sensor"])
    try:
        dofp_layout(meta.get("dofp_layout", DEFAULT_DOFP_LAYOUT))
    except InputError as exc:
        raise CaptureFormatError(f"meta.json dofp_layout: {exc}") from exc
    try:
        PSF.from_spec(meta.get("psf"))
    except (InputError, TypeError, ValueError) as exc:
        raise CaptureFormatError(f"meta.json psf: got {_found(meta.get('psf'))} ({exc}); expected a PSF object "
                                 "such as {\"type\": \"gaussian\", \"sigma_hr_px\": 0.5}.") from None
    try:
        RigModel.from_dict(meta["rig"], where="meta.json rig") if meta.get("rig") is not None else None
    except InputError as exc:
        raise CaptureFormatError(f"{exc} (the true imperfect array; see docs: guides/calibration.md)") from None
    if meta.get("setup") is not None:
        _check_setup_block(meta, path)


def _check_setup_block(meta: dict, path) -> None:
    """The "setup" block: valid, and saying what the top-level keys say (they are its source; a key it
    leaves out is derived from them). A contradiction names the key, both values and the file."""
    where = f"{path}: " if path is not None else ""
    try:
        found = setup_contradiction(meta)
    except (InputError, UnknownNameError) as exc:
        argument = getattr(exc, "argument", "")
        if isinstance(exc, InputError) and argument.startswith("meta.json setup"):
            raise MetaSchemaError(argument.removeprefix("meta.json "), exc.received, exc.valid,
                                  exc.fix or "See docs: guides/simulation.md, 'The camera set-up'.",
                                  config_file=path, kind="meta.json") from None
        raise CaptureFormatError(f"{where}{exc} (the camera set-up; see docs: guides/simulation.md)") from None
    if found is None:
        return
    key, block_value, top_value = found
    top_key = key.removeprefix("setup.")
    if top_key.startswith("psf") and "psf_sigma_hr_px" in meta["setup"]:
        key = "setup.psf_sigma_hr_px"
    if top_key.startswith("sensor.noise"):
        top_key = "sensor.model"
    elif top_key.startswith("psf") and meta.get("kind") == "rendered":
        top_key = "render.optics_" + top_key
    raise MetaSchemaError(key, _short(block_value), f"{_short(top_value)}, the top-level {top_key} (the set-up "
                          "block repeats the top-level keys, which reconstruct reads)",
                          f"Make the two agree, or remove {'.'.join(key.split('.')[:2])} (it is then derived "
                          "from the top level).", config_file=path,
                          kind="meta.json")


def _short(value) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= 80 else text[:77] + "..."
