"""Oracle captures: a capture with one imperfection replaced by the truth, everything else kept.

Both oracles re-simulate the capture's ground truth through the reconstruction's own forward
operator ``A`` (paper eq. 9: analyzer, aperture warp by the capture's stored homographies, the
capture's PSF ``meta.json["psf"]``, 2x2 pixel integration, RGGB sampling; the DoFP mosaic with the
same optics), built by :class:`~capssim.operators.measurement.CameraArrayMeasurement` from the capture's camera
set-up:

* :func:`model_exact_capture` ``y = sensor(A x)`` with the capture's own sensor and the noise draw of
  its seed (the streams of :func:`~capssim.operators.measurement.seed_streams`, as
  :func:`~capssim.simulate.simulate_capture` and the suites' ``apply_sensor`` draw them): for an
  additive Gaussian sensor the noise vector is the capture's own, only the signal under it changes;
* ``noise=False``: ``y = A x`` exactly, float32, with the noise-free sensor (``model: none``).

What separates a capture from its model-exact oracle is everything ``A`` does not model: the
renderer's warp of the scene (not an interpolation of the HR grid), its pixel integration by
supersampling, parallax of non-planar scenes, a real camera's optics.
"""

from __future__ import annotations

import copy

import numpy as np

from capssim.camera.sensor import NoNoiseSensor, noise_sigma_estimate
from capssim.captures.capture import Capture
from capssim.errors import InputError
from capssim.operators.measurement import CameraArrayMeasurement


def _measurement(capture: Capture, *, noise: bool) -> CameraArrayMeasurement:
    setup = capture.setup
    if not noise:
        setup = setup.replace(sensor=NoNoiseSensor())
    return CameraArrayMeasurement.from_setup(setup, int(capture.meta.get("seed", 0)), psf=capture.psf)


def model_exact_capture(capture: Capture, *, noise: bool = True) -> Capture:
    """The capture's ground truth passed through the reconstruction's forward operator.

    Parameters
    ----------
    capture : Capture
        A capture with its ground truth ``gt`` ``(12, 2H, 2W)`` on [0, 1].
    noise : bool, keyword-only
        ``True``: the capture's sensor and the noise draw of its seed; ``False``: no noise
        (float32 irradiance, sensor ``none``).

    Returns
    -------
    Capture
        Same ``meta.json`` (homographies, PSF, layout, seed) except the sensor when ``noise`` is
        False, and ``meta["oracle"]`` naming the oracle; ``caps_raw`` ``(4, H, W)``, ``dofp_raw``
        ``(2H, 2W)`` when the capture has one, the same ``gt``.

    Raises
    ------
    InputError
        If the capture has no ground truth.
    """
    if capture.gt is None:
        raise InputError("capture", "a capture without gt.tiff", "a capture with its ground truth",
                         "An error budget needs the truth: use a simulated, rendered or ground-truth scene.")
    measurement = _measurement(capture, noise=noise)
    gt = np.asarray(capture.gt, dtype=np.float64)
    caps_irradiance, dofp_irradiance = measurement.irradiance(gt, capture.aperture_homographies())
    caps = measurement.sense_caps(caps_irradiance)
    dofp = measurement.sense_dofp(dofp_irradiance) if capture.dofp_raw is not None else None
    meta = copy.deepcopy(capture.meta)
    if not noise:
        sensor = measurement.sensor
        meta["sensor"] = sensor.to_meta()
        if "setup" in meta:
            meta["setup"] = capture.setup.replace(sensor=sensor).to_meta()
    meta["oracle"] = {"kind": "model-exact" if noise else "noise-free",
                      "by": "capssim.eval.error_budget.oracles.model_exact_capture"}
    return Capture(meta=meta, caps_raw=caps, dofp_raw=dofp, gt=capture.gt)


def capture_mismatch(capture: Capture, oracle: Capture, *, border: int = 4) -> dict:
    """How far a capture is from its model-exact oracle, frame by frame, against the sensor's noise.

    Parameters
    ----------
    capture, oracle : Capture
        A capture and :func:`model_exact_capture` of it (``noise=True``: the same noise draw, so for an
        additive sensor the difference is the signal the operator does not model, noise-free).
    border : int, keyword-only
        Raw pixels left out at each edge (the warps' border padding).

    Returns
    -------
    dict
        ``caps_rms`` (full scale, all four frames), ``caps_rms_per_aperture`` ``[4]``, ``dofp_rms`` (or
        None), ``noise_sigma`` (the sensor's std at mid-scale, full scale) and ``caps_rms_over_noise``:
        above 1, the operator mis-models the capture by more than the noise.
    """
    def rms(a, b):
        d = (np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64))[..., border:-border, border:-border]
        return float(np.sqrt(np.mean(d ** 2)))

    caps, model = capture.caps_float(), oracle.caps_float()
    sigma = float(noise_sigma_estimate(capture.sensor))
    total = rms(caps, model)
    dofp = (rms(capture.dofp_float(), oracle.dofp_float())
            if capture.dofp_raw is not None and oracle.dofp_raw is not None else None)
    return {"caps_rms": total, "caps_rms_per_aperture": [rms(caps[n], model[n]) for n in range(caps.shape[0])],
            "dofp_rms": dofp, "noise_sigma": sigma, "caps_rms_over_noise": total / sigma if sigma > 0 else None}


__all__ = ["capture_mismatch", "model_exact_capture"]
