"""Menon 2007 (DDFAPD) Bayer demosaicking in torch: colour-demosaicing's result to the bit, batched, any size."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from capssim.reconstruct.dofp.menon2007 import menon2007_demosaic
from capssim.reconstruct.model.aperture_demosaic import bayer_demosaic_function, demosaic_apertures

SHAPES = [(64, 80), (7, 9), (2, 2), (3, 5), (4, 3), (33, 2)]


def _frames(shape, seed=0):
    rng = np.random.default_rng(seed)
    noise = rng.random(shape)
    quantized = np.round(rng.random(shape) * 255) / 255  # ties in the decision are frequent
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    smooth = 0.5 + 0.3 * np.sin(xx / 3.0) * np.cos(yy / 5.0)
    edge = np.where(xx + 0.3 * yy > shape[1] / 2, 0.9, 0.05)
    return np.stack([noise, quantized, smooth, edge])


@pytest.mark.parametrize("shape", SHAPES)
def test_reproduces_colour_demosaicing_to_the_bit(shape):
    cd = pytest.importorskip("colour_demosaicing")
    frames = _frames(shape)
    ours = menon2007_demosaic(torch.from_numpy(frames)).numpy()
    for frame, rgb in zip(frames, ours):
        reference = cd.demosaicing_CFA_Bayer_Menon2007(frame, "RGGB")
        np.testing.assert_array_equal(np.moveaxis(rgb, 0, -1), reference)


def test_without_the_refining_step_too():
    cd = pytest.importorskip("colour_demosaicing")
    frame = _frames((16, 20), seed=3)[0]
    ours = menon2007_demosaic(torch.from_numpy(frame[None]), refine=False)[0].numpy()
    reference = cd.demosaicing_CFA_Bayer_Menon2007(frame, "RGGB", refining_step=False)
    np.testing.assert_array_equal(np.moveaxis(ours, 0, -1), reference)


def test_exact_on_constant_and_sampled_sites():
    frame = torch.full((1, 12, 10), 0.37, dtype=torch.float64)
    rgb = menon2007_demosaic(frame)
    assert torch.allclose(rgb, torch.full_like(rgb, 0.37), atol=1e-15)
    raw = torch.from_numpy(_frames((12, 10))[0])[None]
    rgb = menon2007_demosaic(raw, refine=False)[0]
    assert torch.equal(rgb[0, 0::2, 0::2], raw[0, 0::2, 0::2])  # red sites keep their sample
    assert torch.equal(rgb[2, 1::2, 1::2], raw[0, 1::2, 1::2])  # blue sites keep theirs


def test_float32_follows_float64():
    frames = torch.from_numpy(_frames((32, 32), seed=1))
    wide = menon2007_demosaic(frames)
    narrow = menon2007_demosaic(frames.to(torch.float32))
    assert narrow.dtype == torch.float32
    assert float((narrow.double() - wide).abs().max()) < 1e-5


def test_bad_shape_is_refused():
    with pytest.raises(ValueError, match=r"\(N, H, W\)"):
        menon2007_demosaic(torch.zeros(8, 8))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_same_code_on_cuda():
    frames = torch.from_numpy(_frames((40, 40), seed=2))
    on_gpu = menon2007_demosaic(frames.cuda()).cpu()
    assert float((on_gpu - menon2007_demosaic(frames)).abs().max()) < 1e-12


def test_demosaic_apertures_uses_it_without_importing_colour():
    """caps-naive's, caps-plus's start's and array-kr's demosaicking no longer imports colour-science."""
    code = ("import sys, numpy as np\n"
            "from capssim.reconstruct.model.aperture_demosaic import demosaic_apertures\n"
            "demosaic_apertures(np.random.default_rng(0).random((4, 24, 24)))\n"
            "print(any(m.split('.')[0] in ('colour', 'colour_demosaicing') for m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stdout + out.stderr


def test_demosaic_apertures_matches_the_per_frame_function():
    raw = _frames((20, 18), seed=4).astype(np.float32)
    batched = demosaic_apertures(raw, bayer_method="menon2007")
    _, frame_fn = bayer_demosaic_function("menon2007")
    pad = 6
    for frame, rgb in zip(raw, batched):
        padded = np.pad(frame.astype(np.float64), pad, mode="reflect")
        single = frame_fn(padded[None])[0][:, pad:-pad, pad:-pad]
        np.testing.assert_array_equal(rgb, np.clip(single, 0, 1).astype(np.float32))
