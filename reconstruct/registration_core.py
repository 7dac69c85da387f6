"""The image-registration engine behind :mod:`reconstruct.registration` (device-agnostic torch).

It registers a batch of *moving* images to one *reference* image whose intensities may
differ from theirs in a spatially varying way (other polarizer angles, other colours):

* **Motion models** (:data:`MOTION_MODELS`), parameterised in pixels of displacement at the
  image radius, so every parameter has the same scale for the optimiser.
* **Interpolation**: an interpolating cubic B-spline (:func:`spline_coefficients`,
  :func:`spline_sample`). torch's ``bicubic`` (Keys, a = -0.75) is *not* used: it misplaces a
  linear ramp by up to 0.047 px depending on the sub-pixel phase, a bias larger than the
  registration target.
* **Coarse stage**: phase correlation of gradient magnitudes (sign-invariant), whose best
  peaks and the zero shift are tried as candidates and judged by the refinement criterion
  at the coarsest pyramid level.
* **Refinement** on a 2x2-average pyramid, minimised with L-BFGS (strong Wolfe) through
  autograd, all moving images in one batch. Two terms:

  - *local correlation* (per moving image): in each ``(2r+1)^2`` window the warped moving
    image is fitted by ``a * reference + b``; the term is the unexplained part
    ``V0 * (1 - R^2)`` with ``R^2 = sum cov^2/var_ref / sum var_mov`` over the windows
    (``V0``: the mean moving variance, fixed per level). Local gain and offset make it
    indifferent to polarizer angle and colour, even to locally inverted contrast.
  - *Stokes consistency* (optional, for the three non-reference polarizer images in the
    order 45, 90, 135 deg against 0 deg): ``I0 + I90 - I45 - I135 = 0`` holds for any
    scene (both orthogonal pairs sum to S0; any extinction ratio, colour weighting or
    common linear blur), so its mean square vanishes at the true warps. It removes the
    bias that polarization texture puts into the local correlation, in the directions it
    constrains (S0 texture fixes ``d90 - d45 - d135``, S1 texture ``d90``, S2 texture
    ``d45 - d135``).

* **Stokes-subspace refinement** (optional, ``stokes_subspace_std > 0``): the local-correlation
  term is biased wherever DoLP/AoP vary (the analyzer images then differ in shape, not only in
  gain), while the Stokes term alone is unbiased for physically consistent data but does not fix
  every direction. A last Gauss-Newton stage on the Stokes residual alone moves the parameters
  only along the directions it determines to within ``stokes_subspace_std`` px (noise-predicted).
  It assumes ``I0 + I90 = I45 + I135`` holds in the data with equal aperture gains: true for
  rendered scenes and for ground truths that obey it, not for ground truths taken as four
  sequential rotating-polarizer shots (qiu-kettle breaks it by 0.9 % of S0 and gets worse).

All coordinates are ``(x=col, y=row)`` with pixel centres on integers.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import InputError, UnknownNameError
from capssim.reconstruct.dofp_common import box_sum as dofp_box_sum

log = logging.getLogger(__name__)

#: motion models and their number of parameters
MOTION_MODELS: dict[str, int] = {"translation": 2, "euclidean": 3, "similarity": 4, "affine": 6, "homography": 8}


# -- motion models --------------------------------------------------------------------------------
def params_to_matrices(p: torch.Tensor, model: str, centre: tuple[float, float], radius: float) -> torch.Tensor:
    """``(B, P)`` parameters -> ``(B, 3, 3)`` reference -> moving pixel matrices.

    In normalised coordinates ``X = (x - centre) / radius`` the map is
    ``X' = (A X + t) / (g . X + 1)``; the parameters are ``radius`` times the deviations from the
    identity, i.e. pixels of displacement at distance ``radius``: translation ``(tx, ty)``;
    euclidean adds the rotation ``theta``; similarity ``(a, b)`` of ``A = I + [[a, -b], [b, a]]``;
    affine the four entries of ``A - I``; homography also ``(g1, g2)``.
    """
    if model not in MOTION_MODELS:
        raise UnknownNameError("motion model", model, list(MOTION_MODELS))
    b = p.shape[0]
    one = torch.ones(b, dtype=p.dtype, device=p.device)
    zero = torch.zeros_like(one)
    q = p / radius
    tx, ty = q[:, 0], q[:, 1]
    if model == "translation":
        a11, a12, a21, a22 = one, zero, zero, one
    elif model == "euclidean":
        c, s = torch.cos(q[:, 2]), torch.sin(q[:, 2])
        a11, a12, a21, a22 = c, -s, s, c
    elif model == "similarity":
        a11, a12, a21, a22 = 1 + q[:, 2], -q[:, 3], q[:, 3], 1 + q[:, 2]
    else:
        a11, a12, a21, a22 = 1 + q[:, 2], q[:, 3], q[:, 4], 1 + q[:, 5]
    g1, g2 = (q[:, 6], q[:, 7]) if model == "homography" else (zero, zero)
    normalized = torch.stack([torch.stack([a11, a12, tx], -1), torch.stack([a21, a22, ty], -1),
                              torch.stack([g1, g2, one], -1)], -2)
    cx, cy = centre
    to_n = torch.tensor([[1 / radius, 0, -cx / radius], [0, 1 / radius, -cy / radius], [0, 0, 1]],
                        dtype=p.dtype, device=p.device)
    from_n = torch.tensor([[radius, 0, cx], [0, radius, cy], [0, 0, 1]], dtype=p.dtype, device=p.device)
    return from_n @ normalized @ to_n


# -- cubic B-spline interpolation ----------------------------------------------------------------
_SPLINE_POLE = math.sqrt(3.0) - 2.0


def spline_coefficients(img: torch.Tensor, *, taps: int = 12) -> torch.Tensor:
    """``(B, H, W)`` samples -> cubic B-spline coefficients (mirror boundary).

    The inverse of the sampled B-spline ``[1 4 1] / 6`` has the impulse response
    ``sqrt(3) z^|k|``, ``z = sqrt(3) - 2`` (Unser, "Splines: a perfect fit for signal and image
    processing", IEEE SPM 1999); applied separably, truncated at ``|k| <= taps``
    (``|z|^12 < 2e-7``) and renormalised so constants stay exact on tiny images.
    """
    k = torch.arange(-taps, taps + 1, dtype=img.dtype, device=img.device)
    h = math.sqrt(3.0) * _SPLINE_POLE ** k.abs()
    x = img[:, None]
    pad_w, pad_h = min(taps, img.shape[-1] - 1), min(taps, img.shape[-2] - 1)
    if pad_w > 0:
        kw = h[taps - pad_w: taps + pad_w + 1]
        x = F.conv2d(F.pad(x, (pad_w, pad_w, 0, 0), mode="reflect"), (kw / kw.sum())[None, None, None, :])
    if pad_h > 0:
        kh = h[taps - pad_h: taps + pad_h + 1]
        x = F.conv2d(F.pad(x, (0, 0, pad_h, pad_h), mode="reflect"), (kh / kh.sum())[None, None, :, None])
    return x[:, 0]


def spline_sample(coeffs: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Evaluate the cubic spline of ``coeffs`` ``(B, H, W)`` at ``coords`` ``(B, ..., 2)`` (x=col, y=row).

    Differentiable in ``coords``. The four B-spline weights of an axis are folded into two
    bilinear fetches (Sigg & Hadwiger, "Fast third-order texture filtering", GPU Gems 2,
    2005), so a 2-D evaluation is four bilinear ``grid_sample`` taps. The border is mirrored.
    The interpolating cubic spline reproduces polynomials up to degree 3: no phase-dependent
    shift bias.
    """
    b, hh, ww = coeffs.shape
    out_shape = coords.shape[:-1]
    xy = coords.reshape(b, 1, -1, 2)

    def fold(t):
        t0 = torch.floor(t.detach())
        f = t - t0
        w0 = (1 - f) ** 3 / 6
        w1 = 2.0 / 3.0 - f * f + 0.5 * f ** 3
        w3 = f ** 3 / 6
        w2 = 1.0 - w0 - w1 - w3
        g0, g1 = w0 + w1, w2 + w3
        return (t0 - 1 + w1 / g0, t0 + 1 + w3 / g1), (g0, g1)

    (x0, x1), (gx0, gx1) = fold(xy[..., 0])
    (y0, y1), (gy0, gy1) = fold(xy[..., 1])
    sx, sy = 2.0 / max(ww - 1, 1), 2.0 / max(hh - 1, 1)
    gx = torch.cat([x0, x1, x0, x1], 1) * sx - 1
    gy = torch.cat([y0, y0, y1, y1], 1) * sy - 1
    taps = F.grid_sample(coeffs[:, None], torch.stack([gx, gy], -1), mode="bilinear", padding_mode="reflection",
                         align_corners=True)[:, 0]  # (B, 4, N)
    gx0, gx1, gy0, gy1 = gx0[:, 0], gx1[:, 0], gy0[:, 0], gy1[:, 0]
    out = gy0 * (gx0 * taps[:, 0] + gx1 * taps[:, 1]) + gy1 * (gx0 * taps[:, 2] + gx1 * taps[:, 3])
    return out.reshape(out_shape)


# -- small image helpers ----------------------------------------------------------------------------
def box_sum(x: torch.Tensor, radius: int) -> torch.Tensor:
    """``(..., H, W)`` sums over ``(2r+1)^2`` windows, zero padded (exact pairwise sums,
    :func:`reconstruct.dofp_common.box_sum`: about 2 log2(2r+1) additions per pixel, and so
    1.3-4x faster than ``avg_pool2d`` forward and backward at r = 3)."""
    if radius <= 0:
        return x
    return dofp_box_sum(x, radius, radius)


def noise_sigma(img: torch.Tensor) -> torch.Tensor:
    """Per-image white-noise std ``(B,)`` of ``(B, H, W)``: Immerkaer's Laplacian-difference
    operator (CVIU 1996) with a median (edge-robust) instead of the mean absolute value."""
    if min(img.shape[-2:]) < 3:
        return img.new_zeros(img.shape[0])
    k = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], dtype=img.dtype, device=img.device)
    r = F.conv2d(img[:, None], k[None, None])[:, 0]
    return r.abs().flatten(1).median(dim=1).values / (0.6745 * 6.0)


def gradient_magnitude(img: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` central-difference gradient magnitude (replicate border)."""
    p = F.pad(img[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = p[:, 1:-1, 2:] - p[:, 1:-1, :-2]
    gy = p[:, 2:, 1:-1] - p[:, :-2, 1:-1]
    return torch.sqrt(gx * gx + gy * gy)


def gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """``(B, H, W)`` separable Gaussian blur, replicate border."""
    if sigma <= 0:
        return img
    rad = max(1, int(math.ceil(3 * sigma)))
    g = torch.exp(-0.5 * (torch.arange(-rad, rad + 1, dtype=img.dtype, device=img.device) / sigma) ** 2)
    g = g / g.sum()
    x = F.conv2d(F.pad(img[:, None], (rad, rad, 0, 0), mode="replicate"), g[None, None, None, :])
    x = F.conv2d(F.pad(x, (0, 0, rad, rad), mode="replicate"), g[None, None, :, None])
    return x[:, 0]


def phase_correlation_peaks(ref: torch.Tensor, mov: torch.Tensor, *, peaks: int = 3
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate translations ``(B, K, 2)`` (x, y) with ``mov(p + t) ~ ref(p)``, and peak heights ``(B, K)``.

    ``ref`` ``(H, W)``, ``mov`` ``(B, H, W)``. Hann-windowed whitened cross-power spectrum;
    the ``K`` highest local maxima, each refined by a parabola through its neighbours.
    Shifts are searched within +-H/4, +-W/4.
    """
    hh, ww = ref.shape
    win = torch.outer(torch.hann_window(hh, periodic=False, dtype=ref.dtype, device=ref.device),
                      torch.hann_window(ww, periodic=False, dtype=ref.dtype, device=ref.device))
    fr = torch.fft.rfft2((ref - ref.mean()) * win)
    fm = torch.fft.rfft2((mov - mov.mean(dim=(-2, -1), keepdim=True)) * win)
    cross = fm * fr.conj()
    mag = cross.abs()
    cross = cross / (mag + 1e-6 * mag.amax(dim=(-2, -1), keepdim=True) + 1e-300)
    corr = torch.fft.irfft2(cross, s=(hh, ww))  # (B, H, W), peak at the shift (wrapped)
    corr = torch.fft.fftshift(corr, dim=(-2, -1))
    cy, cx = hh // 2, ww // 2
    ys = torch.arange(hh, device=ref.device)[:, None] - cy
    xs = torch.arange(ww, device=ref.device)[None, :] - cx
    window = (ys.abs() <= max(1, hh // 4)) & (xs.abs() <= max(1, ww // 4))
    local_max = corr == F.max_pool2d(F.pad(corr[:, None], (1, 1, 1, 1), mode="circular"), 3, stride=1)[:, 0]
    score = torch.where(local_max & window, corr, torch.full_like(corr, -math.inf))
    k = min(peaks, hh * ww)
    top, idx = score.flatten(1).topk(k, dim=1)
    py, px = idx // ww, idx % ww
    bi = torch.arange(corr.shape[0], device=ref.device)[:, None].expand_as(py)

    def at(dy, dx):
        return corr[bi, (py + dy) % hh, (px + dx) % ww]

    c0 = at(0, 0)
    offs = []
    for pos, neg in ((at(0, 1), at(0, -1)), (at(1, 0), at(-1, 0))):
        den = pos - 2 * c0 + neg
        off = torch.where(den.abs() > 1e-12, 0.5 * (neg - pos) / den.where(den.abs() > 1e-12, torch.ones_like(den)),
                          torch.zeros_like(den))
        offs.append(off.clamp(-0.5, 0.5))
    shift = torch.stack([(px - cx).to(ref.dtype) + offs[0], (py - cy).to(ref.dtype) + offs[1]], -1)
    shift = torch.where(torch.isfinite(top)[..., None], shift, torch.zeros_like(shift))
    return shift, top


# -- the criterion at one pyramid level ------------------------------------------------------------------
class LevelCriterion:
    """Registration criterion at one pyramid level (see the module docstring).

    Level pixel ``p`` stands for full-resolution coordinate ``s p + (s - 1) / 2`` (``s = 2^level``,
    2x2 average pooling). The motion parameters are always full-resolution ones.
    """

    def __init__(self, ref, moving, ref_valid, moving_valid, *, scale: int, window_radius: int, model: str,
                 centre, radius: float, eps: float, stokes_weight: float = 0.0, margin: float = 1.5,
                 robust_power: float = 0.0):
        self.ref = ref
        self.robust_power = robust_power
        self.coef = spline_coefficients(moving)
        self.ref_valid = ref_valid
        self.moving_valid = moving_valid
        self.scale = scale
        self.r = window_radius
        self.model, self.centre, self.radius = model, centre, radius
        self.eps = eps
        self.stokes_weight = stokes_weight
        self.margin = margin
        hh, ww = ref.shape
        self.shape = (hh, ww)
        ys, xs = torch.meshgrid(torch.arange(hh, dtype=ref.dtype, device=ref.device),
                                torch.arange(ww, dtype=ref.dtype, device=ref.device), indexing="ij")
        off = (scale - 1) / 2.0
        self.pts = torch.stack([xs.flatten() * scale + off, ys.flatten() * scale + off, torch.ones_like(xs.flatten())])
        self.weights = None
        self.norm = None

    def coords(self, p: torch.Tensor) -> torch.Tensor:
        """Moving-image level coordinates ``(B, H, W, 2)`` of every reference level pixel."""
        g = params_to_matrices(p, self.model, self.centre, self.radius)
        q = g @ self.pts
        off = (self.scale - 1) / 2.0
        xy = (q[:, :2] / q[:, 2:3] - off) / self.scale
        return xy.transpose(1, 2).reshape(p.shape[0], *self.shape, 2)

    def fix_weights(self, p: torch.Tensor) -> None:
        """Freeze the pixel weights at ``p``: valid reference pixel, inside the moving image, not saturated there."""
        with torch.no_grad():
            c = self.coords(p)
            hh, ww = self.shape
            m = self.margin
            inside = (c[..., 0] >= m) & (c[..., 0] <= ww - 1 - m) & (c[..., 1] >= m) & (c[..., 1] <= hh - 1 - m)
            grid = torch.stack([2 * c[..., 0] / max(ww - 1, 1) - 1, 2 * c[..., 1] / max(hh - 1, 1) - 1], -1)
            mv = F.grid_sample(self.moving_valid[:, None], grid, mode="bilinear", padding_mode="zeros",
                               align_corners=True)[:, 0]
            w = inside.to(self.ref.dtype) * (mv > 0.999).to(self.ref.dtype) * self.ref_valid[None]
            self.weights = w
            warped = spline_sample(self.coef, c)
            # window sums that do not depend on the motion: pixel count, reference mean and variance
            r = self.ref[None].expand_as(w)
            n, sum_r, sum_rr = box_sum(torch.stack([w, w * r, w * r * r], 1), self.r).unbind(1)
            self._count = n.clamp_min(1e-9)
            self._ref_mean = sum_r / self._count
            self._ref_variance = (sum_rr / self._count - self._ref_mean ** 2).clamp_min(0)
            # windows whose centre is valid and at least half filled
            self.window = w * (n > 0.5 * (2 * self.r + 1) ** 2).to(w.dtype)
            if self.robust_power > 0:
                self.window = self.window * self.window_r2(warped).clamp(0, 1) ** self.robust_power
            _, moving_variance, _ = self.local_moments(warped)
            self.moving_variance = ((self.window * moving_variance).sum(dim=(1, 2))
                                    / self.window.sum(dim=(1, 2)).clamp_min(1.0))
            self.norm = float(self.ref[self.ref_valid > 0].var()) if bool((self.ref_valid > 0).sum() > 1) else 1.0
            self.norm = max(self.norm, 1e-12)

    def local_moments(self, warped: torch.Tensor):
        """Per-window variances of the reference and the warped images and their covariance, ``(B, H, W)`` each."""
        wm = self.weights * warped
        sum_m, sum_mm, sum_rm = box_sum(torch.stack([wm, wm * warped, wm * self.ref], 1), self.r).unbind(1)
        n, mr = self._count, self._ref_mean
        mm = sum_m / n
        vm = (sum_mm / n - mm * mm).clamp_min(0)
        return self._ref_variance, vm, sum_rm / n - mr * mm

    def window_r2(self, warped: torch.Tensor) -> torch.Tensor:
        """``(B, H, W)`` R^2 of the local affine fit ``a * reference + b`` of each window."""
        vr, vm, c = self.local_moments(warped)
        return c * c / ((vr + self.eps) * (vm + self.eps))

    def local_r2(self, warped: torch.Tensor) -> torch.Tensor:
        """``(B,)`` share of the warped moving images' local variance explained by local affine fits of the reference."""
        vr, vm, c = self.local_moments(warped)
        explained = (self.window * c * c / (vr + self.eps)).sum(dim=(1, 2))
        total = (self.window * (vm + self.eps)).sum(dim=(1, 2)).clamp_min(1e-30)
        return explained / total

    def stokes_residual(self, warped: torch.Tensor) -> torch.Tensor:
        """Mean square of ``I0 + I90 - I45 - I135`` over the pixels valid in all four images."""
        w = self.weights.prod(dim=0)
        res = self.ref + warped[1] - warped[0] - warped[2]
        return (w * res * res).sum() / w.sum().clamp_min(1.0)

    def objective(self, p: torch.Tensor) -> torch.Tensor:
        warped = spline_sample(self.coef, self.coords(p))
        r2 = self.local_r2(warped)
        value = (self.moving_variance * (1 - r2)).sum() / 2
        if self.stokes_weight > 0:
            value = value + self.stokes_weight * self.stokes_residual(warped) / 4
        return value / self.norm


def minimize(criterion: LevelCriterion, p0: torch.Tensor, *, max_iterations: int) -> tuple[torch.Tensor, int, int]:
    """L-BFGS (strong Wolfe) from ``p0`` with the weights frozen at ``p0``; returns ``(p, iterations, evaluations)``."""
    criterion.fix_weights(p0)
    p = p0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([p], lr=1.0, max_iter=max_iterations, tolerance_grad=1e-9, tolerance_change=1e-13,
                            history_size=20, line_search_fn="strong_wolfe")
    evaluations = 0

    def closure():
        nonlocal evaluations
        evaluations += 1
        opt.zero_grad()
        loss = criterion.objective(p)
        loss.backward()
        return loss

    opt.step(closure)
    iterations = int(opt.state[opt._params[0]].get("n_iter", 0))
    return p.detach(), iterations, evaluations


# -- the engine -----------------------------------------------------------------------------------------
@dataclass
class StackRegistration:
    """Result of :func:`register_stack`: ``matrices`` ``(B, 3, 3)`` map reference pixel -> moving pixel."""

    params: np.ndarray
    matrices: np.ndarray
    correlation: np.ndarray
    info: dict = field(default_factory=dict)


def _pyramid(img: torch.Tensor, valid: torch.Tensor, levels: int):
    imgs, vals = [img], [valid]
    for _ in range(1, levels):
        a, v = imgs[-1], vals[-1]
        h2, w2 = a.shape[-2] // 2 * 2, a.shape[-1] // 2 * 2
        imgs.append(F.avg_pool2d(a[:, None, :h2, :w2], 2)[:, 0])
        vals.append((F.avg_pool2d(v[:, None, :h2, :w2], 2)[:, 0] > 0.999).to(a.dtype))
    return imgs, vals


def _final_fit(criterion, p: torch.Tensor, *, stokes: bool = False) -> tuple[torch.Tensor, float | None]:
    """Finest-level local R^2 ``(B,)`` of the estimate ``p`` and, with ``stokes`` (``B == 3``), the
    rms Stokes residual ``I0 + I90 - I45 - I135``."""
    crit = criterion(0, 0.0)
    crit.fix_weights(p)
    with torch.no_grad():
        warped = spline_sample(crit.coef, crit.coords(p))
        return crit.local_r2(warped), (float(crit.stokes_residual(warped).sqrt()) if stokes else None)


def stokes_residual_rms(ref: torch.Tensor, moving: torch.Tensor, params, *, ref_valid: torch.Tensor | None = None,
                        moving_valid: torch.Tensor | None = None, model: str = "similarity", border: int = 3) -> float:
    """rms of ``I0 + I90 - I45 - I135`` (image units) with ``moving`` ``(3, H, W)`` (45, 90, 135 deg)
    warped onto ``ref`` ``(H, W)`` (0 deg) by ``params`` ``(3, P)`` (as :func:`register_stack`
    returns them), over the pixels valid in all four images and ``border`` px from the edge: the
    figure ``register_stack`` reports as ``info["stokes_residual_rms"]``, for any images and warps."""
    if moving.shape[0] != 3:
        raise InputError("moving", tuple(moving.shape), "three images (45, 90, 135 deg) of the reference's shape")
    hh, ww = ref.shape
    rv = torch.ones_like(ref) if ref_valid is None else ref_valid.to(ref.dtype).clone()
    rv[:border], rv[hh - border:], rv[:, :border], rv[:, ww - border:] = 0, 0, 0, 0
    mv = torch.ones_like(moving) if moving_valid is None else moving_valid.to(moving.dtype)
    crit = LevelCriterion(ref, moving, rv, mv, scale=1, window_radius=1, model=model,
                          centre=((ww - 1) / 2.0, (hh - 1) / 2.0), radius=max(hh, ww) / 2.0, eps=1e-12)
    p = torch.as_tensor(params, dtype=ref.dtype, device=ref.device)
    crit.fix_weights(p)
    with torch.no_grad():
        return float(crit.stokes_residual(spline_sample(crit.coef, crit.coords(p))).sqrt())


def _rescue(p, ref, moving, criterion, *, model, threshold, peaks, max_iterations, info,
            margin: float = 0.02) -> torch.Tensor:
    """Images whose final local R^2 is below ``threshold`` (a wrong basin: periodic or
    self-similar targets such as a Siemens star) restart from more phase-correlation peaks of
    the full-resolution gradient images, each refined on the finest level (translation, then
    the full model); the restart is kept when its final R^2 is higher by ``margin``."""
    r2, _ = _final_fit(criterion, p)
    bad = ~(r2 >= threshold)
    record = {"threshold": threshold, "r2_before": r2.tolist(), "rescued": []}
    if not bool(bad.any()):
        info["rescue"] = record
        return p
    shifts, heights = phase_correlation_peaks(gradient_magnitude(ref[None])[0], gradient_magnitude(moving),
                                              peaks=peaks)
    # every start refined by translation on level 1 (cheap) and scored there; the best start per
    # image is then refined with the full model on level 0 and kept if it beats the old estimate
    lvl = 1 if len(info["levels"]) > 1 else 0
    best_t, best_s = p[:, :2].clone(), torch.full_like(r2, -math.inf)
    crit_t = criterion(lvl, 0.0, "translation")
    for k in range(shifts.shape[1]):
        pt, _, _ = minimize(crit_t, shifts[:, k].contiguous(), max_iterations=30)
        crit_t.fix_weights(pt)
        with torch.no_grad():
            score = crit_t.local_r2(spline_sample(crit_t.coef, crit_t.coords(pt)))
        take = torch.isfinite(pt).all(1) & (score > best_s)
        best_t = torch.where(take[:, None], pt, best_t)
        best_s = torch.where(take, score, best_s)
    start = torch.cat([best_t, torch.zeros_like(p[:, 2:])], 1)
    cand, _, _ = minimize(criterion(0, 0.0), start, max_iterations=max_iterations)
    score, _ = _final_fit(criterion, cand)
    better = bad & torch.isfinite(cand).all(1) & (score > r2 + margin)
    p = torch.where(better[:, None], cand, p)
    r2 = torch.where(better, score, r2)
    record["rescued"] = [int(i) for i in torch.nonzero(better).flatten()]
    record["r2_after"] = r2.tolist()
    info["rescue"] = record
    return p


def _stokes_joint_rescue(p, criterion, *, threshold: float, refine, info, weight: float = 100.0,
                         margin: float = 0.1) -> torch.Tensor:
    """Analyzer images that still match the 0 deg reference poorly (local R^2 below ``threshold``
    after :func:`_rescue`; strong polarization texture such as photoelastic fringes makes them
    look unlike the 0 deg image, and the local correlation then settles pixels off) take their
    parameters from a joint re-run, started from the current estimate, in which the Stokes
    consistency ``I0 + I90 = I45 + I135`` (weight ``weight``, on every pyramid level) dominates
    the local correlation: that residual does not care how unlike the 0 deg image an analyzer
    image looks. Kept when the Stokes residual (rms, finest level) falls by more than
    ``margin`` (relative); the well-matched images keep their estimates. Works for one, two or
    three poorly matched images (qiu-cellphonecases 256: 45 and 135 deg, 14-15 -> 0.2-0.4 HR px)."""
    r2, before = _final_fit(criterion, p, stokes=True)
    bad = ~(r2 >= threshold)
    record = {"threshold": threshold, "weight": weight, "images": [int(i) for i in torch.nonzero(bad).flatten()]}
    info["stokes_joint"] = record
    if not bool(bad.any()):
        return p
    joint = torch.as_tensor(refine(p, weight).params, dtype=p.dtype, device=p.device)
    cand = torch.where(bad[:, None], joint, p)
    if not bool(torch.isfinite(cand).all()):
        record["skipped"] = "non-finite parameters"
        return p
    r2_after, after = _final_fit(criterion, cand, stokes=True)
    take = after < (1.0 - margin) * before
    record.update({"stokes_rms_before": before, "stokes_rms_after": after, "r2_after": r2_after.tolist(),
                   "kept": bool(take)})
    return cand if take else p


def _stokes_subspace_refine(p, criterion, *, max_std: float, iterations: int, info) -> torch.Tensor:
    """Gauss-Newton steps on the Stokes residual ``I0 + I90 - I45 - I135`` alone (finest level),
    restricted to the eigen-directions of its Gauss-Newton Hessian ``J^T J`` along which the
    predicted standard deviation ``sqrt(s^2 / lambda)`` (``s^2``: residual mean square) is below
    ``max_std`` raw (level-0) pixels. The other directions (e.g. the two of the three shifts per
    axis that S0 texture alone cannot fix) keep the local-correlation estimate. ``J`` by central
    differences (one column per parameter: 3 x P evaluations, no per-pixel loop)."""
    crit = criterion(0, 1.0)
    crit.fix_weights(p)
    w = crit.weights.prod(dim=0).sqrt()
    shape = p.shape

    def residual(flat):
        warped = spline_sample(crit.coef, crit.coords(flat.view(shape)))
        return (w * (crit.ref + warped[1] - warped[0] - warped[2])).flatten()

    n_eff = float(w.square().sum().clamp_min(1.0))
    record = {"max_std_px": max_std, "steps": []}
    for _ in range(iterations):
        flat = p.flatten().detach()
        r0 = residual(flat)
        step = 1e-3
        cols = []
        for k in range(flat.numel()):
            e = torch.zeros_like(flat)
            e[k] = step
            cols.append((residual(flat + e) - residual(flat - e)) / (2 * step))
        jac = torch.stack(cols, 1)
        hess = jac.T @ jac
        grad = jac.T @ r0
        lam, vec = torch.linalg.eigh(hess)
        s2 = float(r0.square().sum()) / n_eff
        std = torch.sqrt(s2 / lam.clamp_min(1e-30))
        keep = std < max_std
        coef = -(vec.T @ grad) / lam.clamp_min(1e-30)
        delta = vec[:, keep] @ coef[keep]
        record["steps"].append({"kept_directions": int(keep.sum()), "std_px": std.tolist(),
                                "residual_rms": math.sqrt(s2),
                                "step_norm": float(delta.norm())})
        p = (flat + delta).view(shape)
        if float(delta.norm()) < 1e-4:
            break
    info["stokes_subspace"] = record
    return p


def register_stack(ref: torch.Tensor, moving: torch.Tensor, *, ref_valid: torch.Tensor | None = None,
                   moving_valid: torch.Tensor | None = None, model: str = "similarity", window_radius: int = 3,
                   stokes_weight: float = 0.0, stokes_levels: int = 2, max_iterations: int = 60,
                   min_level_size: int = 24, max_levels: int = 5, coarse_peaks: int = 3,
                   border: int = 3, initial: torch.Tensor | None = None, robust_power: float = 0.0,
                   robust_levels: int = 2, robust_passes: int = 2, full_model_levels: int = 2,
                   rescue_below: float = 0.7, rescue_peaks: int = 8, stokes_subspace_std: float = 0.0,
                   stokes_subspace_iterations: int = 4, robust_window_radius: int | None = None,
                   start_level: int | None = None) -> StackRegistration:
    """Register ``moving`` ``(B, H, W)`` to ``ref`` ``(H, W)`` (float64 tensors on one device).

    ``ref_valid``/``moving_valid`` (1 = usable pixel) mask saturated or otherwise bad pixels.
    ``stokes_weight > 0`` adds the Stokes-consistency term on the finest ``stokes_levels``
    levels; it needs ``B == 3`` moving images at 45, 90, 135 deg and a 0 deg reference.
    ``border``: reference pixels this close to the edge are ignored (full-resolution pixels).
    ``initial``: ``(B, P)`` starting parameters (skips the coarse stage and the phase-correlation
    rescue; the Stokes-consistency rescue still runs unless ``rescue_below = 0``);
    ``start_level`` (only with ``initial``): the pyramid level the refinement starts on, 0 = finest
    (default: the coarsest).
    ``stokes_subspace_std > 0`` (needs ``B == 3``) ends with :func:`_stokes_subspace_refine`.
    """
    t0 = time.perf_counter()
    dev, dtype = ref.device, ref.dtype
    b = moving.shape[0]
    hh, ww = ref.shape
    if model not in MOTION_MODELS:
        raise UnknownNameError("motion model", model, list(MOTION_MODELS))
    if stokes_weight > 0 and b != 3:
        raise InputError("stokes_weight", stokes_weight, "0 unless there are exactly 3 moving images (45, 90, 135 deg)")
    ref_valid = torch.ones_like(ref) if ref_valid is None else ref_valid.to(dtype)
    moving_valid = torch.ones_like(moving) if moving_valid is None else moving_valid.to(dtype)
    n_params = MOTION_MODELS[model]
    centre = ((ww - 1) / 2.0, (hh - 1) / 2.0)
    radius = max(hh, ww) / 2.0
    levels = 1
    while min(hh, ww) // (2 ** levels) >= min_level_size and levels < max_levels:
        levels += 1
    if start_level is not None and (initial is None or not 0 <= start_level):
        raise InputError("start_level", start_level, "an integer >= 0, and only together with initial parameters")
    pyr_ref, pyr_ref_valid = _pyramid(ref[None], ref_valid[None], levels)
    pyr_mov, pyr_mov_valid = _pyramid(moving, moving_valid, levels)
    sigma = noise_sigma(torch.cat([ref[None], moving]))
    info: dict = {"levels": [], "pyramid_levels": levels, "noise_sigma": [float(v) for v in sigma]}

    def criterion(level: int, stokes: float, m: str = model, r: int | None = None, robust: float = 0.0):
        s = 2 ** level
        rv = pyr_ref_valid[level][0].clone()
        lb = max(1, int(math.ceil(border / s)))
        rv[:lb], rv[-lb:], rv[:, :lb], rv[:, -lb:] = 0, 0, 0, 0
        lh, lw = rv.shape
        rad = window_radius if r is None else r
        rad = max(1, min(rad, min(lh, lw) // 6))
        eps = float(((2.0 * sigma.max()) / s) ** 2) + 1e-12
        return LevelCriterion(pyr_ref[level][0], pyr_mov[level], rv, pyr_mov_valid[level], scale=s,
                              window_radius=rad, model=m, centre=centre, radius=radius, eps=eps,
                              stokes_weight=stokes, robust_power=robust)

    # coarse stage: candidates from phase correlation, judged by the criterion at the coarsest level
    t_coarse = time.perf_counter()
    if initial is None:
        p = torch.zeros(b, n_params, dtype=dtype, device=dev)
        gm_ref = gradient_magnitude(gaussian_blur(ref[None], 1.0))[0]
        gm_mov = gradient_magnitude(gaussian_blur(moving, 1.0))
        shifts, heights = phase_correlation_peaks(gm_ref, gm_mov, peaks=coarse_peaks)
        candidates = torch.cat([torch.zeros(b, 1, 2, dtype=dtype, device=dev), shifts], 1)  # (B, K+1, 2)
        top = levels - 1
        crit = criterion(top, 0.0, "translation")
        best_score = torch.full((b,), -math.inf, dtype=dtype, device=dev)
        best = torch.zeros(b, 2, dtype=dtype, device=dev)
        tried = []
        for k in range(candidates.shape[1]):
            cand = candidates[:, k]
            if k > 0 and not bool(torch.isfinite(heights[:, k - 1]).any()):
                continue
            pk, _, _ = minimize(crit, cand, max_iterations=15)
            crit.fix_weights(pk)
            with torch.no_grad():
                score = crit.local_r2(spline_sample(crit.coef, crit.coords(pk)))
            score = torch.where(torch.isfinite(score) & torch.isfinite(pk).all(1), score,
                                torch.full_like(score, -math.inf))
            better = score > best_score + 1e-9
            best = torch.where(better[:, None], pk, best)
            best_score = torch.where(better, score, best_score)
            tried.append({"start": cand.tolist(), "converged": pk.tolist(), "local_r2": score.tolist()})
        p[:, :2] = best
        info["coarse"] = {"phase_correlation_shifts": shifts.tolist(), "phase_correlation_heights": heights.tolist(),
                          "candidates": tried, "chosen_shift": best.tolist(), "chosen_local_r2": best_score.tolist()}
    else:
        p = initial.to(dev, dtype).clone()
    info["time_coarse_s"] = time.perf_counter() - t_coarse

    first = levels - 1 if start_level is None else min(start_level, levels - 1)
    for level in range(first, -1, -1):
        stokes = stokes_weight if level < stokes_levels else 0.0
        t1 = time.perf_counter()
        if level >= full_model_levels and model != "translation":
            # coarse levels: translation only (a Siemens star is nearly invariant to scale and
            # rotation about its centre; the full model from the start drifts along that valley)
            crit = criterion(level, stokes, "translation")
            p_new, iters, evals = minimize(crit, p[:, :2].contiguous(), max_iterations=max_iterations)
            p_new = torch.cat([p_new, p[:, 2:]], 1)
        else:
            crit = criterion(level, stokes)
            p_new, iters, evals = minimize(crit, p, max_iterations=max_iterations)
        if bool(torch.isfinite(p_new).all()):
            p = p_new
        else:
            log.warning("registration: non-finite parameters at pyramid level %d; kept the previous estimate", level)
        if robust_power > 0 and level < robust_levels:
            rcrit = criterion(level, stokes, robust=robust_power, r=robust_window_radius)
            for _ in range(robust_passes):  # IRLS: window weights R^2^k frozen at the current estimate
                p_new, it2, ev2 = minimize(rcrit, p, max_iterations=max_iterations)
                iters, evals = iters + it2, evals + ev2
                if bool(torch.isfinite(p_new).all()):
                    p = p_new
        info["levels"].append({"level": level, "size": list(crit.shape), "window_radius": crit.r,
                               "stokes_weight": stokes, "iterations": iters, "evaluations": evals,
                               "time_s": time.perf_counter() - t1,
                               "valid_pixels": [int(v) for v in crit.weights.sum(dim=(1, 2))]})
    if rescue_below > 0 and initial is None:
        p = _rescue(p, ref, moving, criterion, model=model, threshold=rescue_below, peaks=rescue_peaks,
                    max_iterations=max_iterations, info=info)
    if rescue_below > 0 and b == 3:
        def refine(q, weight):
            return register_stack(ref, moving, ref_valid=ref_valid, moving_valid=moving_valid, model=model,
                                  window_radius=window_radius, stokes_weight=weight, stokes_levels=levels,
                                  max_iterations=max_iterations, min_level_size=min_level_size,
                                  max_levels=max_levels, border=border, initial=q, robust_power=0.0,
                                  full_model_levels=full_model_levels, rescue_below=0.0)

        p = _stokes_joint_rescue(p, criterion, threshold=rescue_below, refine=refine, info=info)
    if stokes_subspace_std > 0 and b == 3:
        p = _stokes_subspace_refine(p, criterion, max_std=stokes_subspace_std,
                                    iterations=stokes_subspace_iterations, info=info)
    r2, stokes_rms = _final_fit(criterion, p, stokes=b == 3)
    if stokes_rms is not None:
        info["stokes_residual_rms"] = stokes_rms
    g = params_to_matrices(p, model, centre, radius)
    info["time_s"] = time.perf_counter() - t0
    return StackRegistration(params=p.cpu().numpy(), matrices=g.cpu().numpy(), correlation=r2.cpu().numpy(),
                             info=info)
