"""The optical point-spread function (PSF) of the array's lenses, on the HR grid: one value, one default.

A :class:`PSF` is what ``meta.json["psf"]`` stores (:meth:`PSF.to_spec` / :meth:`PSF.from_spec`)
and what the observation model convolves with (:meth:`PSF.kernel`, the ``Blur_psf`` of the
paper's eq. 9). The paper's synthetic protocol (section 5.2) blurs with an isotropic Gaussian;
capssim's default is :data:`DEFAULT_PSF`, a Gaussian of std :data:`DEFAULT_SIGMA_HR_PX` HR pixels.
:meth:`PSF.check_extent` refuses a kernel wider than the image, or one whose blur would not fit
in memory (:mod:`capssim.runtime.resources`), before the kernel is built.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erf, j1

from capssim.errors import InputError
from capssim.runtime.resources import check_memory, check_range

#: default Gaussian PSF std, in HR pixels (half a raw pixel)
DEFAULT_SIGMA_HR_PX = 0.5

PSF_TYPES = ("none", "gaussian", "airy", "kernel")


#: Gaussian kernels are truncated at this many standard deviations
GAUSSIAN_TRUNCATE = 3.5
#: Airy kernels cover this many dark rings, sampled this many times per pixel and axis
AIRY_RINGS, AIRY_SUPERSAMPLE = 3, 9


def gaussian_kernel_radius(sigma_px: float, *, truncate: float = GAUSSIAN_TRUNCATE) -> int:
    """Half-width (pixels) of :func:`gaussian_psf_kernel`: 0 for ``sigma_px < 1e-6``, else ``ceil(truncate sigma)``."""
    if not (sigma_px >= 0 and math.isfinite(sigma_px)):
        raise InputError("sigma_px", sigma_px, "a finite number >= 0 (pixels)")
    return 0 if sigma_px < 1e-6 else max(1, int(math.ceil(truncate * sigma_px)))


def airy_kernel_radius(f_number: float, wavelength_nm: float, pixel_um: float, *, rings: int = AIRY_RINGS) -> int:
    """Half-width (pixels) of :func:`airy_psf_kernel`: ``(rings + 0.22) lambda N / pixel``, at least 1."""
    for arg, value in (("f_number", f_number), ("wavelength_nm", wavelength_nm), ("pixel_um", pixel_um)):
        if not (value > 0 and math.isfinite(value)):
            raise InputError(arg, value, "a finite positive number")
    lam_n_um = wavelength_nm * 1e-3 * f_number
    return max(1, int(math.ceil((rings + 0.22) * lam_n_um / pixel_um)))


def gaussian_psf_kernel(sigma_px: float, *, truncate: float = GAUSSIAN_TRUNCATE) -> np.ndarray:
    """Pixel-integrated isotropic Gaussian PSF of std ``sigma_px`` (pixels), odd square, sums to 1."""
    radius = gaussian_kernel_radius(sigma_px, truncate=truncate)
    if radius == 0:
        return np.ones((1, 1))
    edges = np.arange(-radius, radius + 2) - 0.5
    cdf = 0.5 * (1 + erf(edges / (math.sqrt(2) * sigma_px)))
    taps = np.diff(cdf)
    taps /= taps.sum()
    return np.outer(taps, taps)


def airy_psf_kernel(f_number: float, wavelength_nm: float, pixel_um: float, *,
                    rings: int = AIRY_RINGS, supersample: int = AIRY_SUPERSAMPLE) -> np.ndarray:
    """Diffraction-limited Airy PSF ``[2 J1(v)/v]^2``, ``v = pi r / (lambda N)``, pixel-integrated.

    ``pixel_um`` is the pitch of the grid it is applied on. The kernel covers ``rings``
    dark rings (first zero at ``1.22 lambda N``) and is normalised to sum 1.
    """
    radius = airy_kernel_radius(f_number, wavelength_nm, pixel_um, rings=rings)
    lam_n_um = wavelength_nm * 1e-3 * f_number
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    grid = np.arange(-radius, radius + 1)
    fine = (grid[:, None] + offsets[None, :]).ravel() * pixel_um
    yy, xx = np.meshgrid(fine, fine, indexing="ij")
    v = np.pi * np.hypot(xx, yy) / lam_n_um
    with np.errstate(invalid="ignore", divide="ignore"):
        psf = np.where(v < 1e-9, 1.0, (2 * j1(v) / np.where(v < 1e-9, 1.0, v)) ** 2)
    n = 2 * radius + 1
    psf = psf.reshape(n, supersample, n, supersample).sum(axis=(1, 3))
    return psf / psf.sum()


@dataclass(frozen=True)
class PSF:
    """An optical PSF on the HR grid.

    ``type``: ``none`` (identity), ``gaussian`` (``sigma_hr_px``, HR pixels), ``airy``
    (``f_number``, ``wavelength_nm``, ``hr_pixel_um`` micrometres) or ``kernel`` (explicit odd
    2-D taps). Build one with :meth:`gaussian`, :meth:`airy`, :meth:`none` or :meth:`from_spec`.
    """

    type: str = "gaussian"
    sigma_hr_px: float | None = DEFAULT_SIGMA_HR_PX
    f_number: float | None = None
    wavelength_nm: float | None = None
    hr_pixel_um: float | None = None
    taps: tuple | None = None

    # constructors ----------------------------------------------------------------------
    @classmethod
    def none(cls) -> "PSF":
        return cls(type="none", sigma_hr_px=None)

    @classmethod
    def gaussian(cls, sigma_hr_px: float = DEFAULT_SIGMA_HR_PX) -> "PSF":
        """Gaussian of std ``sigma_hr_px`` HR pixels; ``0`` gives :meth:`none`."""
        sigma = float(sigma_hr_px)
        if not (sigma >= 0 and math.isfinite(sigma)):
            raise InputError("psf sigma_hr_px", sigma_hr_px, "a finite number >= 0 (HR pixels; 0 = no blur)")
        return cls.none() if sigma == 0 else cls(type="gaussian", sigma_hr_px=sigma)

    @classmethod
    def airy(cls, f_number: float, wavelength_nm: float, hr_pixel_um: float) -> "PSF":
        """Diffraction-limited Airy PSF of an f-number at one wavelength, on HR pixels of ``hr_pixel_um``."""
        return cls(type="airy", sigma_hr_px=None, f_number=float(f_number), wavelength_nm=float(wavelength_nm),
                   hr_pixel_um=float(hr_pixel_um))

    @classmethod
    def from_spec(cls, spec: dict | None) -> "PSF":
        """The PSF a ``meta.json["psf"]`` mapping describes (``None``: no blur); extra keys are ignored."""
        spec = dict(spec or {"type": "none"})
        kind = str(spec.get("type", "none")).lower()
        try:
            if kind == "none":
                return cls.none()
            if kind == "gaussian":
                return cls.gaussian(float(spec["sigma_hr_px"]))
            if kind == "airy":
                pitch = spec.get("hr_pixel_um")
                return cls(type="airy", sigma_hr_px=None, f_number=float(spec["f_number"]),
                           wavelength_nm=float(spec["wavelength_nm"]),
                           hr_pixel_um=None if pitch is None else float(pitch))
            if kind == "kernel":
                taps = np.asarray(spec["kernel"], dtype=np.float64)
                if taps.ndim != 2 or taps.shape[0] % 2 == 0 or taps.shape[1] % 2 == 0:
                    raise InputError("psf.kernel", f"shape {taps.shape}", "an odd-sized 2-D kernel")
                return cls(type="kernel", sigma_hr_px=None, taps=tuple(map(tuple, taps.tolist())))
        except KeyError as exc:
            raise InputError(f"psf.{exc.args[0]}", None, f"a value for a PSF of type {kind!r}") from None
        raise InputError("psf.type", kind, f"one of {', '.join(PSF_TYPES)}")

    # views -----------------------------------------------------------------------------
    def to_spec(self) -> dict:
        """The ``meta.json["psf"]`` mapping of this PSF."""
        if self.type == "none":
            return {"type": "none"}
        if self.type == "gaussian":
            return {"type": "gaussian", "sigma_hr_px": self.sigma_hr_px}
        if self.type == "airy":
            spec = {"type": "airy", "f_number": self.f_number, "wavelength_nm": self.wavelength_nm}
            if self.hr_pixel_um is not None:
                spec["hr_pixel_um"] = self.hr_pixel_um
            return spec
        return {"type": "kernel", "kernel": [list(row) for row in self.taps]}

    def kernel(self, *, hr_pixel_um: float | None = None) -> np.ndarray:
        """Pixel-integrated kernel on the HR grid, ``(k, k)`` float64, odd ``k``, sums to 1.

        ``hr_pixel_um`` is needed for an Airy PSF stored without its own pitch.
        """
        if self.type == "none":
            return np.ones((1, 1))
        if self.type == "gaussian":
            return gaussian_psf_kernel(self.sigma_hr_px)
        if self.type == "airy":
            return airy_psf_kernel(self.f_number, self.wavelength_nm, self._airy_pitch(hr_pixel_um))
        return np.asarray(self.taps, dtype=np.float64)

    def _airy_pitch(self, hr_pixel_um: float | None) -> float:
        """The HR pixel pitch (micrometres) of an Airy PSF: its own, else ``hr_pixel_um``."""
        pitch = self.hr_pixel_um if self.hr_pixel_um is not None else hr_pixel_um
        if pitch is None:
            raise InputError("psf.hr_pixel_um", None, "the HR pixel pitch in micrometres for an Airy PSF")
        return float(pitch)

    def kernel_radius(self, *, hr_pixel_um: float | None = None) -> int:
        """Half-width of :meth:`kernel` in HR pixels, computed without building it."""
        if self.type == "none":
            return 0
        if self.type == "gaussian":
            return gaussian_kernel_radius(self.sigma_hr_px)
        if self.type == "airy":
            return airy_kernel_radius(self.f_number, self.wavelength_nm, self._airy_pitch(hr_pixel_um))
        return max(len(self.taps), len(self.taps[0])) // 2

    def check_extent(self, hr_shape: tuple[int, int], *, option: str = "psf", hr_pixel_um: float | None = None,
                     memory: bool = True) -> None:
        """Refuse a PSF whose kernel is wider than the image or whose blur would not fit in memory.

        Sane range: kernel side ``2 r + 1`` at most ``min(H, W)`` of ``hr_shape``. Memory: the
        kernel itself (an Airy kernel is built on a grid :data:`AIRY_SUPERSAMPLE` times finer)
        and the convolution's unfolded patches, ``k^2 (H + 2r) (W + 2r)`` float64 (one image
        plane at a time); ``memory=False`` checks the range alone. Raises
        :class:`~capssim.errors.ResourceError` naming ``option``.
        """
        radius = self.kernel_radius(hr_pixel_um=hr_pixel_um)
        side = 2 * radius + 1
        h, w = (int(v) for v in hr_shape)
        what = f"the {self.type} PSF's kernel ({side}x{side} HR pixels)"
        fix = f"Use a smaller {'PSF (--psf-sigma-hr-px, --f-number)' if option == 'psf' else option}"
        if radius:
            check_range(option, side, high=min(h, w), what=f"the {self.type} PSF's kernel side (HR pixels)",
                        reason=f"the smaller side of the {h}x{w} image", fix=fix + " or a larger image.")
        if not memory:
            return
        build = (side * AIRY_SUPERSAMPLE) ** 2 * 8 * 6 if self.type == "airy" else side * side * 8
        convolve = side * side * (h + 2 * radius) * (w + 2 * radius) * 8 if radius else 0
        check_memory(option, build + convolve, what=f"blurring a {h}x{w} image with {what}",
                     fix=fix + " or a smaller image.")


#: the PSF of a capture whose caller names none: Gaussian, :data:`DEFAULT_SIGMA_HR_PX` HR pixels
DEFAULT_PSF = PSF.gaussian(DEFAULT_SIGMA_HR_PX)


def as_psf(psf: "PSF | dict | None") -> PSF:
    """``psf`` as a :class:`PSF`: a PSF, a ``meta.json`` mapping, or ``None`` for :data:`DEFAULT_PSF`."""
    if psf is None:
        return DEFAULT_PSF
    return psf if isinstance(psf, PSF) else PSF.from_spec(psf)

