"""The four apertures' demosaicked, registered images fused: a shared intensity and each analyzer's own detail.

Each aperture's frame is demosaicked on its own and warped onto the HR grid by bicubic resampling, as in
``caps-naive`` (``B_n``, ``(4, Ho, Wo)`` per colour). Since ``I_0 + I_90 = I_45 + I_135 = S0``, their mean
``m = S0 / 2`` samples the intensity at the apertures' four sub-pixel phases and the polarization cancels in it.
Each analyzer's image is ``out_n = m' + L(D_n) + w (D_n - L(D_n))`` with ``D_n = B_n - m``:

- ``L`` a Gaussian of std :data:`POL_SIGMA` HR px: the smooth part of the polarization is kept everywhere;
- the detail ``D_n - L(D_n)`` is kept with the weight ``w = max(e_d - LAMBDA N sigma^2, 0) / (e_d + ALPHA e_s)``
  (a Wiener gain with over-subtraction), where ``e_d`` is the local energy (Gaussian :data:`ENERGY_SIGMA`) of the
  four analyzers' detail, ``N sigma^2`` its expected energy from the sensor noise alone (:data:`DETAIL_NOISE_ENERGY`,
  measured for Menon demosaicking and bicubic resampling, ``tests/reconstruction/test_array_kr.py``), and ``e_s``
  the intensity's detail that both analyzer pairs agree on: the local mean of the product of the details of
  ``(B_0 + B_90) / 2`` and ``(B_45 + B_135) / 2``, two independent estimates of ``S0 / 2`` (clamped at 0). Their
  noise and their own interpolation errors are independent, so the product keeps only shared intensity edges; a
  pattern only in the polarization (the polarization star), whose interpolation error differs between the pairs,
  does not count as intensity. Detail of the analyzers that the intensity does not explain is kept; detail that
  comes with intensity edges (each aperture's own interpolation error, aliasing) or at the noise level is dropped;
- ``m' = m + SHARPEN c (m - G_1 m)`` with ``c = ALPHA e_s / (e_d + ALPHA e_s)``: the intensity sharpened by an
  unsharp mask where its shared detail leads the analyzers' detail (``1 - w`` without the noise term, so that the
  noise, which lowers ``w``, is not sharpened).

Where an aperture does not see a pixel (out of its view, or within two raw pixels (the bicubic support) of a saturated sample) its weight
is zero: its image there is ``B_{n+1} + B_{n+3} - B_{n+2}`` (``I_0 + I_90 = I_45 + I_135``) from the others.
The HR grid is fused in chunks of rows with a halo of :data:`HALO` rows (the same result as one piece)
and the colours one at a time, so the working memory is bounded on any frame. Constants chosen on the ``dev`` suite (docs/guides/methods.md).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..model.aperture_demosaic import demosaicked_frames, flat_corrected_raw, sampling_grid

__all__ = ["ALPHA", "DETAIL_NOISE_ENERGY", "ENERGY_SIGMA", "LAMBDA", "POL_SIGMA", "SHARPEN", "demosaicked_fusion",
           "fuse_apertures", "gaussian", "known_noise_sigma", "robust_noise_sigma", "shared_intensity_energy",
           "unseen_pixels", "visibility"]

POL_SIGMA = 2.0
ENERGY_SIGMA = 1.5
ALPHA = 1.0
#: the expected local energy of the four analyzers' detail ``sum_n (D_n - L(D_n))^2`` of pure sensor noise, in units
#: of the raw noise variance (Menon demosaicking, bicubic x2 resampling; measured on white noise, checked by a test)
DETAIL_NOISE_ENERGY = 1.35
#: the over-subtraction of the detail's noise energy (1: the plain Wiener gain); 2 chosen on the dev suite
#: (+0.05 dB PSNR and +0.28 dB DoLP over 1, with the earlier sharpening; docs/guides/methods.md)
LAMBDA = 2.0
SHARPEN = 0.5
#: HR pixels fused per chunk of rows (about 400 bytes each while it is processed)
CHUNK_PIXELS = 1 << 20
#: HR rows read on each side of a chunk: deeper than the filters' chain (3 POL_SIGMA + 3 ENERGY_SIGMA = 10.5)
HALO = 16


def gaussian(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur (replicate border) of ``(..., H, W)``."""
    if sigma <= 0:
        return image
    r = int(np.ceil(3 * sigma))
    t = torch.arange(-r, r + 1, dtype=image.dtype, device=image.device)
    k = torch.exp(-t ** 2 / (2 * sigma * sigma))
    k = k / k.sum()
    shape = image.shape
    x = image.reshape(-1, 1, *shape[-2:])
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return x.reshape(shape)


def _warp(images: torch.Tensor, raw_h: np.ndarray, rows: tuple[int, int], width: int, mode: str, padding: str):
    """``(4, C, H, W)`` resampled onto the HR rows ``[r0, r1)`` (``(4, C, r1 - r0, width)``; aperture n reads
    ``raw_h[n] (x, y, 1)``)."""
    shift = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, float(rows[0])], [0.0, 0.0, 1.0]])
    grid = sampling_grid(np.asarray(raw_h, dtype=np.float64) @ shift, (rows[1] - rows[0], width),
                         tuple(images.shape[-2:]), images.device)
    return F.grid_sample(images, grid, mode=mode, padding_mode=padding, align_corners=True)


def visibility(usable: torch.Tensor, raw_h: np.ndarray, hr_shape: tuple[int, int],
               rows: tuple[int, int] | None = None) -> torch.Tensor:
    """``(4, r1 - r0, Wo)`` float 1/0 (all rows by default): HR pixels whose source in aperture n is in view and
    more than two raw pixels away from any unusable (saturated) sample; ``usable`` ``(4, H, W)`` bool."""
    bad = (~usable.bool()).to(torch.float32)[:, None]
    near_bad = F.max_pool2d(bad, 5, stride=1, padding=2)  # the bicubic support: two raw pixels
    seen = _warp(1.0 - near_bad, raw_h, rows or (0, hr_shape[0]), hr_shape[1], "bilinear", "zeros")[:, 0]
    return (seen >= 0.5).to(torch.float32)


def robust_noise_sigma(raw: torch.Tensor) -> float:
    """The raw noise std from the 10 % quantile of the absolute Laplacian of the frames' ``(4, H, W)`` Bayer
    sub-images (robust to texture, unlike the mean: ``q10 |I * L| / (0.1257 * 6)``); 0 for sub-images under 3x3."""
    h2, w2 = raw.shape[1] // 2 * 2, raw.shape[2] // 2 * 2
    if min(h2, w2) < 6:
        return 0.0
    subs = raw[:, :h2, :w2].reshape(4, h2 // 2, 2, w2 // 2, 2).permute(0, 2, 4, 1, 3).reshape(16, 1, h2 // 2, w2 // 2)
    lap = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], device=raw.device)
    response = F.conv2d(subs.to(torch.float32), lap.view(1, 1, 3, 3)).abs().reshape(-1)
    if response.numel() > 1 << 24:  # quantile's limit: a strided subset
        response = response[:: response.numel() // (1 << 24) + 1]
    return float(torch.quantile(response, 0.1)) / (0.1257 * 6.0)


def unseen_pixels(usable: torch.Tensor, raw_h: np.ndarray, hr_shape: tuple[int, int]) -> np.ndarray:
    """``(12, Ho, Wo)`` bool, channel ``3 n + k``: the HR pixels aperture n does not see (:func:`visibility` false),
    computed in chunks of rows (the record's ``unobserved``, without a full-frame sampling grid)."""
    ho, wo = int(hr_shape[0]), int(hr_shape[1])
    out = np.empty((4, ho, wo), dtype=bool)
    step = max(1, CHUNK_PIXELS // max(wo, 1))
    for r0 in range(0, ho, step):
        r1 = min(ho, r0 + step)
        out[:, r0:r1] = (visibility(usable, raw_h, (ho, wo), (r0, r1)) < 0.5).cpu().numpy()
    return np.repeat(out, 3, axis=0)


def shared_intensity_energy(b: torch.Tensor) -> torch.Tensor:
    """``(Ho, Wo)``: the local energy of the intensity detail shared by the two analyzer pairs of ``b``
    ``(4, Ho, Wo)`` (polarizers 0, 45, 90, 135 deg): the Gaussian (:data:`ENERGY_SIGMA`) local mean of the product of
    the details (minus a Gaussian of :data:`POL_SIGMA`) of ``(b_0 + b_2) / 2`` and ``(b_1 + b_3) / 2``, clamped at 0.
    Independent noise and interpolation errors of the two pairs average out of the product."""
    pair_a = 0.5 * (b[0] + b[2])
    pair_b = 0.5 * (b[1] + b[3])
    product = (pair_a - gaussian(pair_a, POL_SIGMA)) * (pair_b - gaussian(pair_b, POL_SIGMA))
    return gaussian(product, ENERGY_SIGMA).clamp_min(0.0)


def _fuse_colour(b: torch.Tensor, vis: torch.Tensor, sigma_n: float, detail: bool, sharpen: float) -> torch.Tensor:
    """One colour: ``b`` ``(4, Ho, Wo)`` registered aperture images -> the four analyzers' images."""
    other = b.roll(-1, 0) + b.roll(1, 0) - b.roll(2, 0)  # I_n = I_{n+1} + I_{n+3} - I_{n+2}
    b = vis * b + (1.0 - vis) * other
    m = b.mean(0)
    d = b - m
    e_s = shared_intensity_energy(b)
    del b, other
    d_low = gaussian(d, POL_SIGMA)
    d -= d_low  # the analyzers' detail
    e_d = gaussian((d * d).sum(0), ENERGY_SIGMA)
    total = e_d + ALPHA * e_s + 1e-12
    shared = ALPHA * e_s / total  # 1 - w without the noise term
    if detail:
        w = (e_d - LAMBDA * DETAIL_NOISE_ENERGY * sigma_n ** 2).clamp_min(0.0) / total
    else:
        w = torch.zeros_like(m)
    del e_s, e_d, total
    m = m + sharpen * shared * (m - gaussian(m, 1.0))
    d *= w
    d += d_low
    d += m
    return d


def fuse_apertures(rgb: torch.Tensor, usable: torch.Tensor, raw_h: np.ndarray, hr_shape: tuple[int, int],
                   sigma_n: float, *, detail: bool = True, sharpen: float = SHARPEN) -> torch.Tensor:
    """``rgb`` ``(4, 3, H, W)`` demosaicked frames, ``usable`` ``(4, H, W)`` bool (false: saturated or masked),
    ``raw_h`` ``(4, 3, 3)`` HR -> raw maps, ``sigma_n`` the raw noise std: ``(4, 3, Ho, Wo)`` float32.
    ``detail=False`` keeps only the smooth polarization; ``sharpen=0`` leaves the intensity unsharpened."""
    ho, wo = int(hr_shape[0]), int(hr_shape[1])
    out = rgb.new_empty((4, 3, ho, wo))
    step = max(1, CHUNK_PIXELS // max(wo, 1))
    for r0 in range(0, ho, step):  # chunks of rows with a halo: the same result as one piece
        r1 = min(ho, r0 + step)
        a, b = max(0, r0 - HALO), min(ho, r1 + HALO)
        vis = visibility(usable, raw_h, (ho, wo), (a, b))
        for k in range(3):
            warped = _warp(rgb[:, k:k + 1], raw_h, (a, b), wo, "bicubic", "border")[:, 0]
            out[:, k, r0:r1] = _fuse_colour(warped, vis, float(sigma_n), detail, float(sharpen))[:, r0 - a:r1 - a]
    return out


def known_noise_sigma(capture) -> float | None:
    """The Gaussian noise std of the capture's sensor model when its set-up states one (a calibrated camera knows
    its noise; a single small frame of dense texture, e.g. a Siemens star, cannot tell noise from texture)."""
    try:
        sigma = getattr(capture.setup.sensor, "sigma", None)
    except (AttributeError, ValueError, KeyError):
        return None
    return float(sigma) if sigma is not None and capture.setup.noise == "gaussian" else None


def demosaicked_fusion(capture, context, geometry, *, detail: bool = True, sharpen: float = SHARPEN,
                       held_out=None) -> tuple[torch.Tensor, float]:
    """``array-kr``'s default image of a capture under ``geometry``: each aperture's frame demosaicked (Menon 2007,
    flat field divided out with a calibration) and fused (:func:`fuse_apertures`); ``(4, 3, Ho, Wo)`` float32 on the
    context device and the raw noise std used (the sensor's when its set-up states one, else a robust estimate).
    ``held_out`` ``(4, H, W)`` bool: raw pixels it must not see (filled from their neighbours, weight 0)."""
    rgb = demosaicked_frames(capture, context, "menon2007", held_out=held_out)
    usable = ~np.asarray(capture.caps_saturated(), bool)
    if held_out is not None:
        usable &= ~np.asarray(held_out, bool)
    sigma_n = known_noise_sigma(capture)
    if sigma_n is None:
        raw, _ = flat_corrected_raw(capture, context)
        sigma_n = robust_noise_sigma(torch.as_tensor(np.asarray(raw, dtype=np.float32)))
    image = fuse_apertures(rgb, torch.as_tensor(usable, device=context.device), geometry.raw_homographies,
                           geometry.hr_shape, sigma_n, detail=detail, sharpen=sharpen)
    return image, float(sigma_n)
