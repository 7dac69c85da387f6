"""The registration criterion at one pyramid level and its L-BFGS minimisation (paper section 3.1).

:class:`LevelCriterion` scores warps of a batch of *moving* images against one *reference*
image whose intensities may differ from theirs in a spatially varying way (other polarizer
angles, other colours). Two terms:

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

:func:`minimize` runs L-BFGS (strong Wolfe, :mod:`~capssim.reconstruct.registration.lbfgs`) through autograd, all moving
images in one batch.
All coordinates are ``(x=col, y=row)`` with pixel centres on integers.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from capssim.errors import InputError
from capssim.runtime.threads import adapt_threads

from .image_ops import box_sum
from .lbfgs import minimize_lbfgs
from .motion import params_to_matrices, spline_coefficients, spline_sample


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
        """``(B,)`` share of the warped moving images' local variance explained by local affine fits of the
        reference."""
        vr, vm, c = self.local_moments(warped)
        explained = (self.window * c * c / (vr + self.eps)).sum(dim=(1, 2))
        total = (self.window * (vm + self.eps)).sum(dim=(1, 2)).clamp_min(1e-30)
        return explained / total

    def stokes_residual(self, warped: torch.Tensor) -> torch.Tensor:
        """Mean square of ``I0 + I90 - I45 - I135`` over the pixels valid in all four images."""
        w = self.weights.prod(dim=0)
        i45, i90, i135 = warped.unbind(0)
        res = self.ref + i90 - i45 - i135
        return (w * res * res).sum() / w.sum().clamp_min(1.0)

    def objective(self, p: torch.Tensor) -> torch.Tensor:
        warped = spline_sample(self.coef, self.coords(p))
        r2 = self.local_r2(warped)
        value = (self.moving_variance * (1 - r2)).sum() / 2
        if self.stokes_weight > 0:
            value = value + self.stokes_weight * self.stokes_residual(warped) / 4
        return value / self.norm


#: L-BFGS stopping tolerances (gradient max-norm; change of the step and of the value). Tighter ones
#: (1e-9, 1e-13) cost 1.2-2.2x the time and moved no warp by more than 0.0003 HR px (docs: notes/registration.md).
TOLERANCE_GRAD, TOLERANCE_CHANGE = 1e-7, 1e-9


def minimize(criterion: LevelCriterion, p0: torch.Tensor, *, max_iterations: int,
             memory=None) -> tuple[torch.Tensor, int, int]:
    """L-BFGS (strong Wolfe) from ``p0`` with the weights frozen at ``p0``; returns ``(p, iterations, evaluations)``."""
    criterion.fix_weights(p0)

    def value_and_gradient(p: torch.Tensor) -> tuple[float, torch.Tensor]:
        adapt_threads()  # under 'auto': follow the machine's load within the registration too
        with torch.enable_grad():  # callers may run under torch.no_grad()
            p = p.detach().requires_grad_(True)
            value = criterion.objective(p)
            (gradient,) = torch.autograd.grad(value, p)
        return float(value.detach()), gradient

    return minimize_lbfgs(value_and_gradient, p0, max_iterations=max_iterations, tolerance_grad=TOLERANCE_GRAD,
                          tolerance_change=TOLERANCE_CHANGE, history_size=20, memory=memory)


def final_fit(criterion, p: torch.Tensor, *, stokes: bool = False) -> tuple[torch.Tensor, float | None]:
    """Finest-level local R^2 ``(B,)`` of the estimate ``p`` and, with ``stokes`` (``B == 3``), the
    rms Stokes residual ``I0 + I90 - I45 - I135``. ``criterion(level, stokes_weight)`` gives the
    :class:`LevelCriterion` of a pyramid level (:class:`~capssim.reconstruct.registration.levels.LevelCriteria`)."""
    crit = criterion(0, 0.0)
    crit.fix_weights(p)
    with torch.no_grad():
        warped = spline_sample(crit.coef, crit.coords(p))
        return crit.local_r2(warped), (float(crit.stokes_residual(warped).sqrt()) if stokes else None)


def stokes_residual_rms(ref: torch.Tensor, moving: torch.Tensor, params, *, ref_valid: torch.Tensor | None = None,
                        moving_valid: torch.Tensor | None = None, model: str = "similarity", border: int = 3) -> float:
    """rms of ``I0 + I90 - I45 - I135`` (image units) with ``moving`` ``(3, H, W)`` (45, 90, 135 deg)
    warped onto ``ref`` ``(H, W)`` (0 deg) by ``params`` ``(3, P)`` (as
    :func:`~capssim.reconstruct.registration.engine.register_stack` returns them), over the pixels valid in
    all four images and ``border`` px from the edge: the figure ``register_stack`` reports as
    ``info["stokes_residual_rms"]``, for any images and warps."""
    hh, ww = ref.shape
    rv = torch.ones_like(ref) if ref_valid is None else ref_valid.to(ref.dtype).clone()
    rv[:border], rv[hh - border:], rv[:, :border], rv[:, ww - border:] = 0, 0, 0, 0
    mv = torch.ones_like(moving) if moving_valid is None else moving_valid.to(moving.dtype)
    crit = _analyzer_criterion(ref, moving, rv, mv, model)
    p = torch.as_tensor(params, dtype=ref.dtype, device=ref.device)
    crit.fix_weights(p)
    with torch.no_grad():
        return float(crit.stokes_residual(spline_sample(crit.coef, crit.coords(p))).sqrt())


def _analyzer_criterion(ref: torch.Tensor, moving: torch.Tensor, ref_valid: torch.Tensor, moving_valid: torch.Tensor,
                        model: str) -> LevelCriterion:
    """The full-resolution :class:`LevelCriterion` of the 0 deg ``ref`` ``(H, W)`` and the 45, 90, 135 deg
    ``moving`` ``(3, H, W)``, with :func:`~capssim.reconstruct.registration.engine.register_stack`'s centre and
    radius, so that its parameters warp them as they do there."""
    if moving.shape[0] != 3:
        raise InputError("moving", tuple(moving.shape), "three images (45, 90, 135 deg) of the reference's shape")
    hh, ww = ref.shape
    return LevelCriterion(ref, moving, ref_valid, moving_valid, scale=1, window_radius=1, model=model,
                          centre=((ww - 1) / 2.0, (hh - 1) / 2.0), radius=max(hh, ww) / 2.0, eps=1e-12)


def intensity_texture_ratio(ref: torch.Tensor, moving: torch.Tensor, params, *, model: str = "similarity",
                            border: int = 3) -> float:
    """How much texture the sums of orthogonal analyzer images keep: for the pairs (0, 90) and (45, 135) deg, with
    ``moving`` ``(3, H, W)`` (45, 90, 135 deg) warped onto ``ref`` ``(H, W)`` (0 deg) by ``params`` ``(3, P)``,
    ``std(I_a + I_b) / (std(I_a) + std(I_b))`` over the pixels ``border`` px from the edge; the smaller of the two
    (a pair with less than a tenth of the other's texture is left out).

    Each pair sums to ``S0``: about 1 for an unpolarized scene (the two images are alike), about 0.7 for
    independent ones, near 0 when the structure is in the polarization only (``S0`` flat: a polarization star, an
    AoP wheel; the two images are negatives of each other). There the registration is ill-posed: a shift common to
    the 45 and 135 deg apertures leaves their sum, and so every criterion of the registration, unchanged."""
    hh, ww = ref.shape
    crit = _analyzer_criterion(ref, moving, torch.ones_like(ref), torch.ones_like(moving), model)
    p = torch.as_tensor(params, dtype=ref.dtype, device=ref.device)
    with torch.no_grad():
        warped = spline_sample(crit.coef, crit.coords(p))
    images = torch.cat([ref[None], warped])[:, border:hh - border, border:ww - border].flatten(1)
    spread = images.std(dim=1)
    pairs = [(spread[a] + spread[b], images[a] + images[b]) for a, b in ((0, 2), (1, 3))]
    most = max(float(texture) for texture, _ in pairs)
    ratios = [float(total.std() / texture) for texture, total in pairs if float(texture) > 0.1 * most and most > 0]
    return min(ratios) if ratios else 1.0
