"""capssim.camera.array_geometry: the 16 sub-image homographies are derived once from the 4 aperture ones,
and a meta.json whose 16 and 4 disagree is refused with a message that says how to fix it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capssim.camera.array_geometry import ArrayGeometry, lr_homographies, raw_matrix, sub_image_matrix
from capssim.camera.homography import apply_homography, similarity
from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_capture, write_capture
from capssim.errors import CaptureFormatError, InputError
from capssim.simulate import simulate_capture


def _geometry(hr=(32, 48)):
    hn = np.stack([np.eye(3)] + [similarity((0.3 * n, -0.2 * n), 0.1 * n, 1.0 + 0.001 * n, (23.5, 15.5))
                                 for n in range(1, 4)])
    return ArrayGeometry(hn, hr)


def test_sub_image_homographies_are_site_matrix_times_aperture_homography():
    geo = _geometry()
    lr = geo.lr_homographies
    assert lr.shape == (16, 3, 3)
    for m in range(16):
        n, q = divmod(m, 4)
        np.testing.assert_array_equal(lr[m], sub_image_matrix(q) @ geo.aperture_homographies[n])
    np.testing.assert_array_equal(lr, lr_homographies(geo.aperture_homographies))
    # every sub-image pixel centre lies where its aperture warp and its Bayer site put it
    for m in range(16):
        n, q = divmod(m, 4)
        hr_pt = np.array([[7.0, 5.0]])
        raw = apply_homography(raw_matrix() @ geo.aperture_homographies[n], hr_pt)[0]
        sub = apply_homography(lr[m], hr_pt)[0]
        oy, ox = [(0, 0), (0, 1), (1, 0), (1, 1)][q]
        np.testing.assert_allclose(raw, [2 * sub[0] + ox, 2 * sub[1] + oy], atol=1e-12)
    np.testing.assert_array_equal(geo.lr_aperture_warps[5], geo.aperture_homographies[1])
    assert geo.raw_shape == (16, 24) and geo.sub_shape == (8, 12)


def test_geometry_refuses_bad_homographies():
    with pytest.raises(InputError, match="aperture_homographies"):
        ArrayGeometry(np.eye(3)[None], (32, 32))
    with pytest.raises(InputError, match="finite"):
        ArrayGeometry(np.full((4, 3, 3), np.nan), (32, 32))


def test_capture_geometry_round_trips(tmp_path):
    gt = np.random.default_rng(0).random((12, 32, 32)).astype(np.float32)
    cap = simulate_capture(gt, make_sensor("none"), seed=1)
    write_capture(tmp_path / "cap", cap)
    back = read_capture(tmp_path / "cap")
    np.testing.assert_array_equal(back.geometry.aperture_homographies, cap.geometry.aperture_homographies)
    np.testing.assert_array_equal(back.true_lr_homographies(), back.geometry.lr_homographies)


def test_meta_whose_16_and_4_disagree_is_refused(tmp_path):
    gt = np.random.default_rng(0).random((12, 32, 32)).astype(np.float32)
    write_capture(tmp_path / "cap", simulate_capture(gt, make_sensor("none"), seed=1))
    meta_path = tmp_path / "cap" / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["lr_images"][6]["homography"][0][2] += 0.25  # hand-edited: sub-image 6 moved a quarter pixel
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CaptureFormatError) as info:
        read_capture(tmp_path / "cap")
    message = str(info.value)
    assert "lr_images[6]" in message and "aperture_homographies[1]" in message and "0.25" in message
    assert "rewrite the 16 entries" in message


def test_cli_reports_disagreeing_meta_without_traceback(tmp_path):
    import subprocess
    import sys

    gt = np.random.default_rng(0).random((12, 32, 32)).astype(np.float32)
    write_capture(tmp_path / "cap", simulate_capture(gt, make_sensor("none"), seed=1))
    meta_path = tmp_path / "cap" / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["aperture_homographies"][2][1][2] += 1.0  # the 4 edited, the 16 left as they were
    meta_path.write_text(json.dumps(meta))
    r = subprocess.run([sys.executable, "-m", "capssim", "reconstruct", str(tmp_path / "cap"), "-m", "caps-naive",
                        "--true-warps"], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "disagrees" in r.stderr
