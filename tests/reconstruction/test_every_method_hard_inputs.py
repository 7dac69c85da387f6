"""Every registered method (built-in or plug-in, with its defaults and the true warps) on the hard inputs of the
project's standards: a black frame, S0 near 0, a saturated frame, a flat frame, extreme noise and a tiny frame of
odd size. The output always has the capture's HR shape and is finite; where the method reports a pixel observed it is
a physically valid intensity (the projection's guarantee, ``capssim.stokes.physical_validity``, where all four
angles of its colour are observed), and on the scenes
whose answer is known it is near it. A new method is checked here without a line of its own.

Measured on 2026-11-29 (all 15 built-in methods, 32 px HR, about 20 s in one process): the largest departures the
bounds below allow for are the learned networks' bias on a black frame (``cpdnet`` 0.015, ``caps-sisr`` 0.014 of full
scale), 0.06 on the flat frame (``array-kr``, ``caps-naive``: sigma 0.01 through Menon and the bicubic warp) and a mean
error of 0.04-0.07 on the 16 x 24 px texture.
"""

from __future__ import annotations

import functools
import logging

import numpy as np
import pytest

from capssim.camera.sensor import make_sensor
from capssim.eval.synthetic import texture_scene
from capssim.reconstruct.registry import available_methods, reconstruct
from capssim.simulate import simulate_capture
from capssim.stokes.polarization import split_12

#: case -> (HR shape, Gaussian noise std or 0 for none, constant value or None for the texture)
CASES = {
    "black": ((32, 32), 0.0, 0.0),
    "s0-near-zero": ((32, 32), 1e-3, 1e-6),
    "saturated": ((32, 32), 0.01, 1.0),
    "flat": ((32, 32), 0.01, 0.4),
    "noise-0.5": ((32, 32), 0.5, None),
    "odd-tiny": ((18, 26), 0.01, None),
}
#: the largest |output - truth| allowed on the constant scenes where the method reports pixels observed
CONSTANT_TOLERANCE = {"black": 0.02, "s0-near-zero": 0.02, "flat": 0.1}


@functools.lru_cache(maxsize=None)
def _capture(case: str):
    shape, sigma, value = CASES[case]
    if value is None:
        gt = texture_scene(max(shape), seed=2)[0][:, :shape[0], :shape[1]]
    else:
        gt = np.full((12, *shape), value, np.float32)
    sensor = make_sensor("gaussian", sigma=sigma) if sigma > 0 else make_sensor("none")
    return simulate_capture(gt, sensor, seed=1)


#: the built-in methods and the installed plug-ins (not the stand-ins other test modules register in this process)
METHODS = sorted(name for name, spec in available_methods().items()
                 if spec.plugin is not None or spec.module.startswith("capssim.reconstruct.methods."))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("case", list(CASES))
def test_every_method_stays_finite_and_valid_on_hard_inputs(case, method):
    capture = _capture(case)
    logging.disable(logging.WARNING)  # saturated and unobserved pixels are warned about; the record is checked
    try:
        out, record = reconstruct(capture, method, true_warps=True)
    finally:
        logging.disable(logging.NOTSET)
    image = np.asarray(out.image, dtype=np.float64)
    assert image.shape == (12, *capture.hr_shape), image.shape
    assert np.isfinite(image).all(), f"{method} on {case}: non-finite output"
    unobserved = np.zeros(image.shape, bool) if out.unobserved is None else np.asarray(out.unobserved, bool)
    # the projection leaves a colour's four angles as they are where any of them is unobserved (as it groups them)
    projected = ~split_12(unobserved).any(axis=0)  # (3, H, W)
    observed = split_12(image)[:, projected]
    if observed.size:
        assert observed.min() >= -1e-6, f"{method} on {case}: negative intensity {observed.min():.3g} where observed"
        assert observed.max() <= 2.0, f"{method} on {case}: intensity {observed.max():.3g}, twice full scale"
    if case in CONSTANT_TOLERANCE and observed.size:
        error = np.abs(observed - float(CASES[case][2])).max()
        assert error <= CONSTANT_TOLERANCE[case], f"{method} on {case}: {error:.3g} from the constant truth"
    if case == "odd-tiny":
        error = np.abs(image - capture.gt)[:, 2:-2, 2:-2].mean()
        assert error < 0.1, f"{method} on the {capture.hr_shape} texture: mean error {error:.3g}"
    if case == "saturated":
        assert "unobserved" in record and max(record["unobserved"]["fraction"]) > 0, record.get("unobserved")
