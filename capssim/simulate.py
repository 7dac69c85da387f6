"""The paper's synthetic protocol (section 5.2): ground truth -> CAPS and DoFP captures.

Each aperture n >= 1 gets a random sub-pixel offset, rotation and scale (aperture 0 is
the reference); the HR image is analyzed, warped, blurred by the PSF, pixel-integrated
2x2, Bayer-sampled, and passed through the sensor model. The DoFP camera sees the same
scene with the same optics and noise at the HR pitch (same total pixel count 4HW).

Image borders: warped samples outside the ground truth replicate its border (the same
rule the reconstruction's operator uses), so applying the stored homographies and PSF to
``gt.tiff`` reproduces ``caps_raw.tiff`` exactly for ``--noise none``. The cost is that
the outermost ~shift_max HR pixels of apertures 1-3 see replicated rather than real
content.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from capssim.camera.camera_setup import CameraSetup, as_setup
from capssim.camera.homography import random_aperture_homographies
from capssim.camera.psf import PSF
from capssim.camera.rig import RigModel
from capssim.camera.sensor import Sensor
from capssim.captures.capture import Capture, build_meta
from capssim.errors import InputError
from capssim.files.imageio import centre_crop
from capssim.operators.measurement import CameraArrayMeasurement

log = logging.getLogger(__name__)

MIN_HR_SIZE = 16


@dataclass(frozen=True)
class PoseRanges:
    """Uniform ranges of the random aperture misalignment (HR pixels, degrees, relative scale)."""

    shift_max_px: float = 2.0
    rotation_max_deg: float = 0.5
    scale_max: float = 0.005


def prepare_ground_truth(gt: np.ndarray, *, crop: int | None = None,
                         allow_out_of_range: bool = False) -> tuple[np.ndarray, dict]:
    """Check a ``(12, H, W)`` ground truth and crop it to a size the camera model accepts.

    Values must be finite and on [0, 1] (full scale); others are refused, not clipped, so a
    mis-scaled ground truth never gives a silently different capture. With
    ``allow_out_of_range`` (the Python API's :func:`simulate_capture`) values outside [0, 1] are
    kept with a warning: above 1 the sensor saturates, below 0 it clips to black.

    ``crop`` takes a centred ``crop x crop`` window (must be a multiple of 4). Without it, a
    size that is not a multiple of 4 is trimmed (centred) to the largest multiple of 4,
    and the trim is reported.
    """
    gt = np.asarray(gt)
    if gt.ndim != 3 or gt.shape[0] != 12:
        raise InputError("gt", f"shape {gt.shape}", "a (12, H, W) array (channel c = 3*p + k)")
    if not np.issubdtype(gt.dtype, np.floating):
        raise InputError("gt", f"dtype {gt.dtype}", "a float array on [0, 1]")
    if not np.all(np.isfinite(gt)):
        raise InputError("gt", f"{int(np.sum(~np.isfinite(gt)))} NaN/inf values", "finite values")
    low, high = float(gt.min()), float(gt.max())
    if (low < 0.0 or high > 1.0) and not allow_out_of_range:
        raise InputError("gt", f"values in [{low:.6g}, {high:.6g}]", "intensities on [0, 1] (1 = full scale)",
                         "Rescale the ground truth (divide by its peak) or clip it to [0, 1] before simulating.")
    if high > 1.0:
        log.warning("ground truth above full scale (max %.4g) in %.2f %% of its values: the sensor saturates there, "
                    "and scores on [0, 1] do not describe it", high, 100.0 * float(np.mean(gt > 1.0)))
    if low < 0.0:
        log.warning("ground truth below 0 (min %.4g) in %.2f %% of its values: the sensor clips them to black",
                    low, 100.0 * float(np.mean(gt < 0.0)))
    h, w = gt.shape[1:]
    info: dict = {"source_height": h, "source_width": w}
    if crop is not None:
        crop = int(crop)
        if crop % 4 or crop < MIN_HR_SIZE:
            raise InputError("crop", crop, f"a multiple of 4 that is at least {MIN_HR_SIZE}",
                             f"Try --crop {max(MIN_HR_SIZE, crop - crop % 4)}.")
        if crop > min(h, w):
            raise InputError("crop", crop, f"at most the ground-truth size {h}x{w}")
        gt = centre_crop(gt, crop)
        info["crop"] = crop
    else:
        if min(h, w) < MIN_HR_SIZE:  # before the trim, which would report a crop nobody asked for (64x1 -> 64x0)
            raise InputError("gt", f"size {h}x{w}", f"at least {MIN_HR_SIZE}x{MIN_HR_SIZE} HR pixels",
                             "Use a larger ground truth (capssim.eval.synthetic makes any size).")
        th, tw = h - h % 4, w - w % 4
        if (th, tw) != (h, w):
            log.warning("ground truth %dx%d is not a multiple of 4; trimmed (centred) to %dx%d", h, w, th, tw)
            gt = centre_crop(gt, (th, tw))
            info["trimmed_to"] = [th, tw]
    if min(gt.shape[1:]) < MIN_HR_SIZE:
        raise InputError("gt", f"size {gt.shape[1]}x{gt.shape[2]}", f"at least {MIN_HR_SIZE}x{MIN_HR_SIZE} HR pixels")
    return np.ascontiguousarray(gt, dtype=np.float32), info


def simulate_capture(gt: np.ndarray, setup: CameraSetup | Sensor | None = None, *, seed: int = 0,
                     pose_ranges: PoseRanges = PoseRanges(), aperture_homographies: np.ndarray | None = None,
                     source: dict | None = None, kind: str = "simulated", extra_meta: dict | None = None,
                     psf: PSF | dict | None = None, dofp_layout=None, extinction_ratio: float | None = None,
                     rig: RigModel | None = None) -> Capture:
    """Simulate the CAPS raw frames and the DoFP raw frame of a ground truth: ``y = sensor(A x)`` (paper eq. 9).

    The measurement is :meth:`~capssim.operators.measurement.CameraArrayMeasurement.from_setup`;
    ``seed``'s three independent streams (:func:`~capssim.operators.measurement.seed_streams`) draw the poses, the CAPS
    noise and the DoFP noise, so a capture is reproducible.

    Parameters
    ----------
    gt : numpy.ndarray
        ``(12, 2H, 2W)`` intensities on [0, 1], channel ``c = 3 p + k``; values above full scale are kept
        with a warning (they saturate the sensor), negative ones refused (:func:`prepare_ground_truth`).
    setup : CameraSetup or Sensor, optional
        The camera set-up (a bare :class:`~capssim.camera.sensor.Sensor` takes the default set-up around it;
        None: the default set-up). The four options below, when given, replace its fields
        (:func:`~capssim.camera.camera_setup.as_setup`).
    psf : PSF or dict, optional
        The optical PSF on the HR grid (``sigma_hr_px`` in HR pixels).
    dofp_layout : str, optional
        The DoFP camera's mosaic layout.
    extinction_ratio : float, optional
        Polarizer ``T_max / T_min`` (inf: ideal).
    rig : RigModel, optional
        The array's imperfections.
    seed : int
        The capture's seed.
    pose_ranges : PoseRanges
        Ranges of the drawn aperture poses (shift, HR px; rotation, deg; scale).
    aperture_homographies : numpy.ndarray, optional
        ``(4, 3, 3)`` HR reference -> aperture (x=col, y=row), replacing the drawn poses.
    source : dict, optional
        Provenance of the ground truth, written to ``meta.json["source"]``.
    kind : str
        ``meta.json["kind"]``: ``simulated``, ``rendered`` or ``real``.
    extra_meta : dict, optional
        Extra keys for ``meta.json``.

    Returns
    -------
    Capture
        ``caps_raw`` ``(4, H, W)``, ``dofp_raw`` ``(2H, 2W)``, ``gt`` (not yet written); ``meta.json["setup"]``
        is the set-up's, and a non-ideal rig's true values also go to ``meta.json["rig"]``.
    """
    t0 = time.perf_counter()
    setup = as_setup(setup, psf=psf, dofp_layout=dofp_layout, extinction_ratio=extinction_ratio, rig=rig)
    gt, _ = prepare_ground_truth(gt, allow_out_of_range=True)
    hr_shape = gt.shape[1:]
    measurement = CameraArrayMeasurement.from_setup(setup, seed)
    measurement.psf.check_extent(hr_shape, option="psf")
    for n, aperture_psf in enumerate((setup.rig.psf_objects() if setup.rig is not None else None) or []):
        aperture_psf.check_extent(hr_shape, option=f"rig psf[{n}]")
    if aperture_homographies is None:
        aperture_homographies, pose_params = random_aperture_homographies(
            measurement.pose_rng, hr_shape, shift_max_px=pose_ranges.shift_max_px,
            rotation_max_deg=pose_ranges.rotation_max_deg, scale_max=pose_ranges.scale_max)
    else:
        pose_params = None
    caps_raw, dofp_raw = measurement.measure(gt, aperture_homographies)
    extra = {"poses": {"ranges": pose_ranges.__dict__, "apertures": pose_params}}
    if extra_meta:
        extra.update(extra_meta)
    meta = build_meta(kind=kind, hr_shape=hr_shape, aperture_homographies=aperture_homographies, setup=setup,
                      seed=seed, source=source, extra=extra)
    log.info("simulated %dx%d capture in %.2f s", hr_shape[0], hr_shape[1], time.perf_counter() - t0)
    return Capture(meta=meta, caps_raw=caps_raw, dofp_raw=dofp_raw, gt=gt)
