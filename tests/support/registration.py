"""A small simulated capture and a counting stand-in for the registration, for the tests of the stored
warps and of bad warps (offered as fixtures by tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capssim.camera.array_geometry import lr_homographies
from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture
from capssim.reconstruct.model import observation_model
from capssim.reconstruct.registration import RegistrationResult
from capssim.simulate import simulate_capture


def small_capture(folder: Path) -> Path:
    """``folder/capture``: a 32x32 HR capture (noise 0.01, seed 1) of a random scene in [0.2, 0.7]."""
    rng = np.random.default_rng(0)
    gt = (0.2 + 0.5 * rng.random((12, 32, 32))).astype(np.float32)
    path = Path(folder) / "capture"
    write_capture(path, simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=1))
    return path


def counting_registration(monkeypatch, **record) -> list:
    """Replace the registration by a fake that shifts aperture 1 by 0.25 px and returns ``record`` (over
    ``time_s`` 0.01, no warnings, no apertures); returns the list of the ``parameters`` of each call."""
    calls = []
    info = {"time_s": 0.01, "warnings": [], "apertures": [], **record}

    def fake(images, *, hr_shape, saturated=None, parameters=None, device="cpu"):
        calls.append(parameters)
        aperture = np.tile(np.eye(3), (4, 1, 1))
        aperture[1, 0, 2] = 0.25
        return RegistrationResult(lr_homographies(aperture), aperture, dict(info))

    monkeypatch.setattr(observation_model, "estimate_lr_homographies", fake)
    return calls
