"""Channel order, Bayer sites, DoFP layouts and homography frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.array_geometry import lr_homographies, raw_matrix, sub_image_matrix
from capssim.camera.homography import apply_homography, registration_error_hr_px, rotation_and_scale, similarity
from capssim.conventions import (
    CHANNEL_NAMES,
    LR_IMAGE_CHANNELS,
    bayer_channel_map,
    channel_index,
    dofp_channel_map,
    dofp_layout,
    dofp_layout_name,
    lr_image_name,
)
from capssim.errors import InputError
from capssim.operators import DoFPMosaic


def test_channel_order():
    assert CHANNEL_NAMES[:4] == ("0-R", "0-G", "0-B", "45-R")
    assert channel_index(135, "B") == 11 and channel_index(90, 1) == 7
    assert LR_IMAGE_CHANNELS == (0, 1, 1, 2, 3, 4, 4, 5, 6, 7, 7, 8, 9, 10, 10, 11)
    assert lr_image_name(6) == "45-G2"


def test_sony_dofp_mosaic_pixel_by_pixel():
    # Sony IMX250MYR: polarizer cell [[90, 45], [135, 0]], colour quad-Bayer RGGB over 2x2 cells
    expected_angle = [[90, 45, 90, 45], [135, 0, 135, 0]] * 2
    expected_colour = [[0, 0, 1, 1], [0, 0, 1, 1], [1, 1, 2, 2], [1, 1, 2, 2]]
    cmap = dofp_channel_map(8, 8, "sony")
    for r in range(8):
        for c in range(8):
            want = channel_index(expected_angle[r % 4][c % 4], expected_colour[r % 4][c % 4])
            assert cmap[r, c] == want, (r, c)
    # the operator samples exactly that channel
    img = torch.arange(12, dtype=torch.float64)[:, None, None].expand(12, 8, 8).contiguous()
    img = img * 100 + torch.arange(64, dtype=torch.float64).reshape(8, 8)
    mosaic = DoFPMosaic(8, 8, layout="sony")(img)
    np.testing.assert_array_equal(mosaic.numpy(), cmap * 100 + np.arange(64).reshape(8, 8))


def test_alternative_layout_and_names():
    cmap = dofp_channel_map(4, 4, [[0, 45], [135, 90]])
    assert cmap[0, 0] == channel_index(0, "R") and cmap[1, 1] == channel_index(90, "R")
    assert cmap[1, 3] == channel_index(90, "G") and cmap[3, 3] == channel_index(90, "B")
    assert cmap[2, 3] == channel_index(45, "B")
    assert dofp_layout("90-45-135-0") == dofp_layout("sony")
    assert dofp_layout_name([[0, 45], [135, 90]]) == "0-45-135-90"
    for bad in ("sonyx", [[0, 0], [45, 90]], [[0, 45, 90, 135]]):
        with pytest.raises(InputError):
            dofp_layout(bad)


def test_bayer_map():
    np.testing.assert_array_equal(bayer_channel_map(2, 4), [[0, 1, 0, 1], [1, 2, 1, 2]])


def test_reference_raw_pixel_integrates_its_hr_block():
    # raw pixel (i, j) integrates HR 2i..2i+1: its centre 2i + 0.5 maps to raw coordinate i
    np.testing.assert_allclose(apply_homography(raw_matrix(), np.array([[2 * 3 + 0.5, 2 * 5 + 0.5]])), [[3, 5]])
    # sub-image q=G1 (raw offset (0,1)): pixel (u, v) = raw (2u, 2v+1), centre HR (4u+0.5, 4v+2.5)
    np.testing.assert_allclose(apply_homography(sub_image_matrix(1), np.array([[4 * 2 + 2.5, 4 * 1 + 0.5]])), [[2, 1]])
    np.testing.assert_allclose(apply_homography(sub_image_matrix(2), np.array([[0.5, 2.5]])), [[0, 0]])


def test_registration_error_in_hr_pixels():
    hn = np.stack([np.eye(3)] * 4)
    true = lr_homographies(hn)
    shifted = lr_homographies(np.stack([similarity((0.2, 0.0))] * 4))
    err = registration_error_hr_px(shifted, true, (64, 64))
    np.testing.assert_allclose(err, 0.2, atol=1e-12)


def test_rotation_and_scale_of_a_similarity():
    """Display-CCW ``similarity`` rotations come out negative (measured from +x towards +y, row down)."""
    rot, scale = rotation_and_scale(similarity((1.5, -2.0), rotation_deg=3.0, scale=1.01, center_xy=(40.0, 30.0)))
    assert rot == pytest.approx(-3.0) and scale == pytest.approx(1.01)
    assert rotation_and_scale(np.eye(3)) == (0.0, 1.0)
