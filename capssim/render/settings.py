"""What a render of a library scene may be asked for: :class:`RenderSettings`, with its checks and defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.camera_setup import CameraSetup, as_setup
from capssim.camera.sensor import noise_sigma_estimate
from capssim.errors import InputError
from capssim.render.pinhole_array import RigTolerances
from capssim.render.spectral import DEFAULT_CAMERA
from capssim.runtime.resources import check_memory

#: smallest HR ground-truth size (pixels)
MIN_SIZE = 16
#: default Monte-Carlo target (RMS std of the 12-channel ground truth, full scale) without sensor noise
DEFAULT_TARGET_NOISE = 0.004
#: with sensor noise: this fraction of the sensor's noise at mid grey (Monte-Carlo adds <= 12% to the total)
TARGET_NOISE_FRACTION_OF_SENSOR = 0.5
#: upper limit of samples per HR ground-truth pixel when spp comes from the target noise
DEFAULT_MAX_SPP = 1024
#: planar warp: the reference is rendered 4x finer than the ground truth up to this size, 2x above
#: (to bound memory); docs/notes/rendering-internals.md gives the accuracy of each factor
OVERSAMPLE_4_MAX_SIZE = 512
#: bytes held per reference-render pixel: the Stokes sums and squares (21 float64) and the
#: pooled pilot and main renders' means (up to 5 x 9 float64), rounded up
RENDER_BYTES_PER_PIXEL = 512
#: bytes held per HR ground-truth pixel by the camera model (about 8 float64 copies of 12 channels)
HR_BYTES_PER_PIXEL = 768
#: margin (HR pixels) the aperture warps add around the PSF's in the memory estimate
WARP_MARGIN_ESTIMATE = 4


@dataclass(frozen=True)
class RenderSettings:
    """Options of :func:`capssim.render.render_capture` (all optional).

    ``size``: HR ground-truth size in pixels (raw frames are ``size/2``). ``spp``: samples per
    HR ground-truth pixel (``None``: from ``target_noise``, the RMS Monte-Carlo std wanted in
    the 12-channel ground truth on [0, 1] full scale; default :data:`DEFAULT_TARGET_NOISE`
    without sensor noise, :data:`TARGET_NOISE_FRACTION_OF_SENSOR` of the sensor's mid-grey
    noise with it), at most ``max_spp``. ``seed``: the array errors and the sensor noise
    (:func:`capssim.operators.measurement.seed_streams`); ``render_seed`` (default ``seed``) seeds only
    the Monte-Carlo sampling, so two renders of the same array geometry can differ in noise
    alone. ``setup``: the camera set-up (:class:`~capssim.camera.camera_setup.CameraSetup`: sensor, optical
    PSF, DoFP layout, extinction ratio, rig; ``None``: the default set-up). ``variant``: Mitsuba
    variant or ``auto``. ``scene_params`` / ``geometry_params``: the scene's parameters and the array's
    :class:`~capssim.render.pinhole_array.RigTolerances`. ``planar``: ``auto`` (scene flag + measured
    parallax), ``on`` or ``off``; ``oversample``: the planar warp's render grid factor (``None``: 4 up
    to :data:`OVERSAMPLE_4_MAX_SIZE` px, else 2). ``camera``: the camera sensitivities.
    ``progress(stage, done, total)`` is called as rays finish. With ``record_timing=False``
    ``meta.json`` holds no wall times (byte-identical regeneration). ``measure_savings`` also
    renders the alternatives each choice avoided and records the measured times (slow).
    The set-up's rig (:class:`capssim.camera.rig.RigModel`) applies on both paths: the planar warp
    path applies its analyzer rows, PSFs and flat field to the warped reference render; the
    per-aperture path renders apertures 1-3 through polarizers at the rig's angles and
    per-colour extinction ratios, then applies the PSFs and flat field. A non-ideal rig's
    extinction ratios replace the set-up's ``extinction_ratio`` for the CAPS frames (the DoFP
    camera keeps it). ``aperture_homographies`` ``(4, 3, 3)``: replaces the array's drawn homographies
    (planar warp path only; e.g. a calibrated rig's geometry, at ``size``).
    """

    size: int = 256
    spp: int | None = None
    seed: int = 0
    setup: CameraSetup | None = None
    variant: str = "auto"
    scene_params: dict | None = None
    geometry_params: dict | None = None
    target_noise: float | None = None
    record_timing: bool = True
    progress: Callable[[str, int, int], None] | None = None
    planar: str = "auto"
    oversample: int | None = None
    camera: str = DEFAULT_CAMERA
    max_spp: int = DEFAULT_MAX_SPP
    measure_savings: bool = False
    render_seed: int | None = None
    aperture_homographies: np.ndarray | None = None

    def checked(self) -> "RenderSettings":
        """These settings checked (:class:`~capssim.errors.InputError` otherwise), with defaults filled in.

        The result has an integer ``size``, a :class:`~capssim.camera.camera_setup.CameraSetup`, the
        ``oversample`` factor in effect and an integer ``render_seed``.
        """
        size = _check_size(self.size)
        setup = as_setup(self.setup)
        RigTolerances.from_params(self.geometry_params)
        psf = setup.psf
        if self.planar not in ("auto", "on", "off"):
            raise InputError("planar", self.planar, "'auto', 'on' or 'off'")
        oversample = (4 if size <= OVERSAMPLE_4_MAX_SIZE else 2) if self.oversample is None else self.oversample
        if oversample not in (1, 2, 3, 4):
            raise InputError("oversample", self.oversample, "1, 2, 3 or 4 (or None for automatic)")
        spp = self.spp
        if spp is not None and not (isinstance(spp, (int, np.integer)) and 1 <= spp <= 1 << 16):
            raise InputError("spp", spp, "an integer in [1, 65536] (samples per HR pixel), or None for --target-noise")
        if self.target_noise is not None and not (math.isfinite(self.target_noise) and self.target_noise > 0):
            raise InputError("target_noise", self.target_noise, "a positive number (RMS std on [0, 1] full scale)")
        if not (isinstance(self.max_spp, (int, np.integer)) and not isinstance(self.max_spp, bool)
                and 1 <= self.max_spp <= 1 << 16):
            raise InputError("max_spp", self.max_spp, "an integer in [1, 65536] (samples per HR pixel)")
        for n, aperture_psf in enumerate((setup.rig.psf_objects() if setup.rig is not None else None) or []):
            aperture_psf.check_extent((size, size), option=f"rig psf[{n}]", memory=False)
        if self.aperture_homographies is not None:
            ArrayGeometry(self.aperture_homographies, (size, size))  # refuses a bad stack, naming it
        render_seed = self.seed if self.render_seed is None else int(self.render_seed)
        checked = replace(self, size=size, setup=setup, oversample=oversample, render_seed=render_seed)
        psf.check_extent((size, size), option="psf", memory=False)
        check_memory("size", checked.memory_estimate_bytes(), what=f"a {size}x{size} render",
                     fix="Use a smaller --size.")
        psf.check_extent((size, size), option="psf")
        return checked

    def memory_estimate_bytes(self) -> int:
        """Bytes a render of these (checked) settings holds at its peak, about.

        The reference render covers ``size + 2 margin`` HR pixels (margin: the PSF's radius
        and the warps' :data:`WARP_MARGIN_ESTIMATE`), ``oversample`` times finer on the planar
        path, at :data:`RENDER_BYTES_PER_PIXEL`; the camera model adds
        :data:`HR_BYTES_PER_PIXEL` per ground-truth pixel.
        """
        margin = self.setup.psf.kernel_radius() + WARP_MARGIN_ESTIMATE
        fine = 1 if self.planar == "off" else self.oversample
        render_side = (self.size + 2 * margin) * fine
        return render_side * render_side * RENDER_BYTES_PER_PIXEL + self.size * self.size * HR_BYTES_PER_PIXEL

    def target(self) -> float:
        """The Monte-Carlo target: ``target_noise``, or the default for this sensor (checked settings)."""
        if self.target_noise is not None:
            return self.target_noise
        sigma = noise_sigma_estimate(self.setup.sensor, 0.5)
        if sigma <= 0:
            return DEFAULT_TARGET_NOISE
        return max(1e-3, TARGET_NOISE_FRACTION_OF_SENSOR * sigma)


def _check_size(size) -> int:
    try:
        s = int(size)
    except (TypeError, ValueError):
        raise InputError("size", repr(size), "an integer") from None
    if s != size or s < MIN_SIZE or s % 4:
        raise InputError("size", size, f"a multiple of 4 that is at least {MIN_SIZE} (the HR ground-truth size)",
                         f"Try --size {max(MIN_SIZE, s - s % 4)}.")
    return s


__all__ = ["DEFAULT_MAX_SPP", "DEFAULT_TARGET_NOISE", "MIN_SIZE", "RenderSettings"]
