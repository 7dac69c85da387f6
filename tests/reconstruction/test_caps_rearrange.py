"""Rearrangement of the 4 RGGB frames into 16 observations (paper 3.1)."""

import numpy as np
import pytest
import torch

from capssim.conventions import LR_IMAGE_CHANNELS, split_bayer
from capssim.errors import InputError
from capssim.reconstruct.model.rearrange import rearrange_raw


def test_split_bayer_sites_and_order():
    raw = np.zeros((4, 4, 6), dtype=np.float32)
    for n in range(4):
        raw[n, 0::2, 0::2] = 10 * n + 0  # R
        raw[n, 0::2, 1::2] = 10 * n + 1  # G1
        raw[n, 1::2, 0::2] = 10 * n + 2  # G2
        raw[n, 1::2, 1::2] = 10 * n + 3  # B
    out = split_bayer(raw)
    assert out.shape == (16, 2, 3)
    for m in range(16):
        n, q = divmod(m, 4)
        assert np.all(out[m] == 10 * n + q)
    # sub-image pixel (u, v) is raw pixel (2u + oy, 2v + ox)
    raw = np.random.default_rng(0).random((4, 8, 8)).astype(np.float32)
    out = split_bayer(raw)
    assert out[4 * 2 + 2][1, 3] == raw[2, 2 * 1 + 1, 2 * 3 + 0]  # aperture 2, G2 at offset (1, 0)


def test_rearrange_channels_weights_and_capture_agree():
    rng = np.random.default_rng(1)
    raw = rng.random((4, 8, 12)).astype(np.float32)
    sat = np.zeros((4, 8, 12), dtype=bool)
    sat[1, 0, 1] = True  # aperture 1, G1 site, sub-image pixel (0, 0)
    obs = rearrange_raw(raw, sat)
    assert obs.images.shape == (16, 4, 6) and obs.images.dtype == torch.float32
    assert obs.channel_of.tolist() == list(LR_IMAGE_CHANNELS)
    assert obs.images_per_channel().tolist() == [1, 2, 1] * 4  # the two G images stay separate
    assert obs.weights[5, 0, 0] == 0 and obs.weights.sum() == obs.weights.numel() - 1
    # same split as Capture.lr_images
    from capssim.captures.capture import Capture

    cap = Capture.__new__(Capture)
    cap.meta = {"geometry": {"raw_height": 8, "raw_width": 12}, "sensor": {"model": "none"}}
    cap.caps_raw = raw
    imgs, _ = cap.lr_images()
    assert np.array_equal(imgs, obs.images.numpy())


@pytest.mark.parametrize("bad", [np.zeros((3, 8, 8), np.float32), np.zeros((4, 7, 8), np.float32),
                                 np.full((4, 8, 8), np.nan, np.float32), np.zeros((4, 8, 8), np.uint16)])
def test_rearrange_rejects_bad_input(bad):
    with pytest.raises(InputError):
        rearrange_raw(bad)
