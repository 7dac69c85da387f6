"""The camera-array measurement ``y = sensor(A x)`` and its random-stream rule (paper eq. 9-11, section 5.2).

``A`` is the shared observation model of :mod:`capssim.operators.camera`: the CAPS raw
operator (analyzer, aperture warp, optical PSF, 2x2 pixel integration, RGGB sampling; eq. 9)
and the DoFP raw operator with the same optics. ``sensor`` is a :class:`capssim.camera.sensor.Sensor`
(noise, clipping, quantization).

One seed gives three independent random streams (:func:`seed_streams`): the aperture poses,
the CAPS sensor noise and the DoFP sensor noise. Simulation, rendering, the dataset and the
benchmarks all draw from these streams in the same order, so a seed names one measurement
wherever it is made.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from capssim.camera.camera_setup import CameraSetup
from capssim.camera.psf import PSF, as_psf
from capssim.camera.rig import RigModel
from capssim.camera.sensor import Sensor
from capssim.conventions import DEFAULT_DOFP_LAYOUT
from capssim.operators.base import Composition
from capssim.operators.camera import caps_raw_operator, dofp_raw_operator


def seed_streams(seed: int) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
    """The ``(pose, caps, dofp)`` generators of one seed: ``SeedSequence(seed).spawn(3)``, in that order."""
    pose_rng, caps_rng, dofp_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    return pose_rng, caps_rng, dofp_rng


@dataclass
class CameraArrayMeasurement:
    """``y = sensor(A x)`` for the CAPS array and the DoFP camera, with the random streams of ``seed``.

    ``psf``: the optical PSF on the HR grid (a :class:`~capssim.camera.psf.PSF`, a ``meta.json``
    mapping, or ``None`` for the default); ``dofp_layout``: the DoFP mosaic layout;
    ``extinction_ratio``: of the polarizers (``None``: ideal). The three streams of
    :func:`seed_streams` are created once, so successive calls continue them. ``rig``: an
    imperfect array (:class:`capssim.camera.rig.RigModel`: its analyzer, per-aperture PSFs and flat
    field replace the ideal ones for the CAPS frames; the DoFP camera is another camera and
    keeps ``psf`` and ``extinction_ratio``).
    """

    sensor: Sensor
    psf: PSF | dict | None = None
    dofp_layout: object = DEFAULT_DOFP_LAYOUT
    extinction_ratio: float | None = None
    seed: int = 0
    rig: RigModel | None = None
    pose_rng: np.random.Generator = field(init=False, repr=False)
    caps_rng: np.random.Generator = field(init=False, repr=False)
    dofp_rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self):
        self.psf = as_psf(self.psf)
        self.pose_rng, self.caps_rng, self.dofp_rng = seed_streams(self.seed)

    @classmethod
    def from_setup(cls, setup: CameraSetup, seed: int = 0, *, psf: PSF | None = None) -> "CameraArrayMeasurement":
        """``y = sensor(A x)`` of a camera set-up (:class:`~capssim.camera.camera_setup.CameraSetup`: sensor, PSF,
        DoFP layout, extinction ratio, rig) with the random streams of ``seed``; ``psf`` replaces the
        set-up's (a renderer, whose views are already blurred, passes ``PSF.none()``)."""
        return cls(setup.sensor, psf=setup.psf if psf is None else psf, dofp_layout=setup.dofp_layout,
                   extinction_ratio=setup.extinction_ratio, seed=seed, rig=setup.rig)

    # A ----------------------------------------------------------------------------------
    def caps_operator(self, hr_shape, aperture_homographies: np.ndarray) -> Composition:
        """``(12, 2H, 2W) -> (4, H, W)`` CAPS raw irradiance (eq. 9); homographies ``(4, 3, 3)`` HR ref -> aperture."""
        return caps_raw_operator(hr_shape, aperture_homographies, self.psf.kernel(),
                                 extinction_ratio=self.extinction_ratio, rig=self.rig)

    def dofp_operator(self, hr_shape) -> Composition:
        """``(12, 2H, 2W) -> (2H, 2W)`` DoFP raw irradiance with the same optics."""
        return dofp_raw_operator(hr_shape, self.psf.kernel(), layout=self.dofp_layout,
                                 extinction_ratio=self.extinction_ratio)

    def irradiance(self, x: np.ndarray, aperture_homographies: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Noiseless ``(A_caps x, A_dofp x)``, float64, of a ``(12, 2H, 2W)`` HR image on [0, 1]."""
        hr_shape = x.shape[1:]
        image = torch.from_numpy(np.asarray(x).astype(np.float64))
        with torch.no_grad():
            caps = self.caps_operator(hr_shape, aperture_homographies)(image)
            dofp = self.dofp_operator(hr_shape)(image)
        return caps.numpy(), dofp.numpy()

    # sensor -----------------------------------------------------------------------------
    def sense_caps(self, irradiance: np.ndarray) -> np.ndarray:
        """CAPS raw frames ``(4, H, W)`` from their irradiance, drawing from the CAPS stream."""
        return self.sensor.capture(irradiance, self.caps_rng)

    def sense_dofp(self, irradiance: np.ndarray) -> np.ndarray:
        """DoFP raw frame ``(2H, 2W)`` from its irradiance, drawing from the DoFP stream."""
        return self.sensor.capture(irradiance, self.dofp_rng)

    def measure(self, x: np.ndarray, aperture_homographies: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(caps_raw, dofp_raw) = sensor(A x)`` of a ``(12, 2H, 2W)`` HR image on [0, 1]."""
        caps_irradiance, dofp_irradiance = self.irradiance(x, aperture_homographies)
        return self.sense_caps(caps_irradiance), self.sense_dofp(dofp_irradiance)


__all__ = ["CameraArrayMeasurement", "seed_streams"]
