"""An imperfect camera array: polarizer angles, extinction, gain, vignetting and per-aperture PSF.

The ideal CAPS array (paper section 2) has perfect polarizers at exactly 0/45/90/135 degrees,
four identical cameras and one PSF. A real rig differs (issue "Real rigs"); :class:`RigModel`
holds what the camera model needs to describe it, and nothing else:

* ``angle_offsets_deg`` ``(4,)``: polarizer n analyzes at ``nominal_n + offset_n`` degrees;
* ``extinction_ratio`` ``(4, 3)``: ``T_max / T_min`` per aperture n and colour k (inf = ideal);
* ``gain`` ``(4,)``: the flat-field response at the raw frame centre (1 = nominal);
* ``vignetting`` ``(4, 15)``: a smooth map per aperture, a 2-D polynomial of degree <= 4 in
  normalised raw coordinates (:data:`VIGNETTING_MONOMIALS`), 1 at the frame centre;
* ``psf``: four PSF specs (:meth:`capssim.camera.psf.PSF.to_spec`), or ``None`` for the capture's one PSF.

The parts (:mod:`capssim.camera.rig_parts`): a polarizer at an arbitrary angle, read from the four stored
angles (exact for physically consistent images, and the stored channel itself at a nominal angle, so
an ideal rig gives today's operator bit for bit), with a finite extinction ratio; and the vignetting
polynomial.

The flat field of aperture n is ``F_n(u, v) = gain_n V_n(u, v)`` on its raw grid: the raw value
of uniform unpolarized light of 12-channel level ``L`` is ``F_n L``.

Files: :func:`write_rig_json` / :func:`read_rig_json` hold a rig with, optionally, its array
geometry (the 4 aperture homographies), uncertainties and fit residuals: the format of both
``capssim calibrate``'s output and a simulated rig's true values.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.psf import PSF
from capssim.camera.rig_checks import (
    MAX_FLAT_FIELD,
    MIN_FLAT_FIELD,
    RIG_FILE_SPEC,
    check_homographies,
    check_vignetting,
)
from capssim.camera.rig_parts import (  # noqa: F401  (re-exported: the rig's parts, capssim.camera.rig's public names)
    N_VIGNETTING_TERMS,
    VIGNETTING_MONOMIALS,
    analyzer_row,
    flat_vignetting,
    normalised_raw_coordinates,
    polarizer_reading,
    radial_vignetting,
    vignetting_design,
)
from capssim.conventions import BAYER_OFFSETS, BAYER_SITE_COLOUR, N_APERTURES, N_CHANNELS, POLARIZER_ANGLES_DEG
from capssim.errors import InputError
from capssim.files.imageio import atomic_write_text
from capssim.files.schema import load_json_file, validate

RIG_FORMAT, RIG_FORMAT_VERSION = "capssim-rig", 1


#: realistic imperfections of a hand-built array (preset ``realistic``), with where each range comes from
REALISTIC_RANGES = {
    "angle_offset_deg": (2.0, "polarizer film cut and rotation-mount setting: +-1-2 deg is typical of "
                              "hand-aligned mounts (the paper calibrated its prototype by hand)"),
    "extinction_ratio": ({"R": (100.0, 300.0), "G": (100.0, 300.0), "B": (30.0, 100.0)},
                         "wire-grid and nanoparticle polarizer films fall off in the blue: vendor curves "
                         "(e.g. Thorlabs LPVISE film, Sony IMX250MZR on-chip wire grids) give a few hundred "
                         "in red/green and tens to ~100 below 450 nm"),
    "gain": (0.05, "unit-to-unit responsivity and lens transmission spread of machine-vision cameras "
                   "(EMVA 1288 data sheets: a few per cent)"),
    "vignetting_corner": ((0.15, 0.25), "relative illumination at the sensor corner of a C-mount lens near "
                                        "f/2.8-f/4: 75-85 % (cos^4 law plus mechanical vignetting)"),
    "psf_sigma_hr_px": ((0.4, 0.6), "the default Gaussian PSF (0.5 HR px) with +-20 % lens-to-lens focus spread"),
}


#: the keyword arguments of :meth:`RigModel.with_overrides`
OVERRIDE_KEYS = ("angle_offsets_deg", "extinction_ratio", "gain", "vignetting_corner", "psf_sigmas_hr_px")


# -- the rig -----------------------------------------------------------------------------------------
def _array(value, shape: tuple, where: str, *, minimum: float | None = None, maximum: float | None = None,
           allow_inf: bool = False, fix: str | None = None) -> np.ndarray:
    try:
        arr = np.array([[math.inf if v is None else v for v in row] if isinstance(row, (list, tuple)) else
                        (math.inf if row is None else row) for row in value], dtype=np.float64) \
            if isinstance(value, (list, tuple)) else np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(where, repr(value)[:80], f"numbers of shape {shape}") from None
    if arr.shape != shape:
        raise InputError(where, f"shape {arr.shape}", f"shape {shape}")
    bad = np.isnan(arr) | (np.isinf(arr) if not allow_inf else np.isneginf(arr))
    if minimum is not None:
        bad |= arr < minimum
    if maximum is not None:
        bad |= arr > maximum
    if bad.any():
        valid = (f"finite numbers in [{minimum:g}, {maximum:g}]" if minimum is not None and maximum is not None
                 else f"finite numbers >= {minimum}" if minimum is not None else "finite numbers")
        raise InputError(where, arr[bad].tolist()[:4], valid + (" (or null/inf for ideal)" if allow_inf else ""), fix)
    return arr


@dataclass(frozen=True)
class RigModel:
    """The imperfections of one camera array (module docstring); every array is float64.

    Parameters
    ----------
    angle_offsets_deg : numpy.ndarray
        ``(4,)`` polarizer n analyzes at ``45 n + offset_n`` degrees (within +-20).
    extinction_ratio : numpy.ndarray
        ``(4, 3)`` ``T_max / T_min`` per aperture and colour, > 1 (inf: ideal).
    gain, vignetting : numpy.ndarray
        ``(4,)`` flat-field response at the frame centre; ``(4, 15)`` polynomial vignetting coefficients.
    psf : tuple, optional
        Four PSF specs (:meth:`capssim.camera.psf.PSF.to_spec`), or None for the capture's one PSF.
    """

    angle_offsets_deg: np.ndarray = field(default_factory=lambda: np.zeros(N_APERTURES))
    extinction_ratio: np.ndarray = field(default_factory=lambda: np.full((N_APERTURES, 3), math.inf))
    gain: np.ndarray = field(default_factory=lambda: np.ones(N_APERTURES))
    vignetting: np.ndarray = field(default_factory=lambda: np.tile(flat_vignetting(), (N_APERTURES, 1)))
    psf: tuple | None = None

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "angle_offsets_deg", _array(self.angle_offsets_deg, (N_APERTURES,), "rig angle_offsets_deg"))
        if np.any(np.abs(self.angle_offsets_deg) > 20.0):
            raise InputError("rig angle_offsets_deg", self.angle_offsets_deg.tolist(), "offsets within +-20 degrees",
                             "A larger error means the polarizer is at another nominal angle: re-mount it.")
        set_(self, "extinction_ratio", _array(self.extinction_ratio, (N_APERTURES, 3), "rig extinction_ratio",
                                              minimum=1.0, allow_inf=True))
        if np.any(self.extinction_ratio <= 1.0):
            raise InputError("rig extinction_ratio", self.extinction_ratio.min(), "T_max/T_min > 1 (inf: ideal)")
        set_(self, "gain", _array(self.gain, (N_APERTURES,), "rig gain", minimum=MIN_FLAT_FIELD, maximum=MAX_FLAT_FIELD,
                                  fix="The gain is each aperture's response relative to the nominal 1 (a real array's "
                                      "spread a few per cent): measure it again with 'capssim calibrate'."))
        set_(self, "vignetting", _array(self.vignetting, (N_APERTURES, N_VIGNETTING_TERMS), "rig vignetting"))
        check_vignetting(self.gain, self.vignetting)  # the flat field > 0 everywhere
        if self.psf is not None:
            if len(self.psf) != N_APERTURES:
                raise InputError("rig psf", f"{len(self.psf)} entries", f"{N_APERTURES} PSF specs or null")
            set_(self, "psf", tuple(p.to_spec() if isinstance(p, PSF) else PSF.from_spec(p).to_spec()
                                    for p in self.psf))

    # constructors -----------------------------------------------------------------------------
    @classmethod
    def ideal(cls) -> "RigModel":
        """Perfect polarizers, identical cameras, no vignetting, the capture's one PSF."""
        return cls()

    @classmethod
    def preset(cls, name: str = "realistic", *, seed: int = 0) -> "RigModel":
        """A named rig: ``ideal``, or ``realistic``, one draw from :data:`REALISTIC_RANGES`.

        Parameters
        ----------
        name : str
            ``ideal`` or ``realistic``.
        seed : int
            Seed of the ``realistic`` draw (the same seed gives the same rig).

        Returns
        -------
        RigModel
        """
        if name == "ideal":
            return cls.ideal()
        if name != "realistic":
            raise InputError("rig", repr(name), "a preset name (ideal, realistic) or a capssim-rig JSON file")
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 22]))
        er_ranges = REALISTIC_RANGES["extinction_ratio"][0]
        er = np.stack([[math.exp(rng.uniform(math.log(lo), math.log(hi))) for lo, hi in er_ranges.values()]
                       for _ in range(N_APERTURES)])
        lo, hi = REALISTIC_RANGES["vignetting_corner"][0]
        vignetting = np.stack([radial_vignetting(rng.uniform(lo, hi), centre_uv=tuple(rng.uniform(-0.1, 0.1, 2)))
                               for _ in range(N_APERTURES)])
        slo, shi = REALISTIC_RANGES["psf_sigma_hr_px"][0]
        return cls(angle_offsets_deg=rng.uniform(-1, 1, N_APERTURES) * REALISTIC_RANGES["angle_offset_deg"][0],
                   extinction_ratio=er, gain=1.0 + rng.uniform(-1, 1, N_APERTURES) * REALISTIC_RANGES["gain"][0],
                   vignetting=vignetting,
                   psf=tuple(PSF.gaussian(float(rng.uniform(slo, shi))).to_spec() for _ in range(N_APERTURES)))

    @classmethod
    def from_spec(cls, spec: dict) -> "RigModel":
        """The rig of a ``{preset, seed, <override>...}`` mapping (dataset configs, bench suites): the preset's
        draw (default ``realistic``, seed 0), then the quantities it names (:meth:`with_overrides`)."""
        rig = cls.preset(spec.get("preset", "realistic"), seed=int(spec.get("seed", 0)))
        overrides = {k: spec[k] for k in OVERRIDE_KEYS if spec.get(k) is not None}
        return rig.with_overrides(**overrides) if overrides else rig

    def with_overrides(self, *, angle_offsets_deg=None, extinction_ratio=None, gain=None,
                       vignetting_corner: float | None = None, psf_sigmas_hr_px=None) -> "RigModel":
        """A copy with the given quantities replaced.

        ``extinction_ratio``: 1, 3 (per colour) or 12 (per aperture and colour, aperture-major)
        values; ``vignetting_corner``: a centred radial fall-off for every aperture;
        ``psf_sigmas_hr_px``: 4 Gaussian stds (HR px).
        """
        changes: dict = {}
        if angle_offsets_deg is not None:
            changes["angle_offsets_deg"] = np.asarray(angle_offsets_deg, dtype=np.float64)
        if extinction_ratio is not None:
            er = np.atleast_1d(np.asarray(extinction_ratio, dtype=np.float64))
            if er.size not in (1, 3, 12):
                raise InputError("extinction_ratio", f"{er.size} values",
                                 "1 (all), 3 (per colour R,G,B) or 12 (per aperture and colour) values")
            changes["extinction_ratio"] = np.broadcast_to(er.reshape(-1, 3) if er.size != 1 else er, (4, 3)).copy() \
                if er.size != 12 else er.reshape(4, 3)
        if gain is not None:
            changes["gain"] = np.asarray(gain, dtype=np.float64)
        if vignetting_corner is not None:
            changes["vignetting"] = np.tile(radial_vignetting(float(vignetting_corner)), (N_APERTURES, 1))
        if psf_sigmas_hr_px is not None:
            sig = list(np.atleast_1d(np.asarray(psf_sigmas_hr_px, dtype=np.float64)))
            if len(sig) != N_APERTURES or not all(math.isfinite(s) and s >= 0 for s in sig):
                raise InputError("aperture PSF sigmas", sig, f"{N_APERTURES} finite numbers >= 0 (HR px)")
            changes["psf"] = tuple(PSF.gaussian(float(s)).to_spec() for s in sig)
        return replace(self, **changes)

    # what the camera model needs ------------------------------------------------------------------
    @property
    def is_ideal(self) -> bool:
        """Whether this rig is :meth:`ideal` (its operators are today's ideal ones)."""
        return (not np.any(self.angle_offsets_deg) and bool(np.all(np.isinf(self.extinction_ratio)))
                and bool(np.all(self.gain == 1.0)) and bool(np.all(self.vignetting == flat_vignetting()))
                and self.psf is None)

    @property
    def has_flat_field(self) -> bool:
        """Whether gain or vignetting differ from 1 anywhere."""
        return not (np.all(self.gain == 1.0) and np.all(self.vignetting == flat_vignetting()))

    def analyzer_matrix(self) -> np.ndarray:
        """``(12, 12)``: row ``3n + k`` is aperture n's polarizer seen in colour k, over the 12 channels."""
        out = np.zeros((N_APERTURES * 3, N_CHANNELS))
        for n, nominal in enumerate(POLARIZER_ANGLES_DEG):
            for k in range(3):
                row = analyzer_row(nominal + float(self.angle_offsets_deg[n]), float(self.extinction_ratio[n, k]))
                out[3 * n + k, [3 * p + k for p in range(4)]] = row
        return out

    def lr_channel_matrix(self) -> np.ndarray:
        """``(16, 12)``: row ``m = 4n + q`` is what Bayer sub-image m sees of the 12 channels."""
        full = self.analyzer_matrix()
        return np.stack([full[3 * (m // 4) + BAYER_SITE_COLOUR[m % 4]] for m in range(4 * N_APERTURES)])

    def flat_field(self, raw_shape) -> np.ndarray:
        """The flat field ``F_n(u, v) = gain_n V_n(u, v)`` of each aperture on its raw grid.

        Parameters
        ----------
        raw_shape : tuple of int
            ``(H, W)`` raw pixels.

        Returns
        -------
        numpy.ndarray
            ``(4, H, W)`` float64, the relative response to uniform unpolarized light.
        """
        u, v = normalised_raw_coordinates(raw_shape)
        maps = vignetting_design(u, v) @ self.vignetting.T  # (H, W, 4)
        return np.moveaxis(maps, -1, 0) * self.gain[:, None, None]

    def lr_flat_field(self, raw_shape) -> np.ndarray:
        """``(16, H/2, W/2)``: the flat field at each Bayer sub-image's pixels (``m = 4n + q``)."""
        flat = self.flat_field(raw_shape)
        return np.stack([flat[m // 4, BAYER_OFFSETS[m % 4][0]::2, BAYER_OFFSETS[m % 4][1]::2]
                         for m in range(4 * N_APERTURES)])

    def psf_objects(self) -> list[PSF] | None:
        """The four apertures' :class:`~capssim.camera.psf.PSF`, or ``None`` (the capture's one PSF)."""
        return None if self.psf is None else [PSF.from_spec(spec) for spec in self.psf]

    def psf_kernels(self) -> list[np.ndarray] | None:
        """The four apertures' HR-grid kernels, or ``None``."""
        objects = self.psf_objects()
        return None if objects is None else [p.kernel() for p in objects]

    # serialisation ----------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-ready values (inf extinction as ``null``)."""
        return {
            "angle_offsets_deg": self.angle_offsets_deg.tolist(),
            "extinction_ratio": [[None if math.isinf(v) else v for v in row] for row in self.extinction_ratio.tolist()],
            "gain": self.gain.tolist(),
            "vignetting": {"basis": "u^i v^j, u = (col - (W-1)/2) / ((W-1)/2), v likewise for rows (raw grid)",
                           "monomials": [list(m) for m in VIGNETTING_MONOMIALS],
                           "coefficients": self.vignetting.tolist()},
            "psf": None if self.psf is None else [dict(p) for p in self.psf],
        }

    @classmethod
    def from_dict(cls, data: dict, *, where: str = "rig") -> "RigModel":
        """The inverse of :meth:`to_dict`; errors name ``where`` and the key."""
        if not isinstance(data, dict):
            raise InputError(where, type(data).__name__, "a mapping of rig quantities")
        unknown = set(data) - {"angle_offsets_deg", "extinction_ratio", "gain", "vignetting", "psf"}
        if unknown:
            raise InputError(where, f"keys {sorted(unknown)}", "angle_offsets_deg, extinction_ratio, gain, vignetting, psf")
        vig = data.get("vignetting")
        if isinstance(vig, dict):
            if [tuple(m) for m in vig.get("monomials", VIGNETTING_MONOMIALS)] != list(VIGNETTING_MONOMIALS):
                raise InputError(f"{where}.vignetting.monomials", vig.get("monomials"), str(VIGNETTING_MONOMIALS))
            vig = vig.get("coefficients")
        kwargs = {k: data[k] for k in ("angle_offsets_deg", "extinction_ratio", "gain", "psf") if k in data}
        if vig is not None:
            kwargs["vignetting"] = vig
        try:
            return cls(**kwargs)
        except InputError as exc:
            raise InputError(f"{where}: {exc.argument}", exc.received, exc.valid, exc.fix) from None


# -- the file -------------------------------------------------------------------------------------------
@dataclass
class RigFile:
    """A rig and what comes with it in a ``capssim-rig`` JSON file.

    ``geometry``: the array's 4 aperture homographies (HR reference -> aperture HR, at
    ``geometry.hr_shape``) or ``None``; ``calibrated``: the quantities that were measured
    (a calibration may cover only some); ``uncertainty`` / ``residuals``: per quantity, as the
    calibration wrote them; ``source``: provenance.
    """

    rig: RigModel
    geometry: ArrayGeometry | None = None
    calibrated: tuple[str, ...] = ()
    uncertainty: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)
    source: dict = field(default_factory=dict)
    path: Path | None = None

    def to_dict(self) -> dict:
        return {"format": RIG_FORMAT, "version": RIG_FORMAT_VERSION, "rig": self.rig.to_dict(),
                "geometry": None if self.geometry is None else geometry_entry(self.geometry),
                "calibrated": list(self.calibrated), "uncertainty": self.uncertainty, "residuals": self.residuals,
                "source": self.source}


def geometry_entry(geometry: ArrayGeometry) -> dict:
    """The file's ``geometry`` entry: the HR shape and the 4 aperture homographies (HR reference -> aperture HR)."""
    return {"hr_height": int(geometry.hr_shape[0]), "hr_width": int(geometry.hr_shape[1]),
            "aperture_homographies": geometry.aperture_homographies.tolist()}


def write_rig_json(path, rig: RigModel, *, geometry: ArrayGeometry | None = None, calibrated=(),
                   uncertainty: dict | None = None, residuals: dict | None = None, source: dict | None = None) -> Path:
    """Write a ``capssim-rig`` file atomically (temp file, then rename); returns its path."""
    data = RigFile(rig, geometry, tuple(calibrated), uncertainty or {}, residuals or {}, source or {}).to_dict()
    path = Path(path)
    atomic_write_text(path, json.dumps(data, indent=1, allow_nan=False) + "\n")
    return path


def read_rig_json(path, *, argument: str = "rig") -> RigFile:
    """Read a ``capssim-rig`` file; every problem is an :class:`InputError` naming ``argument``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(argument, str(path), "an existing capssim-rig JSON file",
                         "Write one with `capssim calibrate` (or give a preset name).")
    data = load_json_file(path, kind=f"{argument} file")  # nesting, encoding and syntax guarded
    if not isinstance(data, dict) or data.get("format") != RIG_FORMAT:
        raise InputError(argument, f"{path}: format {data.get('format') if isinstance(data, dict) else '?'!r}",
                         f"a {RIG_FORMAT!r} file", "Write one with `capssim calibrate`.")
    if data.get("version") != RIG_FORMAT_VERSION:
        raise InputError(argument, f"{path}: version {data.get('version')!r}", f"version {RIG_FORMAT_VERSION}")
    validate(RIG_FILE_SPEC, data, config_file=path, kind=f"{argument} file")
    rig = RigModel.from_dict(data.get("rig"), where=f"{argument} {path.name}: rig")
    geometry = None
    if data.get("geometry") is not None:
        geo = data["geometry"]
        try:
            geometry = ArrayGeometry(geo["aperture_homographies"], (int(geo["hr_height"]), int(geo["hr_width"])))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{argument} {path.name}: geometry", repr(exc)[:80],
                             "a mapping with hr_height, hr_width and aperture_homographies (4x3x3)") from None
        except InputError as exc:  # shape, non-finite values
            raise InputError(f"{argument} {path.name}: geometry.{exc.argument}", exc.received, exc.valid) from None
        check_homographies(geometry.aperture_homographies, geometry.hr_shape,
                           where=f"{argument} {path.name}: geometry.aperture_homographies")
    return RigFile(rig, geometry, tuple(data.get("calibrated") or ()), data.get("uncertainty") or {},
                   data.get("residuals") or {}, data.get("source") or {}, path)


__all__ = ["OVERRIDE_KEYS", "REALISTIC_RANGES", "RIG_FORMAT", "RIG_FORMAT_VERSION", "VIGNETTING_MONOMIALS", "RigFile", "RigModel",
           "analyzer_row", "geometry_entry", "normalised_raw_coordinates", "polarizer_reading", "radial_vignetting", "read_rig_json",
           "vignetting_design", "write_rig_json"]
