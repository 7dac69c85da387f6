"""Initialization fusing all 16 observations on the HR grid (the SCSR step)."""

import numpy as np
import pytest
import torch

from capssim.camera.array_geometry import raw_matrix
from capssim.reconstruct.model.init_fusion import fuse_initial_estimate, normalized_convolution, sample_positions, splat
from capssim.reconstruct.model.rearrange import observations_from_capture


def scene(size=64, seed=0):
    from scipy.ndimage import gaussian_filter

    from capssim.stokes.polarization import twelve_from_stokes

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    edges = ((np.sin(2 * np.pi * 5 * xx + 3 * yy) > 0) * 0.25 + (yy > 0.5) * 0.2)
    s0 = np.stack([0.3 + edges * g + 0.1 * gaussian_filter(rng.random((size, size)), 2) for g in (1.0, 0.8, 0.6)])
    dolp = 0.4 * gaussian_filter(rng.random((size, size)), 6) / 0.5
    aop = np.pi * xx
    return twelve_from_stokes(np.stack([s0, s0 * dolp * np.cos(2 * aop), s0 * dolp * np.sin(2 * aop)])).astype(np.float32)


def capture(gt, sigma=0.0, seed=0, **pose):
    from capssim.camera.sensor import make_sensor
    from capssim.simulate import PoseRanges, simulate_capture

    sensor = make_sensor("gaussian", sigma=sigma) if sigma else make_sensor("none")
    return simulate_capture(gt, sensor, seed=seed, pose_ranges=PoseRanges(**pose))


def psnr(a, b):
    return float(np.mean([-10 * np.log10(np.mean((np.clip(a[c], 0, 1) - b[c]) ** 2)) for c in range(a.shape[0])]))


def bicubic_per_image(cap):
    """Per-sub-image bicubic onto the HR grid (what the fusion must beat)."""
    import cv2

    from capssim.conventions import LR_IMAGE_CHANNELS

    lr, _ = cap.lr_images()
    hm = cap.true_lr_homographies()
    out = np.zeros((12, *cap.hr_shape))
    cnt = np.zeros(12)
    for m in range(16):
        out[LR_IMAGE_CHANNELS[m]] += cv2.warpPerspective(lr[m], hm[m], cap.hr_shape[::-1],
                                                         flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                                                         borderMode=cv2.BORDER_REPLICATE)
        cnt[LR_IMAGE_CHANNELS[m]] += 1
    return out / cnt[:, None, None]


def test_sample_positions_of_reference_r_image():
    from capssim.camera.array_geometry import lr_homographies

    hm = lr_homographies(np.stack([np.eye(3)] * 4))
    pos = sample_positions(hm, (4, 5))
    # R sub-image pixel (u, v) integrates HR pixels 4u..4u+1, 4v..4v+1: centre (4v + 0.5, 4u + 0.5)
    assert np.allclose(pos[0, 2, 3], [12.5, 8.5])
    assert np.allclose(pos[3, 0, 0], [2.5, 2.5])  # B site, offset (1, 1)
    assert np.allclose(sample_positions(raw_matrix()[None], (2, 2))[0, 1, 1], [2.5, 2.5])


def test_splat_and_normalized_convolution_reproduce_a_plane():
    pos = torch.as_tensor(np.random.default_rng(0).uniform(0, 31, (1, 40, 40, 2)), dtype=torch.float64)
    vals = 0.2 + 0.01 * pos[..., 0] + 0.02 * pos[..., 1]
    tgt = torch.zeros(1, dtype=torch.int64)
    num = splat(vals, pos, tgt, 1, (32, 32))
    den = splat(torch.ones_like(vals), pos, tgt, 1, (32, 32))
    est = normalized_convolution(num, den, 1.0)
    yy, xx = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    plane = 0.2 + 0.01 * xx + 0.02 * yy
    # zeroth-order normalized convolution: exact for constants, small bias on slopes
    assert torch.allclose(est[0, 4:-4, 4:-4], plane[4:-4, 4:-4].double(), atol=1e-2)
    const = normalized_convolution(splat(torch.full_like(vals, 0.7), pos, tgt, 1, (32, 32)), den, 1.0)
    assert torch.allclose(const, torch.full_like(const, 0.7))


def test_fusion_beats_per_image_bicubic():
    gt = scene(64)
    cap = capture(gt, sigma=0.005)
    obs = observations_from_capture(cap)
    init = fuse_initial_estimate(obs, cap.true_lr_homographies(), cap.hr_shape).numpy()
    assert init.shape == (12, 64, 64) and np.isfinite(init).all()
    m = (slice(None), slice(4, -4), slice(4, -4))
    fused, bicubic = psnr(init[m], gt[m]), psnr(bicubic_per_image(cap)[m], gt[m])
    assert fused > bicubic + 1.0, (fused, bicubic)


def test_fusion_hard_cases():
    flat = np.full((12, 32, 32), 0.4, np.float32)
    cap = capture(flat)
    init = fuse_initial_estimate(observations_from_capture(cap), cap.true_lr_homographies(), cap.hr_shape)
    assert torch.allclose(init, torch.full_like(init, 0.4), atol=1e-5)
    dark = scene(32) * 1e-4
    cap = capture(dark)
    init = fuse_initial_estimate(observations_from_capture(cap), cap.true_lr_homographies(), cap.hr_shape)
    assert torch.isfinite(init).all() and float(init.abs().max()) < 1e-3
    # every observation saturated / weight 0: still finite
    obs = observations_from_capture(cap)
    obs.weights.zero_()
    init = fuse_initial_estimate(obs, cap.true_lr_homographies(), cap.hr_shape)
    assert torch.isfinite(init).all()


def _normalized_convolution_whole_image(num, den, sigma, min_density=1e-3, max_doublings=6):
    """The definition: every doubled kernel applied to the whole image."""
    from capssim.reconstruct.filters import gaussian_blur

    out, missing, s = None, None, sigma
    for _ in range(max_doublings + 1):
        bn, bd = gaussian_blur(num, s), gaussian_blur(den, s)
        est, ok = bn / bd.clamp(min=1e-12), bd > min_density
        out = torch.where(ok, est, torch.zeros_like(est)) if out is None else torch.where(missing & ok, est, out)
        missing = ~ok if missing is None else missing & ~ok
        if not bool(missing.any()):
            break
        s *= 2
    return out, missing


@pytest.mark.parametrize("hole", [(0, 12), (30, 64), (0, 64)])
def test_normalized_convolution_fills_holes_as_the_whole_image_doubling(hole):
    gen = torch.Generator().manual_seed(3)
    den = (torch.rand(3, 64, 48, generator=gen, dtype=torch.float64) < 0.3).double()
    den[:, hole[0]:hole[1], :20] = 0  # a hole, a band, or whole planes' left part
    den[2, :, :] = 0 if hole == (0, 64) else den[2]  # one plane without any sample
    num = den * torch.rand(3, 64, 48, generator=gen, dtype=torch.float64)
    expected, missing = _normalized_convolution_whole_image(num, den, 1.5)
    got = normalized_convolution(num, den, 1.5)
    keep = ~missing
    torch.testing.assert_close(got[keep], expected[keep], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("sigma", [2.0, 8.0])
def test_blur_at_holes_equals_the_whole_image_blur(sigma):
    from capssim.reconstruct.filters import gaussian_blur
    from capssim.reconstruct.model.init_fusion import _gaussian_blur_at

    gen = torch.Generator().manual_seed(5)
    x = torch.rand(12, 120, 170, generator=gen)
    corners = torch.tensor([[0, 0], [2, 7], [119, 169], [60, 1], [5, 160], [118, 3]])  # every quadrant, the borders
    cluster = torch.stack([torch.randint(0, 30, (200,), generator=gen), torch.randint(90, 130, (200,), generator=gen)], 1)
    for pixels in (corners, cluster):
        at = _gaussian_blur_at(x, pixels, sigma)
        assert torch.equal(at, gaussian_blur(x, sigma)[:, pixels[:, 0], pixels[:, 1]])
    everywhere = torch.stack(torch.meshgrid(torch.arange(0, 120, 3), torch.arange(0, 170, 3), indexing="ij"), -1)
    assert _gaussian_blur_at(x, everywhere.reshape(-1, 2), 20.0) is None  # boxes past the image: blur the image
