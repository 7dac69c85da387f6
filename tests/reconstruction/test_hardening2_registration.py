"""Issue 34, class 10: stored registrations are validated on load, and invalid ones recomputed.

A hand-edited ``CAPTURE/registration/*.json`` keeps its identity (its key still matches), so only its
warps tell it apart. Each row tampers the stored warps; the next run must warn, naming the file,
register again and store valid warps (never "Reduce dt", never a run with most pixels unobserved).
The registration is a counting fake (a 0.25 px shift of aperture 1) so that each row runs in
milliseconds.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pytest
import torch
from support.fuzz import invoke

from capssim.captures.capture import read_capture
from capssim.reconstruct.model import observation_model
from capssim.reconstruct.registration.store import warps_problem
from capssim.reconstruct.registry import RunContext, StageTimer


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    tamper: Callable[[np.ndarray], np.ndarray]  # (4, 3, 3) stored warps -> tampered
    reason: str  # in the warning

    def __str__(self):
        return f"class{self.cls}-{self.name.replace(' ', '-')}"


def _scaled(h):
    return h * 1000.0


def _translation_scaled(h):
    h = h.copy()
    h[:, :2, 2] = h[:, :2, 2] * 1000.0 + 100.0
    return h


def _singular(h):
    h = h.copy()
    h[3] = [[0, 0, 0], [0, 0, 0], [0, 0, 1]]
    return h


def _horizon(h):
    h = h.copy()
    h[2, 2, 0] = -0.1  # h31: the denominator changes sign at x = 10 (inside the 32 px grid)
    return h


def _zoomed(h):
    h = h.copy()
    h[1, :2, :2] *= 5.0
    return h


ROWS = [
    Row(10, "warps scaled by 1000", _scaled, "h33"),
    Row(10, "translations scaled by 1000", _translation_scaled, "of the reference grid"),
    Row(10, "singular warp", _singular, "singular"),
    Row(10, "horizon across the image", _horizon, "horizon"),
    Row(10, "aperture zoomed 5x", _zoomed, "scale"),
    Row(10, "not a number", lambda h: np.full_like(h, np.nan), "non-finite"),
]


@pytest.fixture
def estimator(fake_registration):
    """The registration replaced by a counting fake (a 0.25 px shift of aperture 1)."""
    return fake_registration()


def _geometry(path):
    capture = read_capture(path, load_gt=False)
    context = RunContext(device=torch.device("cpu"), timer=StageTimer(), registration="local-correlation")
    images, saturated = capture.lr_images()
    return observation_model.method_geometry(capture, context, images=images, saturated=saturated)


def _tamper(capture, row) -> str:
    files = sorted((capture / "registration").glob("*.json"))
    assert len(files) == 1
    content = json.loads(files[0].read_text())
    tampered = row.tamper(np.asarray(content["aperture_homographies"], dtype=np.float64))
    content["aperture_homographies"] = [[[None if not np.isfinite(v) else v for v in r] for r in m]
                                        for m in tampered.tolist()]
    files[0].write_text(json.dumps(content))
    return str(files[0])


@pytest.mark.parametrize("row", ROWS, ids=str)
def test_tampered_stored_warps_are_recomputed_with_a_warning(row, small_capture_dir, estimator, caplog):
    geometry, first = _geometry(small_capture_dir)
    assert first["store"] == "computed" and warps_problem(geometry.aperture_homographies, (32, 32)) is None
    name = _tamper(small_capture_dir, row)
    with caplog.at_level(logging.WARNING):
        again, record = _geometry(small_capture_dir)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(estimator) == 2 and record["store"] == "computed", warnings
    assert any(name in w and "recomputed" in w and row.reason in w for w in warnings), warnings
    np.testing.assert_array_equal(again.aperture_homographies, geometry.aperture_homographies)
    _, third = _geometry(small_capture_dir)  # the recomputed warps were stored again, valid
    assert len(estimator) == 2 and third["store"] == "reused"


def test_cli_run_on_a_tampered_store_recomputes_and_succeeds(small_capture_dir, estimator):
    outcome, text = invoke(["reconstruct", small_capture_dir, "-m", "caps", "--iterations", 1, "--no-progress"])
    assert outcome == "ok", text
    name = _tamper(small_capture_dir, ROWS[0])
    outcome, text = invoke(["reconstruct", small_capture_dir, "-m", "caps", "--iterations", 1, "--no-progress"])
    assert outcome == "ok" and name in text and "recomputed" in text, text
    assert "Reduce dt" not in text and len(estimator) == 2
    record = json.loads((small_capture_dir / "recon" / "caps.json").read_text())
    assert record["registration"]["store"] == "computed"
