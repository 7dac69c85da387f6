"""Sensor models: noise, clipping and quantization, applied *after* the linear camera model.

Input is irradiance normalised so that 1.0 is full scale. Three models:

* ``none``: no noise; float32 output equal to the input (raw levels 0 and 1 unless stated).
* ``gaussian``: the paper's protocol (section 5.2), white Gaussian noise of std ``sigma``
  on [0, 1] data, clipped to [0, 1] and written as uint16 DN
  ``round(black + x (white - black))``; the levels default to 0 and ``2^bit_depth - 1``.
* ``poisson-gaussian``: EMVA 1288 linear model. Electrons ``e = Poisson(x * exposure *
  full_well) + N(0, read_noise^2)``, clipped to ``[0, full_well]``;
  ``DN = round(gain * e + black_level)`` clipped to ``[0, 2^bit_depth - 1]``. Its
  photon-transfer curve is ``var(DN) = gain * (mean(DN) - black) + gain^2 read^2 + 1/12``.

Reconstruction sees the sensor only through :meth:`Sensor.to_float` and
:meth:`Sensor.saturation_mask` (saturated pixels get weight 0). Every model honours the
``black_level`` and ``white_level`` of ``meta.json``'s ``sensor`` entry, its ``bit_depth`` (DN
above ``2^bit_depth - 1`` are refused) and, for ``poisson-gaussian``, its gain, in writing
(:meth:`Sensor.capture`, :meth:`Sensor.to_meta`) and in reading (:func:`sensor_from_meta`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import ClassVar

import numpy as np

from capssim.errors import InputError, UnknownNameError

#: EMVA 1288 style presets. Values are typical data-sheet figures (docs: guides/simulation.md, "Sensor models");
#: the PYTHON1300 full well and read noise are unconfirmed, keep them as parameters.
SENSOR_PRESETS: dict[str, dict] = {
    "python1300": {
        "description": "ON Semi PYTHON1300 (paper prototype, Hikvision MV-CA013-20GC): 4.8 um, 10 bit",
        "pixel_um": 4.8, "full_well_e": 10000.0, "read_noise_e": 9.0, "gain_dn_per_e": 0.1,
        "black_level_dn": 16, "bit_depth": 10,
    },
    "imx250myr": {
        "description": "Sony IMX250MYR-class polarization sensor: 3.45 um, 12 bit",
        "pixel_um": 3.45, "full_well_e": 10500.0, "read_noise_e": 2.5, "gain_dn_per_e": 0.37,
        "black_level_dn": 240, "bit_depth": 12,
    },
}

NOISE_MODELS = ("none", "gaussian", "poisson-gaussian")
#: the noise model of a sensor that names none (the camera set-up's default)
DEFAULT_NOISE = "none"
#: the EMVA 1288 preset of a ``poisson-gaussian`` sensor that names none
DEFAULT_SENSOR_PRESET = "imx250myr"


def _finite(arg: str, value, *, minimum: float = 0.0, strict: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(arg, repr(value), "a number") from None
    ok = math.isfinite(v) and (v > minimum if strict else v >= minimum)
    if not ok:
        raise InputError(arg, value, f"a finite number {'>' if strict else '>='} {minimum}")
    return v


def _bit_depth(value) -> int:
    try:
        bits = float(value)
    except (TypeError, ValueError):
        bits = math.nan
    if not (bits.is_integer() and 8 <= bits <= 16):
        raise InputError("bit_depth", value, "an integer in 8..16")
    return int(bits)


def _check_levels(black: float, white: float, top: float, *, unit: str) -> None:
    """:class:`InputError` unless ``0 <= black < white <= top`` (raw levels, ``unit``)."""
    if not 0 <= black < top:
        raise InputError("black_level", black, f"a {unit} level in [0, {top:g})")
    if not black < white <= top:
        raise InputError("white_level", white, f"a {unit} level in ({black:g}, {top:g}]",
                         "Set white_level to the raw value of a saturated pixel, at most the ADC maximum.")


def _check_dn_range(raw: np.ndarray, bit_depth: int) -> None:
    """:class:`InputError` if integer DN exceed ``2^bit_depth - 1`` (e.g. left-aligned 12-bit data)."""
    if np.issubdtype(raw.dtype, np.integer) and raw.size and int(raw.max()) > 2**bit_depth - 1:
        raise InputError("raw values", f"maximum {int(raw.max())} DN", f"DN <= {2**bit_depth - 1} for bit_depth "
                         f"{bit_depth}", "Give the sensor's true bit_depth in meta.json, or shift left-aligned "
                         "data down to the ADC range.")


def _check_irradiance(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        raise InputError("irradiance", f"dtype {x.dtype}", "a float array normalised to [0, 1] full scale")
    if not np.all(np.isfinite(x)):
        raise InputError("irradiance", f"{int(np.sum(~np.isfinite(x)))} non-finite values", "finite values")
    return x.astype(np.float64, copy=False)


@dataclass
class Sensor:
    """Base sensor; subclasses implement :meth:`capture`."""

    model: str = "none"

    @property
    def black_level(self) -> float:
        return 0.0

    @property
    def white_level(self) -> float:
        return 1.0

    def capture(self, irradiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return _check_irradiance(irradiance).astype(np.float32)

    #: the dataclass fields holding the raw levels (written to meta.json as black_level / white_level)
    LEVEL_FIELDS: ClassVar[tuple[str, ...]] = ()

    def check_raw(self, raw: np.ndarray) -> None:
        """:class:`InputError` if ``raw`` cannot come from this sensor (DN above its ADC range)."""

    def to_float(self, raw: np.ndarray) -> np.ndarray:
        """Raw values -> float32 irradiance estimate on [0, 1] full scale:
        ``(raw - black_level) / (white_level - black_level)``."""
        raw = np.asarray(raw)
        self.check_raw(raw)
        return ((raw.astype(np.float64) - self.black_level) / (self.white_level - self.black_level)).astype(np.float32)

    def saturation_mask(self, raw: np.ndarray) -> np.ndarray:
        """True where a pixel is clipped at the white level (reconstruction weight 0)."""
        raw = np.asarray(raw)
        if np.issubdtype(raw.dtype, np.floating):
            return np.zeros(raw.shape, dtype=bool)
        return raw >= self.white_level

    def to_meta(self) -> dict:
        meta = {k: v for k, v in asdict(self).items() if k not in self.LEVEL_FIELDS}
        meta.update(black_level=self.black_level, white_level=self.white_level,
                    raw_dtype="float32" if self.model == "none" else "uint16")
        return meta


@dataclass
class NoNoiseSensor(Sensor):
    """No noise: float32 raw values; ``black_level_raw`` and ``white_level_raw`` are the raw
    values of black and of full scale (0 and 1 for what simulate and render write)."""

    model: str = "none"
    black_level_raw: float = 0.0
    white_level_raw: float = 1.0
    LEVEL_FIELDS: ClassVar[tuple[str, ...]] = ("black_level_raw", "white_level_raw")

    def __post_init__(self):
        self.black_level_raw = _finite("black_level", self.black_level_raw, minimum=-math.inf)
        self.white_level_raw = _finite("white_level", self.white_level_raw, minimum=-math.inf)
        if not self.white_level_raw > self.black_level_raw:
            raise InputError("white_level", self.white_level_raw, f"a raw value above black_level "
                             f"{self.black_level_raw:g}")

    def capture(self, irradiance, rng):
        x = _check_irradiance(irradiance)
        if (self.black_level_raw, self.white_level_raw) != (0.0, 1.0):
            x = self.black_level_raw + x * (self.white_level_raw - self.black_level_raw)
        return x.astype(np.float32)

    @property
    def black_level(self) -> float:
        return self.black_level_raw

    @property
    def white_level(self) -> float:
        return self.white_level_raw


@dataclass
class GaussianSensor(Sensor):
    """White Gaussian noise of std ``sigma`` on [0, 1] data, clip, quantize to ``bit_depth``.

    ``black_level_dn`` and ``white_level_dn`` (DN of black and of full scale; ``None``: the ADC
    maximum ``2^bit_depth - 1``) map [0, 1] to DN: ``DN = round(black + x (white - black))``.
    """

    model: str = "gaussian"
    sigma: float = 0.01
    bit_depth: int = 16
    black_level_dn: float = 0.0
    white_level_dn: float | None = None
    LEVEL_FIELDS: ClassVar[tuple[str, ...]] = ("black_level_dn", "white_level_dn")

    def __post_init__(self):
        self.sigma = _finite("sigma", self.sigma)
        self.bit_depth = _bit_depth(self.bit_depth)
        top = float(2**self.bit_depth - 1)
        self.black_level_dn = _finite("black_level", self.black_level_dn)
        if self.white_level_dn is not None:
            self.white_level_dn = _finite("white_level", self.white_level_dn)
            if self.white_level_dn == top:
                self.white_level_dn = None  # the default, spelled out
        _check_levels(self.black_level_dn, self.white_level, top, unit="DN")

    @property
    def black_level(self) -> float:
        return self.black_level_dn

    @property
    def white_level(self) -> float:
        return float(2**self.bit_depth - 1) if self.white_level_dn is None else self.white_level_dn

    def check_raw(self, raw):
        _check_dn_range(raw, self.bit_depth)

    def capture(self, irradiance, rng):
        x = _check_irradiance(irradiance)
        noisy = x + rng.normal(0.0, self.sigma, size=x.shape) if self.sigma > 0 else x
        span = self.white_level - self.black_level
        return np.round(self.black_level + np.clip(noisy, 0.0, 1.0) * span).astype(np.uint16)


@dataclass
class PoissonGaussianSensor(Sensor):
    """EMVA 1288 linear sensor (shot noise, read noise, gain, black level, ADC)."""

    model: str = "poisson-gaussian"
    full_well_e: float = 10500.0
    read_noise_e: float = 2.5
    gain_dn_per_e: float = 0.37
    black_level_dn: int = 240
    bit_depth: int = 12
    exposure: float = 1.0
    preset: str | None = None
    pixel_um: float | None = None
    description: str | None = field(default=None, repr=False)
    #: saturation DN when it is below the full-well DN (``None``: :meth:`full_well_dn`)
    white_level_dn: float | None = None
    LEVEL_FIELDS: ClassVar[tuple[str, ...]] = ("white_level_dn",)

    def __post_init__(self):
        self.full_well_e = _finite("full_well_e", self.full_well_e, strict=True)
        self.read_noise_e = _finite("read_noise_e", self.read_noise_e)
        self.gain_dn_per_e = _finite("gain_dn_per_e", self.gain_dn_per_e, strict=True)
        self.exposure = _finite("exposure", self.exposure, strict=True)
        self.bit_depth = _bit_depth(self.bit_depth)
        black = _finite("black_level_dn", self.black_level_dn)
        if not black.is_integer() or not black < 2**self.bit_depth - 1:
            raise InputError("black_level_dn", self.black_level_dn, f"an integer in [0, {2**self.bit_depth - 1})")
        self.black_level_dn = int(black)
        if self.full_well_dn() <= self.black_level_dn:
            raise InputError("gain_dn_per_e", self.gain_dn_per_e, "a gain that maps the full well above the black level")
        if self.white_level_dn is not None:
            self.white_level_dn = _finite("white_level", self.white_level_dn)
            if self.white_level_dn == self.full_well_dn():
                self.white_level_dn = None  # the default, spelled out
        _check_levels(self.black_level, self.white_level, self.full_well_dn(), unit="DN")

    @property
    def black_level(self) -> float:
        return float(self.black_level_dn)

    def full_well_dn(self) -> float:
        """DN of a full-well pixel, or the ADC maximum if that is lower."""
        return float(min(2**self.bit_depth - 1, round(self.gain_dn_per_e * self.full_well_e + self.black_level_dn)))

    @property
    def white_level(self) -> float:
        """The saturation DN: ``white_level_dn``, else :meth:`full_well_dn`."""
        return self.full_well_dn() if self.white_level_dn is None else self.white_level_dn

    def check_raw(self, raw):
        _check_dn_range(raw, self.bit_depth)

    def capture(self, irradiance, rng):
        x = _check_irradiance(irradiance)
        mean_e = np.clip(x, 0.0, None) * self.exposure * self.full_well_e
        electrons = rng.poisson(mean_e).astype(np.float64)
        if self.read_noise_e > 0:
            electrons = electrons + rng.normal(0.0, self.read_noise_e, size=x.shape)
        electrons = np.clip(electrons, 0.0, self.full_well_e)
        dn = np.round(self.gain_dn_per_e * electrons + self.black_level_dn)
        return np.clip(dn, 0, self.white_level).astype(np.uint16)

    def to_float(self, raw):
        """DN -> irradiance on [0, 1] of ``exposure * full_well`` (inverts the mean response)."""
        raw = np.asarray(raw)
        self.check_raw(raw)
        raw = raw.astype(np.float64)
        return ((raw - self.black_level) / (self.gain_dn_per_e * self.full_well_e * self.exposure)).astype(np.float32)

    def noise_std(self, x: np.ndarray) -> np.ndarray:
        """Noise std on the [0, 1] scale at irradiance ``x`` (shot + read + quantization)."""
        e = np.clip(x, 0, None) * self.exposure * self.full_well_e
        var_dn = self.gain_dn_per_e**2 * (e + self.read_noise_e**2) + 1.0 / 12
        return np.sqrt(var_dn) / (self.gain_dn_per_e * self.full_well_e * self.exposure)


def make_sensor(noise: str = DEFAULT_NOISE, *, sigma: float | None = None, preset: str | None = None,
                **overrides) -> Sensor:
    """Build a sensor from CLI-style options.

    Parameters
    ----------
    noise : str
        ``none``, ``gaussian`` or ``poisson-gaussian``.
    sigma : float, optional
        Noise standard deviation on the [0, 1] scale; required for ``gaussian``.
    preset : str, optional
        A :data:`SENSOR_PRESETS` name (``poisson-gaussian``), e.g. ``python1300``.
    **overrides
        Sensor fields that replace the preset's (e.g. ``full_well_e``, ``read_noise_e``).

    Returns
    -------
    Sensor

    Raises
    ------
    UnknownNameError
        An unknown noise model or preset (the message lists the valid names).
    InputError
        Options that do not fit the noise model (``sigma`` missing for ``gaussian``, given for ``none``).
    """
    key = str(noise).lower()
    if key not in NOISE_MODELS:
        raise UnknownNameError("noise model", noise, list(NOISE_MODELS))
    if key == "none":
        if sigma not in (None, 0, 0.0) or preset:
            raise InputError("noise", "none with --sigma/--sensor", "no noise options for noise 'none'",
                             "Use --noise gaussian or --noise poisson-gaussian.")
        return NoNoiseSensor()
    if key == "gaussian":
        if sigma is None:
            raise InputError("sigma", None, "the noise std on [0, 1] data for noise 'gaussian'", "Add e.g. --sigma 0.01.")
        return GaussianSensor(sigma=sigma, **overrides)
    params: dict = {}
    if preset is not None:
        if preset not in SENSOR_PRESETS:
            raise UnknownNameError("sensor preset", preset, list(SENSOR_PRESETS))
        params.update(SENSOR_PRESETS[preset], preset=preset)
    params.update(overrides)
    return PoissonGaussianSensor(**params)


_SENSOR_CLASSES: dict[str, type[Sensor]] = {"none": NoNoiseSensor, "gaussian": GaussianSensor,
                                             "poisson-gaussian": PoissonGaussianSensor}


def sensor_from_meta(meta: dict) -> Sensor:
    """Inverse of :meth:`Sensor.to_meta` (``meta.json``'s ``sensor`` entry).

    ``black_level`` and ``white_level`` (raw values of black and of saturation, as a user with a
    real camera writes them) set the model's levels; for ``poisson-gaussian`` a ``black_level``
    must agree with ``black_level_dn`` when both are given.
    """
    if not isinstance(meta, dict) or "model" not in meta:
        raise InputError("sensor", repr(meta)[:80], "a dict with a 'model' key")
    model = meta["model"]
    if model not in _SENSOR_CLASSES:
        raise UnknownNameError("noise model", model, list(NOISE_MODELS))
    params = {k: v for k, v in meta.items() if k not in ("model", "black_level", "white_level", "raw_dtype")}
    kind = _SENSOR_CLASSES[model]
    black_field = "black_level_dn" if kind is PoissonGaussianSensor else kind.LEVEL_FIELDS[0]
    for key, target in (("black_level", black_field), ("white_level", kind.LEVEL_FIELDS[-1])):
        if meta.get(key) is None:
            continue
        if target in params and params[target] is not None and _number(params[target]) != _number(meta[key]):
            raise InputError(f"sensor.{key}", meta[key], f"the value of sensor.{target}, {params[target]}",
                             f"Give one of {key} and {target}, or make them agree.")
        params[target] = meta[key]
    return kind(**params)


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError("sensor level", repr(value), "a number") from None


def noise_std_map(sensor: Sensor, x: np.ndarray) -> np.ndarray:
    """Noise std on the [0, 1] scale of each value of ``x`` (irradiance on [0, 1], any shape), float32:
    constant for a Gaussian sensor (its sigma with the quantization step), ``noise_std(x)`` for a
    Poisson-Gaussian one, 0 without noise."""
    x = np.asarray(x, dtype=np.float64)
    if isinstance(sensor, PoissonGaussianSensor):
        return sensor.noise_std(x).astype(np.float32)
    return np.full(x.shape, noise_sigma_estimate(sensor), dtype=np.float32)


def noise_sigma_estimate(sensor: Sensor, level: float = 0.5) -> float:
    """Noise std on the [0, 1] scale at irradiance ``level`` (0 for ``none``)."""
    if isinstance(sensor, GaussianSensor):
        dn_per_full_scale = sensor.white_level - sensor.black_level
        return float(math.hypot(sensor.sigma, 1.0 / (dn_per_full_scale * math.sqrt(12))))
    if isinstance(sensor, PoissonGaussianSensor):
        return float(sensor.noise_std(np.asarray(level)))
    return 0.0
