"""Camera RGB from spectral radiance: real camera sensitivities, wavelength sampling, white balance.

The colour of each CAPS aperture (and of the ground truth) is what a real RGGB sensor
integrates::

    RGB_c = wb_c * integral L(lambda) s_c(lambda) d lambda            (c = R, G, B)

with ``s_c`` a measured camera spectral sensitivity (colour-science
``MSDS_CAMERA_SENSITIVITIES``, default ``Nikon 5100 (NPL)``, 380-780 nm, 5 nm steps,
linearly interpolated) and ``wb_c`` a fixed white balance: a white Lambertian reflector
under the D65 illuminant of radiance 1 reads ``(1, 1, 1)``. Light is integrated separately
for each Stokes component ``S0, S1, S2`` (they are linear in the radiance), which is what
Mitsuba's ``stokes`` integrator cannot do (it converts to sRGB; docs/notes/rendering-internals.md).

Wavelengths are importance-sampled with a pdf proportional to ``D65 * sum_c wb_c s_c``
(each channel's daylight response, mixed equally), four per ray (hero wavelengths,
equally spaced in the CDF; the first one stratified per pixel), so every channel's
estimator ``mean_i S(lambda_i) wb_c s_c(lambda_i) / p(lambda_i)`` has bounded weights.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from capssim.errors import InputError, UnknownNameError
from capssim.files.imageio import atomic_write_bytes

DEFAULT_CAMERA = "Nikon 5100 (NPL)"
WAVELENGTH_STEP_NM = 1.0
#: hero wavelengths per ray in Mitsuba's spectral variants
N_WAVELENGTHS = 4


def _cache_file(name: str):
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "capssim"
    safe = "".join(ch if ch.isalnum() else "_" for ch in name)
    return base / f"{safe}.npz"


def cached_arrays(name: str, build) -> dict:
    """Arrays from colour-science (slow to import) cached as ``~/.cache/capssim/NAME.npz``.

    ``build()`` returns a dict of arrays; it runs only when the cache is missing or unreadable.
    A cache that cannot be written is not an error.
    """
    path = _cache_file(name)
    try:
        with np.load(path, allow_pickle=False) as cached:
            return {k: cached[k] for k in cached.files}
    except (OSError, KeyError, ValueError):
        pass
    data = build()
    try:
        buf = io.BytesIO()
        np.savez(buf, **data)
        atomic_write_bytes(path, buf.getvalue())
    except OSError:
        pass
    return data


@lru_cache(maxsize=None)
def camera_sensitivities(name: str = DEFAULT_CAMERA) -> tuple[np.ndarray, np.ndarray]:
    """``(wavelengths_nm (K,), sensitivities (K, 3))`` on a 1 nm grid, each channel peak-normalised.

    The curves come from colour-science; importing it takes seconds, so the resampled
    table is cached in ``$XDG_CACHE_HOME/capssim`` (``~/.cache/capssim``) after first use.
    """
    def build():
        import colour

        known = list(colour.MSDS_CAMERA_SENSITIVITIES)
        if name not in known:
            raise UnknownNameError("camera sensitivity set", name, known)
        msds = colour.MSDS_CAMERA_SENSITIVITIES[name]
        lam = np.asarray(msds.wavelengths, dtype=np.float64)
        values = np.clip(np.asarray(msds.values, dtype=np.float64), 0.0, None)
        grid = np.arange(np.ceil(lam[0]), np.floor(lam[-1]) + WAVELENGTH_STEP_NM / 2, WAVELENGTH_STEP_NM)
        sens = np.stack([np.interp(grid, lam, values[:, c]) for c in range(3)], axis=1)
        return {"wavelengths": grid, "sensitivities": sens / sens.max(axis=0, keepdims=True)}

    data = cached_arrays("camera_sensitivities_" + name, build)
    grid, sens = data["wavelengths"], data["sensitivities"]
    return grid, sens


@dataclass
class CameraResponse:
    """Spectral sensitivities, their sampling pdf and the D65 white balance, for one camera.

    ``white_balance`` ``(3,)`` is set by :meth:`calibrate` for the active Mitsuba variant
    (the illuminant's representation differs between mono and spectral variants).
    """

    name: str = DEFAULT_CAMERA
    white_balance: np.ndarray | None = None
    variant: str | None = None

    def __post_init__(self):
        self.wavelengths, self.sensitivities = camera_sensitivities(self.name)
        self.pdf = None
        self._tables = {}

    @property
    def range_nm(self) -> tuple[float, float]:
        return float(self.wavelengths[0]), float(self.wavelengths[-1])

    def d65_on_grid(self) -> np.ndarray:
        """Mitsuba's own ``d65`` spectrum on :attr:`wavelengths` (spectral variants)."""
        import drjit as dr
        import mitsuba as mi

        d65 = mi.load_dict({"type": "d65"})
        si = dr.zeros(mi.SurfaceInteraction3f, self.wavelengths.size)
        column = mi.Float(self.wavelengths.astype(np.float32))
        si.wavelengths = mi.UnpolarizedSpectrum(*([column] * N_WAVELENGTHS))
        return np.asarray(d65.eval(si)).reshape(N_WAVELENGTHS, -1)[0].astype(np.float64)

    def calibrate(self) -> "CameraResponse":
        """Set the white balance (and, in spectral variants, the wavelength pdf) for the active
        Mitsuba variant; returns ``self``.

        White balance: ``wb_c = 1 / int D65 s_c`` with Mitsuba's D65 (mono variants: the D65
        value, the same for R, G, B). Wavelength pdf: ``p ~ D65 * sum_c wb_c s_c``, an equal
        mixture of the three channels' responses to daylight, so every channel's estimator
        has weights <= 3 for daylight-like spectra.
        """
        import drjit as dr
        import mitsuba as mi

        if mi.is_spectral:
            d65 = self.d65_on_grid()
            white = np.trapezoid(d65[:, None] * self.sensitivities, self.wavelengths, axis=0)
        else:
            si = dr.zeros(mi.SurfaceInteraction3f, 1)
            white = np.full(3, float(np.asarray(mi.load_dict({"type": "d65"}).eval(si)).ravel()[0]))
        if not np.all(white > 0):
            raise InputError("camera", self.name, "sensitivities with a positive response to D65")
        self.white_balance = 1.0 / white
        if mi.is_spectral:
            mix = d65 * (self.sensitivities * self.white_balance[None, :]).sum(axis=1)
            self.pdf = mix / np.trapezoid(mix, self.wavelengths)
        self.variant = mi.variant()
        self._tables = {}
        return self

    # --- drjit side (called while tracing a render kernel) ------------------------------
    def sampling_tables(self):
        """Mitsuba objects for sampling wavelengths and evaluating ``s_c``: cached per variant."""
        import mitsuba as mi

        key = mi.variant()
        cache = self._tables
        if key not in cache:
            lo, hi = self.range_nm
            distr = mi.ContinuousDistribution(mi.ScalarVector2f(lo, hi), self.pdf.astype(np.float32))
            weighted = (self.sensitivities * self.white_balance[None, :]).astype(np.float32)
            tables = [mi.Float(weighted[:, c]) for c in range(3)]
            cache[key] = (distr, tables)
        return cache[key]

    def sample_wavelengths(self, u):
        """Four hero wavelengths from one uniform sample ``u``; returns ``(Spectrum of lambdas, list of
        per-wavelength weights [R, G, B] as UnpolarizedSpectrum)`` with weight_c,i =
        wb_c s_c(lambda_i) / (4 p(lambda_i))."""
        import drjit as dr
        import mitsuba as mi

        distr, tables = self.sampling_tables()
        lams, pdfs = [], []
        for i in range(N_WAVELENGTHS):
            # hero wavelengths: u stratifies [0, 1/4), the others are its shifts by i/4
            ui = dr.minimum((u + i) / N_WAVELENGTHS, 1.0 - 1e-7)
            lam, pdf = distr.sample_pdf(ui)
            lams.append(lam)
            pdfs.append(pdf)
        lo, _ = self.range_nm
        n = len(self.wavelengths)
        weights = []
        for c in range(3):
            per = []
            for lam, pdf in zip(lams, pdfs):
                x = (lam - lo) / WAVELENGTH_STEP_NM
                i0 = mi.UInt32(dr.clip(dr.floor(x), 0, n - 2))
                t = dr.clip(x - mi.Float(i0), 0.0, 1.0)
                s = dr.lerp(dr.gather(mi.Float, tables[c], i0), dr.gather(mi.Float, tables[c], i0 + 1), t)
                per.append(dr.select(pdf > 0, s / (N_WAVELENGTHS * pdf), 0.0))
            weights.append(mi.UnpolarizedSpectrum(*per))
        return mi.UnpolarizedSpectrum(*lams), weights

    def to_meta(self) -> dict:
        return {"sensitivities": self.name, "range_nm": list(self.range_nm),
                "white_balance": "D65 white Lambertian = (1, 1, 1)",
                "white_balance_gains": None if self.white_balance is None else self.white_balance.tolist(),
                "wavelength_sampling": "4 hero wavelengths, pdf proportional to D65 x sum_c wb_c s_c"}

    def expected_rgb(self, reflectance_nm: np.ndarray, reflectance: np.ndarray) -> np.ndarray:
        """Analytic camera RGB of a Lambertian reflectance lit by D65 of radiance 1 (known-truth
        checks): ``int R D65 s_c / int D65 s_c``, with Mitsuba's D65 (a spectral variant must
        be active)."""
        lam = self.wavelengths
        r = np.interp(lam, np.asarray(reflectance_nm, float), np.asarray(reflectance, float))
        e = self.d65_on_grid()
        num = np.trapezoid((r * e)[:, None] * self.sensitivities, lam, axis=0)
        den = np.trapezoid(e[:, None] * self.sensitivities, lam, axis=0)
        return num / den
