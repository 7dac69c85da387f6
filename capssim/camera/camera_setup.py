"""The camera set-up: one frozen value for the sensor and its noise, the PSF, the DoFP layout, the
polarizers' extinction ratio, the rig, and the seed rule (paper eq. 9-11, section 5.2).

:class:`CameraSetup` is what simulate, render, calibration captures, the dataset writer and the
benchmark suites build their captures from, and what every capture's ``meta.json`` records as its
``"setup"`` block (:meth:`CameraSetup.to_meta`, :meth:`CameraSetup.from_meta`). One spelling per
quantity, one default each:

* ``sensor``: ``{noise, sigma, preset, exposure, bit_depth, ...}``, the noise model ``noise``
  (``none``, ``gaussian``, ``poisson-gaussian``; default :data:`DEFAULT_NOISE`), the Gaussian std
  ``sigma`` on [0, 1] full scale, an EMVA 1288 ``preset`` (:data:`~capssim.camera.sensor.SENSOR_PRESETS`;
  default :data:`DEFAULT_SENSOR_PRESET`) and the fields that replace the preset's;
* ``psf_sigma_hr_px``: the Gaussian optical PSF's std in HR pixels (0 = no blur; default
  :data:`~capssim.camera.psf.DEFAULT_SIGMA_HR_PX`), or ``psf``: any PSF as ``meta.json["psf"]`` spells it
  (e.g. ``{type: airy, f_number, wavelength_nm, hr_pixel_um}``);
* ``dofp_layout``: the DoFP 2x2 polarizer cell, by name or ``[[a, b], [c, d]]`` degrees (default
  :data:`DEFAULT_DOFP_LAYOUT`, the Sony IMX250MYR's ``[[90, 45], [135, 0]]``);
* ``extinction_ratio``: ``T_max / T_min`` of the polarizers (>= 1; default ``null``, ideal);
* ``rig``: an imperfect array (:class:`~capssim.camera.rig.RigModel`), a preset draw
  ``{preset, seed, <overrides>}`` or :meth:`RigModel.to_dict <capssim.camera.rig.RigModel.to_dict>`'s
  mapping (default ``null``, the ideal array).

The seed rule (:data:`SEED_RULE`, :func:`capssim.operators.measurement.seed_streams`) is part of the set-up;
the seed itself names one capture and stays ``meta.json["seed"]``. A rendered capture's
``meta.json["psf"]`` is ``none`` (its PSF is already in ``gt.tiff``); its set-up's ``psf`` is the
optical PSF the renderer applied.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

from capssim.camera.psf import DEFAULT_PSF, DEFAULT_SIGMA_HR_PX, PSF, as_psf
from capssim.camera.rig import RigModel
from capssim.camera.sensor import (
    DEFAULT_NOISE,
    DEFAULT_SENSOR_PRESET,
    NOISE_MODELS,
    SENSOR_PRESETS,
    GaussianSensor,
    NoNoiseSensor,
    PoissonGaussianSensor,
    Sensor,
    make_sensor,
    sensor_from_meta,
)
from capssim.conventions import DEFAULT_DOFP_LAYOUT, dofp_layout_name
from capssim.errors import InputError, UnknownNameError

#: how one seed becomes the random streams of a capture (:func:`capssim.operators.measurement.seed_streams`)
SEED_RULE = "numpy SeedSequence(seed).spawn(3): aperture poses, CAPS sensor noise, DoFP sensor noise"
#: the keys of a set-up mapping (YAML, the ``meta.json`` "setup" block)
SETUP_KEYS = ("sensor", "psf_sigma_hr_px", "psf", "dofp_layout", "extinction_ratio", "rig", "seed_rule")
#: the keys of a ``sensor`` mapping written by hand (YAML); ``meta.json`` adds the model's own fields
SENSOR_KEYS = ("noise", "sigma", "preset", "exposure", "bit_depth")
#: keys of a rig mapping that say it is :meth:`RigModel.to_dict`'s (else it is a preset draw, RigModel.from_spec)
_RIG_DICT_KEYS = ("vignetting", "psf")

__all__ = ["DEFAULT_DOFP_LAYOUT", "DEFAULT_NOISE", "DEFAULT_SENSOR_PRESET", "DEFAULT_SIGMA_HR_PX", "SEED_RULE",
           "SENSOR_KEYS", "SETUP_KEYS", "CameraSetup", "as_setup", "sensor_from_mapping", "sensor_from_options",
           "setup_contradiction", "top_level_setup_mapping"]


def sensor_from_mapping(mapping, *, where: str = "sensor") -> Sensor:
    """The :class:`~capssim.camera.sensor.Sensor` of a ``sensor`` mapping: ``noise`` (the model; ``model`` in
    ``meta.json`` files written before the set-up block), then ``preset`` (poisson-gaussian: its
    :data:`~capssim.camera.sensor.SENSOR_PRESETS` entry, default :data:`DEFAULT_SENSOR_PRESET`) and the fields
    that replace it. Errors name ``where`` and the key."""
    if not isinstance(mapping, dict):
        raise InputError(where, f"{type(mapping).__name__} {mapping!r}"[:80], "a mapping such as {noise: gaussian, "
                         "sigma: 0.01}", f"Write {where} as a mapping with a 'noise' key.")
    params = dict(mapping)
    if "noise" in params and "model" in params:
        raise InputError(f"{where}.model", params["model"], f"no 'model' key beside 'noise' ({params['noise']!r})",
                         "'noise' names the noise model; remove 'model'.")
    noise = params.pop("noise", params.pop("model", DEFAULT_NOISE))
    if not isinstance(noise, str) or noise.lower() not in NOISE_MODELS:
        raise InputError(f"{where}.noise", repr(noise), f"one of {', '.join(NOISE_MODELS)}",
                         f"For example {where}: {{noise: gaussian, sigma: 0.01}}.")
    noise = noise.lower()
    if noise == "gaussian" and params.get("sigma") is None:
        raise InputError(f"{where}.sigma", "nothing", "the Gaussian noise std on [0, 1] data for noise 'gaussian'",
                         "Add e.g. sigma: 0.01 (--sigma 0.01 on the command line).")
    try:
        if noise != "poisson-gaussian" or not params.get("preset", DEFAULT_SENSOR_PRESET):
            return sensor_from_meta({"model": noise, **params})
        preset = params.pop("preset", None) or DEFAULT_SENSOR_PRESET
        if preset not in SENSOR_PRESETS:
            raise UnknownNameError("sensor preset", preset, list(SENSOR_PRESETS))
        params = {k: v for k, v in params.items() if k not in ("raw_dtype",)}
        return sensor_from_meta({"model": noise, **SENSOR_PRESETS[preset], "preset": preset, **params})
    except UnknownNameError as exc:
        raise InputError(f"{where}.preset", repr(exc.name), f"one of {', '.join(exc.known)}") from None
    except InputError as exc:
        raise InputError(f"{where}.{exc.argument}", exc.received, exc.valid, exc.fix) from None
    except TypeError as exc:  # a key the model has no field for
        known = _sensor_fields(noise)
        raise InputError(where, f"keys {sorted(params)} ({exc})"[:160], f"the fields of noise {noise!r}: {known}",
                         "Remove the keys that this noise model does not take.") from None


def _sensor_fields(noise: str) -> str:
    kind = {"none": NoNoiseSensor, "gaussian": GaussianSensor, "poisson-gaussian": PoissonGaussianSensor}[noise]
    return ", ".join(f.name for f in fields(kind) if f.name != "model")


def _sensor_block(sensor: Sensor) -> dict:
    """The set-up block's ``sensor``: :meth:`Sensor.to_meta` with the model spelled ``noise``, first."""
    meta = sensor.to_meta()
    return {"noise": meta.pop("model"), **meta}


def _rig(value, where: str) -> RigModel | None:
    """A rig from a :class:`RigModel`, ``None``, ``RigModel.to_dict()``'s mapping or a preset draw."""
    if value is None or isinstance(value, RigModel):
        return value
    if not isinstance(value, dict):
        raise InputError(where, f"{type(value).__name__} {value!r}"[:80], "a mapping (preset, seed, overrides) or null")
    if not value:
        return None
    if any(k in value for k in _RIG_DICT_KEYS):
        return RigModel.from_dict(value, where=where)
    try:
        return RigModel.from_spec(value)
    except InputError as exc:  # RigModel names "rig", "rig gain", ...: name the key under ``where``
        key = exc.argument.removeprefix("rig").strip()
        raise InputError(f"{where}.{key}" if key else where, exc.received, exc.valid, exc.fix) from None


def _extinction_ratio(value, where: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value) or not value >= 1:
        raise InputError(where, repr(value), "a number >= 1 (T_max / T_min), or null for ideal polarizers",
                         "For example extinction_ratio: 100.")
    return None if math.isinf(value) else float(value)


@dataclass(frozen=True, eq=False)
class CameraSetup:
    """The camera set-up of a capture (module docstring); two set-ups are equal when their :meth:`to_meta` blocks are.

    Parameters
    ----------
    sensor : Sensor
        Sensor and noise (:func:`~capssim.camera.sensor.make_sensor`); default no noise.
    psf : PSF or dict, optional
        A :class:`~capssim.camera.psf.PSF`, a ``meta.json`` PSF mapping or None for :data:`~capssim.camera.psf.DEFAULT_PSF`.
    dofp_layout : str
        The DoFP camera's mosaic layout, kept as its canonical name.
    extinction_ratio : float, optional
        Polarizer ``T_max / T_min``; None or inf: ideal.
    rig : RigModel, optional
        The array's imperfections; None: the ideal array.
    """

    sensor: Sensor = field(default_factory=NoNoiseSensor)
    psf: PSF = DEFAULT_PSF
    dofp_layout: str = DEFAULT_DOFP_LAYOUT
    extinction_ratio: float | None = None
    rig: RigModel | None = None

    def __post_init__(self):
        set_ = object.__setattr__
        if not isinstance(self.sensor, Sensor):
            raise InputError("setup sensor", type(self.sensor).__name__, "a capssim.camera.sensor.Sensor",
                             "Build one with capssim.camera.sensor.make_sensor, or use CameraSetup.from_mapping.")
        try:
            set_(self, "psf", as_psf(self.psf))
        except (InputError, TypeError, ValueError) as exc:
            raise InputError("setup psf", repr(self.psf)[:80], f"a capssim.camera.psf.PSF or a PSF mapping ({exc})") from None
        set_(self, "dofp_layout", _checked(dofp_layout_name, self.dofp_layout, "setup dofp_layout"))
        set_(self, "extinction_ratio", _extinction_ratio(self.extinction_ratio, "setup extinction_ratio"))
        set_(self, "rig", _rig(self.rig, "setup rig"))

    # constructors --------------------------------------------------------------------------------
    @classmethod
    def from_mapping(cls, mapping, *, where: str = "setup") -> "CameraSetup":
        """The set-up a mapping describes: a dataset's or suite's YAML, or a ``meta.json`` "setup" block.

        Parameters
        ----------
        mapping : dict or None
            The keys of :data:`SETUP_KEYS`, each optional (None: the default set-up); ``sensor`` may be a
            :class:`~capssim.camera.sensor.Sensor`.
        where : str
            The mapping's name in error messages.

        Returns
        -------
        CameraSetup

        Raises
        ------
        InputError
            One line naming ``where.key``, the value and what is valid.
        """
        if mapping is None:
            return cls()
        if not isinstance(mapping, dict):
            raise InputError(where, f"{type(mapping).__name__} {mapping!r}"[:80], f"a mapping of {', '.join(SETUP_KEYS)}")
        unknown = sorted(set(mapping) - set(SETUP_KEYS))
        if unknown:
            raise InputError(f"{where}.{unknown[0]}", "an unknown key", f"one of {', '.join(SETUP_KEYS)}",
                             "Check the spelling (docs: guides/simulation.md, 'The camera set-up').")
        if mapping.get("seed_rule", SEED_RULE) != SEED_RULE:
            raise InputError(f"{where}.seed_rule", repr(mapping["seed_rule"]), repr(SEED_RULE),
                             "The seed rule is capssim's; remove the key or copy it unchanged.")
        sensor = mapping.get("sensor")
        if not isinstance(sensor, Sensor):
            sensor = sensor_from_mapping(sensor or {}, where=f"{where}.sensor")
        return cls(sensor=sensor,
                   psf=_psf_from_mapping(mapping, where),
                   dofp_layout=_checked(dofp_layout_name, mapping.get("dofp_layout", DEFAULT_DOFP_LAYOUT),
                                        f"{where}.dofp_layout"),
                   extinction_ratio=_extinction_ratio(mapping.get("extinction_ratio"), f"{where}.extinction_ratio"),
                   rig=_rig(mapping.get("rig"), f"{where}.rig"))

    @classmethod
    def from_meta(cls, meta: dict) -> "CameraSetup":
        """The set-up of a capture's ``meta.json``.

        The top-level keys the readers use (``sensor``, ``psf`` or a render's ``render.optics_psf``,
        ``dofp_layout``, ``extinction_ratio``, ``rig``) are the source; the "setup" block repeats them.
        A key the block leaves out is derived from the top level (a file written before the block
        existed has none); :func:`setup_contradiction` finds a block key that says otherwise
        (:func:`capssim.captures.capture_meta.validate_meta` refuses it)."""
        block = meta.get("setup")
        if block is None:
            return cls.from_mapping(top_level_setup_mapping(meta), where="meta.json")
        if not isinstance(block, dict):
            return cls.from_mapping(block, where="meta.json setup")
        return cls.from_mapping(_filled_block(meta), where="meta.json setup")

    # views ----------------------------------------------------------------------------------------
    @property
    def noise(self) -> str:
        """The noise model's name: ``none``, ``gaussian`` or ``poisson-gaussian``."""
        return self.sensor.model

    def to_meta(self) -> dict:
        """The ``meta.json`` "setup" block (JSON-ready; :meth:`from_mapping` reads it back)."""
        rig = None if self.rig is None or self.rig.is_ideal else self.rig.to_dict()
        return {"sensor": _sensor_block(self.sensor), "psf": self.psf.to_spec(), "dofp_layout": self.dofp_layout,
                "extinction_ratio": self.extinction_ratio, "rig": rig, "seed_rule": SEED_RULE}

    def replace(self, **changes) -> "CameraSetup":
        """A copy with the given fields replaced (checked as in the constructor)."""
        return replace(self, **changes)

    def __eq__(self, other) -> bool:
        return isinstance(other, CameraSetup) and self.to_meta() == other.to_meta()

    __hash__ = None  # a sensor and a rig are mutable-looking values: compare set-ups, do not hash them


def top_level_setup_mapping(meta: dict) -> dict:
    """The set-up mapping the top-level keys of a ``meta.json`` give (the readers' source of truth;
    ``sensor`` is the :class:`~capssim.camera.sensor.Sensor` :func:`~capssim.camera.sensor.sensor_from_meta` reads)."""
    sensor = meta.get("sensor")
    optics = (meta.get("render") or {}).get("optics_psf") if meta.get("kind") == "rendered" else None
    return {  # the sensor as the readers read it (Capture.sensor): no preset filled in
        "sensor": sensor_from_meta(sensor) if isinstance(sensor, dict) and "model" in sensor else sensor,
        "psf": optics if optics is not None else (meta.get("psf") or {"type": "none"}),
        "dofp_layout": meta.get("dofp_layout", DEFAULT_DOFP_LAYOUT),
        "extinction_ratio": meta.get("extinction_ratio"),
        "rig": meta.get("rig"),
    }


def _filled_block(meta: dict) -> dict:
    """The "setup" block with the keys it leaves out taken from the top level."""
    block, top = dict(meta["setup"]), top_level_setup_mapping(meta)
    for key, value in top.items():
        if key not in block and not (key == "psf" and "psf_sigma_hr_px" in block):
            block[key] = value
    if isinstance(block.get("sensor"), dict):
        block["sensor"] = {k: v for k, v in block["sensor"].items() if k != "raw_dtype"}
    return block


#: the set-up block's keys that repeat a top-level key
_REPEATED_KEYS = ("sensor", "psf", "dofp_layout", "extinction_ratio", "rig")


def _first_difference(a, b, path: str):
    """The first leaf where two JSON values differ, as ``(path, a_leaf, b_leaf)``, or None."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in list(a) + [k for k in b if k not in a]:
            found = _first_difference(a.get(key), b.get(key), f"{path}.{key}")
            if found:
                return found
        return None
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool) \
            and not isinstance(b, bool):
        return None if float(a) == float(b) else (path, a, b)
    return None if a == b else (path, a, b)


def setup_contradiction(meta: dict) -> tuple[str, object, object] | None:
    """Where a ``meta.json``'s "setup" block contradicts its top-level keys: ``(key, setup value,
    top-level value)`` for the first such key (e.g. ``("setup.psf.sigma_hr_px", 3.0, 0.5)``), or None.

    Both sides are read as :class:`CameraSetup` and compared in the block's spelling, so a value written
    two ways (``5`` and ``5.0``, a rig as a preset draw and as its parameters) agrees. A rendered
    capture's top-level ``psf`` is ``none`` (its blur is in ``gt.tiff``): its block's ``psf`` is
    compared with ``render.optics_psf``."""
    if not isinstance(meta.get("setup"), dict):
        return None
    block = CameraSetup.from_meta(meta).to_meta()
    top = CameraSetup.from_mapping(top_level_setup_mapping(meta), where="meta.json").to_meta()
    for key in _REPEATED_KEYS:
        found = _first_difference(block[key], top[key], f"setup.{key}")
        if found:
            return found
    return None


def _checked(function, value, where: str):
    try:
        return function(value)
    except InputError as exc:
        raise InputError(where, exc.received, exc.valid, exc.fix) from None


def _psf_from_mapping(mapping: dict, where: str) -> PSF:
    """``psf_sigma_hr_px`` (a Gaussian) or ``psf`` (any PSF mapping), not both; neither: the default."""
    if mapping.get("psf") is not None and mapping.get("psf_sigma_hr_px") is not None:
        raise InputError(f"{where}.psf_sigma_hr_px", mapping["psf_sigma_hr_px"], f"no psf_sigma_hr_px beside "
                         f"{where}.psf", "Give one of psf_sigma_hr_px (a Gaussian) and psf (any PSF).")
    if mapping.get("psf") is not None:
        try:
            return PSF.from_spec(mapping["psf"]) if isinstance(mapping["psf"], dict) else as_psf(mapping["psf"])
        except InputError as exc:
            raise InputError(f"{where}.{exc.argument}", exc.received, exc.valid, exc.fix) from None
        except (TypeError, ValueError) as exc:
            raise InputError(f"{where}.psf", repr(mapping["psf"])[:80], f"a PSF mapping such as {{type: gaussian, "
                             f"sigma_hr_px: {DEFAULT_SIGMA_HR_PX}}} ({exc})") from None
    sigma = mapping.get("psf_sigma_hr_px", DEFAULT_SIGMA_HR_PX)
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not (math.isfinite(sigma) and sigma >= 0):
        raise InputError(f"{where}.psf_sigma_hr_px", repr(sigma), "a finite number >= 0 (HR pixels; 0 = no blur)",
                         f"For example psf_sigma_hr_px: {DEFAULT_SIGMA_HR_PX}.")
    return PSF.gaussian(float(sigma))


def as_setup(setup: "CameraSetup | Sensor | None" = None, *, psf=None, dofp_layout=None, extinction_ratio=None,
             rig: RigModel | None = None) -> CameraSetup:
    """``setup`` as a :class:`CameraSetup`: a set-up, a bare :class:`~capssim.camera.sensor.Sensor` (the rest
    default) or ``None`` (the default set-up); the options that are not ``None`` replace its fields
    (the keyword arguments of :func:`capssim.simulate.simulate_capture` before the set-up value)."""
    if setup is None or isinstance(setup, Sensor):
        base = CameraSetup() if setup is None else CameraSetup(sensor=setup)
    elif isinstance(setup, CameraSetup):
        base = setup
    else:
        raise InputError("setup", type(setup).__name__, "a capssim.camera.camera_setup.CameraSetup, a capssim.camera.sensor.Sensor "
                         "or None", "Build one with CameraSetup.from_mapping({...}).")
    changes = {k: v for k, v in (("psf", psf), ("dofp_layout", dofp_layout), ("extinction_ratio", extinction_ratio),
                                 ("rig", rig)) if v is not None}
    return base.replace(**changes) if changes else base


def sensor_from_options(noise: str = DEFAULT_NOISE, *, sigma: float | None = None,
                        preset: str | None = None) -> Sensor:
    """The sensor of command-line style options: ``poisson-gaussian`` without ``preset`` takes
    :data:`DEFAULT_SENSOR_PRESET`."""
    if str(noise).lower() == "poisson-gaussian" and preset is None:
        preset = DEFAULT_SENSOR_PRESET
    return make_sensor(noise, sigma=sigma, preset=preset)
