"""The schema of a capture's ``meta.json`` (docs: guides/captures.md, "Capture folder format").

:func:`check_meta_schema` is the first step of :func:`capssim.captures.capture_meta.validate_meta`: the JSON
types and ranges of every field capssim reads, and the fields it cannot honour refused
(docs: guides/limits.md). A problem raises :class:`MetaSchemaError`, one line naming the file and
the key (``kind`` ``meta.json``; a :class:`~capssim.files.schema.ConfigError` and a
:class:`~capssim.errors.CaptureFormatError` both, so older callers still catch it).

Decisions per field (honoured or refused):

* ``cfa``: RGGB, BGGR, GRBG or GBRG, honoured by every method (any case accepted);
* ``polarizer_angles_deg``: must be ``[0, 45, 90, 135]`` (the operators model those four only);
* ``geometry.sr_factor`` 2 and ``geometry.n_apertures`` 4 (the only array capssim models);
* ``dofp_layout_name`` must name the same cell as ``dofp_layout``;
* ``lr_images[m]``: ``index``, ``aperture``, ``polarizer_deg`` and ``bayer_offset_rowcol`` must be
  those of ``m = 4 n + q``; ``colour`` and ``channel`` those the ``cfa`` gives (both optional);
* ``kind``: ``simulated``, ``rendered`` or ``real``;
* a star scene's ``cycles`` (``scene.star``, ``star`` or ``source.star``): an integer >= 1, read by evaluate.

Keys capssim does not read (provenance such as ``poses``, ``render``, ``dataset``) are kept as they
are, unless they are a near-miss of a known key (``cfaa``): that is an error with a "Did you mean".
"""

from __future__ import annotations

import difflib

from capssim.conventions import (
    BAYER_OFFSETS,
    CFA_PATTERNS,
    COLOURS,
    N_APERTURES,
    N_LR_IMAGES,
    POLARIZER_ANGLES_DEG,
    SR_FACTOR,
    cfa_pattern,
    dofp_layout,
    lr_image_channels,
)
from capssim.errors import CaptureFormatError, InputError
from capssim.files.schema import (
    AnyMapping,
    ConfigError,
    Custom,
    Integer,
    Mapping,
    Nullable,
    Number,
    Sequence,
    Spec,
    String,
    validate,
)

#: the kinds of capture (``meta.json["kind"]``)
CAPTURE_KINDS = ("simulated", "rendered", "real")


class MetaSchemaError(ConfigError, CaptureFormatError):
    """A ``meta.json`` that breaks its schema (one line: file, key, what it holds, what is valid)."""


class Free(Spec):
    """Any JSON value (provenance capssim does not read)."""

    description = "any JSON value"

    def check(self, value, path):
        return value


class Tolerant(Mapping):
    """A :class:`Mapping` that keeps unknown keys (provenance) but refuses a near-miss of a known key."""

    def __init__(self, fields, *, required=(), what="a mapping"):
        super().__init__(fields, required=required, extra=Free(), what=what)

    def check(self, value, path):
        if isinstance(value, dict):
            for key in value:
                if key not in self.fields:
                    close = difflib.get_close_matches(str(key), list(self.fields), n=1, cutoff=0.8)
                    if close:
                        raise ConfigError(f"{path}.{key}" if path else str(key), "an unknown key",
                                          f"one of {', '.join(self.fields)}", f"Did you mean {close[0]!r}?")
        return super().check(value, path)


def _exactly(expected, what: str):
    def check(value):
        if value != expected:
            raise InputError("", value, f"{expected} ({what}; capssim models no other)",
                             "Fix the value, or remove the key.")
        return value
    return Custom(check, f"{expected}")


def _cfa(value):
    if not isinstance(value, str):
        raise InputError("cfa", value, f"one of {', '.join(CFA_PATTERNS)}")
    return cfa_pattern(value)


def _layout(value):
    try:
        return dofp_layout(value)
    except InputError as exc:
        raise InputError("dofp_layout", value, exc.valid) from None


STAR_SPEC = Tolerant({
    "cycles": Integer(minimum=1),
    "center_rowcol": Nullable(Sequence(Number(), lengths=(2,), what="numbers (row, col)")),
    "radius_px": Nullable(Number(minimum=0, exclusive_minimum=True)),
    "contrast": Nullable(Number(minimum=0)),
}, required=("cycles",), what="a star description (cycles, center_rowcol, radius_px, contrast)")

SCENE_SPEC = Tolerant({"star": Nullable(STAR_SPEC)}, what="the scene's provenance")

GEOMETRY_SPEC = Tolerant({
    "hr_height": Integer(minimum=4, multiple_of=4), "hr_width": Integer(minimum=4, multiple_of=4),
    "raw_height": Integer(minimum=2, multiple_of=2), "raw_width": Integer(minimum=2, multiple_of=2),
    "sub_height": Integer(minimum=1), "sub_width": Integer(minimum=1),
    "sr_factor": _exactly(SR_FACTOR, "the camera array's super-resolution factor"),
    "n_apertures": _exactly(N_APERTURES, "the number of apertures"),
}, required=("hr_height", "hr_width", "raw_height", "raw_width"),
    what="an object with hr_height, hr_width, raw_height, raw_width")

LR_IMAGE_SPEC = Tolerant({
    "index": Integer(minimum=0, maximum=N_LR_IMAGES - 1), "aperture": Integer(minimum=0, maximum=N_APERTURES - 1),
    "polarizer_deg": Number(), "bayer_site": String(), "colour": String(choices=list(COLOURS)),
    "channel": Integer(minimum=0, maximum=11),
    "bayer_offset_rowcol": Sequence(Integer(minimum=0, maximum=1), lengths=(2,), what="integers (row, col)"),
    "homography": Free(),
}, required=("homography",), what="an lr_images entry (index, aperture, polarizer_deg, ..., homography)")

#: the sensor's model; its other keys are checked by :func:`capssim.camera.sensor.sensor_from_meta`
SENSOR_SPEC = Mapping({"model": String()}, required=("model",), extra=Free(),
                      what="an object with a string 'model' (none, gaussian or poisson-gaussian)")

META_SPEC = Tolerant({
    "schema": String(), "schema_version": Integer(),
    "kind": String(choices=list(CAPTURE_KINDS)),
    "geometry": GEOMETRY_SPEC,
    "conventions": AnyMapping("the conventions"),
    "cfa": Custom(_cfa, f"one of {', '.join(CFA_PATTERNS)}"),
    "polarizer_angles_deg": _exactly(list(POLARIZER_ANGLES_DEG), "the apertures' polarizer angles"),
    "setup": Nullable(AnyMapping("the camera set-up")),
    "extinction_ratio": Nullable(Number(minimum=1, exclusive_minimum=True)),
    "dofp_layout": Custom(_layout, "a 2x2 DoFP polarizer cell"),
    "dofp_layout_name": Custom(_layout, "a DoFP layout name"),
    "aperture_homographies": Free(),
    "lr_images": Sequence(LR_IMAGE_SPEC, lengths=(N_LR_IMAGES,), what="lr_images entries"),
    "psf": Nullable(AnyMapping("a PSF object")),
    "sensor": SENSOR_SPEC,
    "files": Tolerant({"caps_raw": String(), "dofp_raw": Nullable(String()), "gt": Nullable(String())},
                      required=("caps_raw",), what="an object of file names, e.g. {\"caps_raw\": \"caps_raw.tiff\"}"),
    "seed": Nullable(Integer(minimum=0)),
    "source": Tolerant({"star": Nullable(STAR_SPEC)}, what="the ground truth's provenance"),
    "scene": Nullable(SCENE_SPEC),
    "star": Nullable(STAR_SPEC),
    "rig": Nullable(AnyMapping("a rig object")),
    "calibration_file": Nullable(String()),
    "software": AnyMapping("the software versions"),
    # provenance written by capssim's own writers (kept as they are)
    "poses": Free(), "render": Free(), "dataset": Free(), "calibration": Free(), "oracle": Free(), "bench": Free(),
    "scene_params": Free(),
}, required=("geometry", "lr_images", "sensor", "files"), what="a meta.json object")


def _cross_checks(meta: dict) -> None:
    """The fields that must agree with each other: the DoFP layout's name, and each lr_images entry
    with ``m = 4 n + q`` and the ``cfa``."""
    if "dofp_layout" in meta and "dofp_layout_name" in meta:
        if _layout(meta["dofp_layout"]) != _layout(meta["dofp_layout_name"]):
            raise ConfigError("dofp_layout_name", repr(meta["dofp_layout_name"]),
                              f"the name of dofp_layout {meta['dofp_layout']} (the two contradict each other)",
                              "Fix one of them, or remove dofp_layout_name.")
    cfa = _cfa(meta.get("cfa", "RGGB"))
    colours, channels = CFA_PATTERNS[cfa], lr_image_channels(cfa)
    for m, entry in enumerate(meta["lr_images"]):
        n, q = divmod(m, 4)
        expected = {"index": m, "aperture": n, "polarizer_deg": POLARIZER_ANGLES_DEG[n],
                    "bayer_offset_rowcol": list(BAYER_OFFSETS[q]), "colour": COLOURS[colours[q]],
                    "channel": channels[m]}
        for key, want in expected.items():
            if key in entry and entry[key] != want:
                why = f"cfa {cfa}" if key in ("colour", "channel") else f"image m = 4 n + q = {m}"
                raise ConfigError(f"lr_images[{m}].{key}", repr(entry[key]), f"{want!r} (from {why})",
                                  "Fix the entry, or remove the key (it follows from the conventions).")


def check_meta_schema(meta, *, path=None) -> None:
    """Check ``meta`` (a parsed ``meta.json``) against :data:`META_SPEC` and :func:`_cross_checks`.

    Parameters
    ----------
    meta : dict
        The parsed file.
    path : str or pathlib.Path, optional
        The file, named in the message.

    Raises
    ------
    MetaSchemaError
        One line: ``meta.json PATH, key 'K': got ...; expected ...``.
    """
    try:
        validate(META_SPEC, meta, config_file=path, kind="meta.json")
        _cross_checks(meta)
    except ConfigError as exc:
        raise MetaSchemaError(exc.key_path, exc.received, exc.valid, exc.fix,
                              config_file=str(path) if path is not None else None, kind="meta.json") from None
