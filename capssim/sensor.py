"""Sensor models: noise, clipping and quantization, applied *after* the linear camera model.

Input is irradiance normalised so that 1.0 is full scale. Three models:

* ``none``: no noise; float32 output equal to the input.
* ``gaussian``: the paper's protocol (section 5.2), white Gaussian noise of std ``sigma``
  on [0, 1] data, clipped to [0, 1] and quantized to ``bit_depth`` bits (uint16 DN).
* ``poisson-gaussian``: EMVA 1288 linear model. Electrons ``e = Poisson(x * exposure *
  full_well) + N(0, read_noise^2)``, clipped to ``[0, full_well]``;
  ``DN = round(gain * e + black_level)`` clipped to ``[0, 2^bit_depth - 1]``. Its
  photon-transfer curve is ``var(DN) = gain * (mean(DN) - black) + gain^2 read^2 + 1/12``.

Reconstruction sees the sensor only through :meth:`Sensor.to_float` and
:meth:`Sensor.saturation_mask` (saturated pixels get weight 0).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

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


def _finite(arg: str, value, *, minimum: float = 0.0, strict: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(arg, repr(value), "a number") from None
    ok = math.isfinite(v) and (v > minimum if strict else v >= minimum)
    if not ok:
        raise InputError(arg, value, f"a finite number {'>' if strict else '>='} {minimum}")
    return v


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

    def to_float(self, raw: np.ndarray) -> np.ndarray:
        """Raw values -> float32 irradiance estimate on [0, 1] full scale."""
        raw = np.asarray(raw)
        return ((raw.astype(np.float64) - self.black_level) / (self.white_level - self.black_level)).astype(np.float32)

    def saturation_mask(self, raw: np.ndarray) -> np.ndarray:
        """True where a pixel is clipped at the white level (reconstruction weight 0)."""
        raw = np.asarray(raw)
        if np.issubdtype(raw.dtype, np.floating):
            return np.zeros(raw.shape, dtype=bool)
        return raw >= self.white_level

    def to_meta(self) -> dict:
        meta = asdict(self)
        meta.update(black_level=self.black_level, white_level=self.white_level,
                    raw_dtype="float32" if self.model == "none" else "uint16")
        return meta


@dataclass
class NoNoiseSensor(Sensor):
    model: str = "none"


@dataclass
class GaussianSensor(Sensor):
    """White Gaussian noise of std ``sigma`` on [0, 1] data, clip, quantize to ``bit_depth``."""

    model: str = "gaussian"
    sigma: float = 0.01
    bit_depth: int = 16

    def __post_init__(self):
        self.sigma = _finite("sigma", self.sigma)
        if int(self.bit_depth) not in range(8, 17):
            raise InputError("bit_depth", self.bit_depth, "an integer in 8..16")
        self.bit_depth = int(self.bit_depth)

    @property
    def white_level(self) -> float:
        return float(2**self.bit_depth - 1)

    def capture(self, irradiance, rng):
        x = _check_irradiance(irradiance)
        noisy = x + rng.normal(0.0, self.sigma, size=x.shape) if self.sigma > 0 else x
        return np.round(np.clip(noisy, 0.0, 1.0) * self.white_level).astype(np.uint16)


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

    def __post_init__(self):
        self.full_well_e = _finite("full_well_e", self.full_well_e, strict=True)
        self.read_noise_e = _finite("read_noise_e", self.read_noise_e)
        self.gain_dn_per_e = _finite("gain_dn_per_e", self.gain_dn_per_e, strict=True)
        self.exposure = _finite("exposure", self.exposure, strict=True)
        if int(self.bit_depth) not in range(8, 17):
            raise InputError("bit_depth", self.bit_depth, "an integer in 8..16")
        self.bit_depth = int(self.bit_depth)
        self.black_level_dn = int(self.black_level_dn)
        if not 0 <= self.black_level_dn < 2**self.bit_depth - 1:
            raise InputError("black_level_dn", self.black_level_dn, f"an integer in [0, {2**self.bit_depth - 1})")
        if self.white_level <= self.black_level_dn:
            raise InputError("gain_dn_per_e", self.gain_dn_per_e, "a gain that maps the full well above the black level")

    @property
    def black_level(self) -> float:
        return float(self.black_level_dn)

    @property
    def white_level(self) -> float:
        """DN of a full-well pixel, or the ADC maximum if that is lower."""
        return float(min(2**self.bit_depth - 1, round(self.gain_dn_per_e * self.full_well_e + self.black_level_dn)))

    def capture(self, irradiance, rng):
        x = _check_irradiance(irradiance)
        mean_e = np.clip(x, 0.0, None) * self.exposure * self.full_well_e
        electrons = rng.poisson(mean_e).astype(np.float64)
        if self.read_noise_e > 0:
            electrons = electrons + rng.normal(0.0, self.read_noise_e, size=x.shape)
        electrons = np.clip(electrons, 0.0, self.full_well_e)
        dn = np.round(self.gain_dn_per_e * electrons + self.black_level_dn)
        return np.clip(dn, 0, 2**self.bit_depth - 1).astype(np.uint16)

    def to_float(self, raw):
        """DN -> irradiance on [0, 1] of ``exposure * full_well`` (inverts the mean response)."""
        raw = np.asarray(raw).astype(np.float64)
        return ((raw - self.black_level) / (self.gain_dn_per_e * self.full_well_e * self.exposure)).astype(np.float32)

    def noise_std(self, x: np.ndarray) -> np.ndarray:
        """Noise std on the [0, 1] scale at irradiance ``x`` (shot + read + quantization)."""
        e = np.clip(x, 0, None) * self.exposure * self.full_well_e
        var_dn = self.gain_dn_per_e**2 * (e + self.read_noise_e**2) + 1.0 / 12
        return np.sqrt(var_dn) / (self.gain_dn_per_e * self.full_well_e * self.exposure)


def make_sensor(noise: str = "none", *, sigma: float | None = None, preset: str | None = None,
                **overrides) -> Sensor:
    """Build a sensor from CLI-style options.

    ``noise`` is one of ``none``, ``gaussian`` (needs ``sigma``), ``poisson-gaussian``
    (``preset`` names a :data:`SENSOR_PRESETS` entry; keyword overrides replace fields).
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


def sensor_from_meta(meta: dict) -> Sensor:
    """Inverse of :meth:`Sensor.to_meta` (``meta.json``'s ``sensor`` entry)."""
    if not isinstance(meta, dict) or "model" not in meta:
        raise InputError("sensor", repr(meta)[:80], "a dict with a 'model' key")
    params = {k: v for k, v in meta.items() if k not in ("model", "black_level", "white_level", "raw_dtype")}
    model = meta["model"]
    if model == "none":
        return NoNoiseSensor()
    if model == "gaussian":
        return GaussianSensor(**params)
    if model == "poisson-gaussian":
        return PoissonGaussianSensor(**params)
    raise UnknownNameError("noise model", model, list(NOISE_MODELS))


def noise_sigma_estimate(sensor: Sensor, level: float = 0.5) -> float:
    """Noise std on the [0, 1] scale at irradiance ``level`` (0 for ``none``)."""
    if isinstance(sensor, GaussianSensor):
        return float(math.hypot(sensor.sigma, 1.0 / (sensor.white_level * math.sqrt(12))))
    if isinstance(sensor, PoissonGaussianSensor):
        return float(sensor.noise_std(np.asarray(level)))
    return 0.0
