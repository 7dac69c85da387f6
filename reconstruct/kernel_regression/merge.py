"""The camera-array merge of ``array-kr``: intensity from all four apertures, polarization from each its own.

Reference: Wronski et al., "Handheld multi-frame super-resolution", ACM TOG 38(4) (SIGGRAPH 2019) for the
kernel-regression merge of raw Bayer samples (:mod:`.gather`, :mod:`.steering`); the colour step is the
colour-difference interpolation of demosaicking (e.g. Kiku et al., IEEE TIP 25(3) 2016, residual interpolation),
and the polarization step the same idea across analyzers (the intensity guide of IGRI2, Morimatsu et al.,
IEEE Sensors J. 21(23) 2021).

Model. Aperture ``n`` behind a polarizer at ``45 n`` degrees records ``I_n = (S0 + S1 cos 2a_n + S2 sin 2a_n) / 2``
of its pixel's colour, so ``2 I_n`` is ``S0`` plus a polarization term that cancels over the four apertures
(``I_0 + I_90 = I_45 + I_135 = S0``). The merge, with no iteration, on the HR grid ``(Ho, Wo) = (2H, 2W)``:

1. ``G~``: green ``S0`` proxy, every aperture's green samples ``2 v`` merged with an isotropic kernel;
2. ``Q``: the steered kernel of ``G~`` (:func:`.steering.steered`);
3. ``G``: the same merge with ``Q``;
4. ``R = G + KR(2 v - G(q))`` over the red samples (``G(q)`` bilinear at each sample's HR position ``q``),
   ``B`` alike: colour differences vary slowly, so red and blue borrow green's resolution;
5. each aperture's own samples against the merged intensity, ``rho = (v + eps) / (S0(q) / 2 + eps)`` (``ratio``)
   or ``v - S0(q) / 2`` (``difference``), merged over that aperture alone with an isotropic kernel of std
   :data:`POL_SIGMA` (not ``Q``: the intensity is flat where only the polarization has structure), then ``I_n = S0 / 2 * rho_n``
   (``S0 / 2 + d_n``). Structure the analyzers share comes from all four apertures; structure only in the
   polarization (a star of angles on a flat intensity) comes from the aperture's own samples, not smeared
   by the others.

Weights: saturated samples have weight 0, except for an aperture and colour with no unsaturated sample in reach
(there they decide: the clip level is then the best bound); window
entries outside an aperture's frame have weight 0; where an aperture sees nothing of a pixel its ratio is 1
(its difference 0), i.e. ``I_n = S0 / 2``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .gather import SampleField, kernel_sums
from .steering import isotropic, steered

__all__ = ["POLARIZATION_MODES", "POL_SIGMA", "SATURATED_WEIGHT", "aperture_weights", "merge_apertures"]

POLARIZATION_MODES = ("ratio", "difference")
#: the isotropic kernel std (HR px) of the polarization step, per colour (each aperture's own samples: not
#: steered by the intensity, which is flat where only the polarization has structure)
POL_SIGMA = (1.6, 1.2, 1.6)
#: the kernel scale of the colour differences (x the steered kernel), per colour
DIFF_SCALE = (1.5, 1.0, 1.5)
#: ``kernel_sums``' fallback: saturated samples decide only where no unsaturated sample is in reach
SATURATED_WEIGHT = 1.0
#: the isotropic kernel std (HR px) of step 1, per colour
ISO_SCALE = (1.5, 1.0, 1.5)
#: the ridge on the slopes of the local linear fit (HR px^2, times the total weight)
RIDGE = 0.05
#: the regularizer of the ratio (full scale)
RATIO_EPS = 0.01


def _divide(num: torch.Tensor, den: torch.Tensor, default: float) -> torch.Tensor:
    """``num / den`` where ``den > 1e-8``, ``default`` elsewhere."""
    ok = den > 1e-8
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.full_like(num, default))


def aperture_mean(estimates: torch.Tensor, den: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
    """``(4, Ho, Wo)`` per-aperture estimates -> their mean over the apertures that see the pixel (kernel weight
    ``den`` above :data:`SEEN_WEIGHT`; where none does, those with any weight, e.g. only saturated samples), 0
    where none has any: equal shares, so that the polarization terms of ``2 v`` cancel (``I_0 + I_90 =
    I_45 + I_135``) whatever the local sample density of each aperture."""
    seen = torch.where(seen.any(0, keepdim=True), seen, den > 1e-8).to(estimates.dtype)
    return (estimates * seen).sum(0) / seen.sum(0).clamp_min(1.0)


def local_linear(num: torch.Tensor, den: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """The constant term of the weighted least-squares plane ``v ~ c + gx dx + gy dy`` from the moments of
    :func:`~.gather.kernel_sums` (``linear=True``) of one colour summed over apertures, ``num`` ``(3, Ho, Wo)`` and
    ``den`` ``(6, Ho, Wo)``, with the ridge :data:`RIDGE` ``* sum w`` on the slopes; ``fallback`` where ``sum w``
    is 0."""
    s0, sx, sy, sxx, sxy, syy = den
    ridge = RIDGE * s0
    a = torch.stack([torch.stack([s0, sx, sy], -1), torch.stack([sx, sxx + ridge, sxy], -1),
                     torch.stack([sy, sxy, syy + ridge], -1)], -2)  # (Ho, Wo, 3, 3)
    ok = s0 > 1e-8
    a = torch.where(ok[..., None, None], a, torch.eye(3, device=a.device, dtype=a.dtype).expand_as(a))
    c = torch.linalg.solve(a, torch.movedim(num, 0, -1)[..., None])[..., 0, 0]
    return torch.where(ok, c, fallback)


def at_samples(image: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """``image`` ``(C, Ho, Wo)`` bilinearly at the HR positions ``pos`` ``(4, 2, P)`` -> ``(4, C, P)`` (border)."""
    ho, wo = image.shape[-2:]
    gx = 2 * pos[:, 0] / max(wo - 1, 1) - 1
    gy = 2 * pos[:, 1] / max(ho - 1, 1) - 1
    grid = torch.stack([gx, gy], dim=-1)[:, None]  # (4, 1, P, 2)
    out = F.grid_sample(image[None].expand(pos.shape[0], -1, -1, -1), grid, mode="bilinear",
                        padding_mode="border", align_corners=True)
    return out[:, :, 0]


def _own_colour(values: torch.Tensor, colour: torch.Tensor) -> torch.Tensor:
    """``(4, 3, P)`` per-colour values at the samples -> ``(4, P)`` the value of each sample's own colour."""
    return torch.gather(values, 1, colour.view(1, 1, -1).expand(values.shape[0], 1, -1))[:, 0]


def aperture_weights(field: SampleField, hr_shape: tuple[int, int], *, sigma: float = 1.0) -> torch.Tensor:
    """``(4, Ho, Wo)``: the total kernel weight of each aperture's usable samples at every HR pixel (isotropic
    kernel of std ``sigma`` HR px, all colours): exactly 0 where all its samples in reach are saturated or
    outside its frame."""
    q = isotropic(hr_shape, sigma, field.values.device)
    _, den, _ = kernel_sums(field, field.values, q, (1.0, 1.0, 1.0))
    return den.sum(1)


def merge_intensity(field: SampleField, hr_shape: tuple[int, int], sigma_n: float, *, scale: float = 1.0,
                    steer: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Steps 1-4: ``S0`` ``(3, Ho, Wo)`` (R, G, B) and the steered inverse covariance ``Q`` ``(3, Ho, Wo)``."""
    two = 2.0 * field.values
    iso = isotropic(hr_shape, scale, field.values.device)
    num, den, seen = kernel_sums(field, two, iso, ISO_SCALE, fallback=SATURATED_WEIGHT)
    green0 = aperture_mean(_divide(num[:, 1], den[:, 1], 0.0), den[:, 1], seen[:, 1])
    q = steered(green0, sigma_n, scale=scale, steer=steer)
    num, den, seen = kernel_sums(field, two, q, DIFF_SCALE, fallback=SATURATED_WEIGHT, linear=True)
    green = aperture_mean(local_linear(num[:, :, 1], den[:, :, 1], green0[None]), den[0, :, 1], seen[:, 1])
    diff = two - at_samples(green[None], field.pos)[:, 0]
    num, den, seen = kernel_sums(field, diff, q, DIFF_SCALE, fallback=SATURATED_WEIGHT)
    red = green + aperture_mean(_divide(num[:, 0], den[:, 0], 0.0), den[:, 0], seen[:, 0])
    blue = green + aperture_mean(_divide(num[:, 2], den[:, 2], 0.0), den[:, 2], seen[:, 2])
    return torch.stack([red, green, blue]), q


def merge_apertures(field: SampleField, hr_shape: tuple[int, int], sigma_n: float, *, scale: float = 1.0,
                    steer: bool = True, polarization: str = "ratio") -> tuple[torch.Tensor, dict]:
    """The whole merge (module docstring): ``(4, 3, Ho, Wo)`` (aperture/polarizer ``n``, colour ``k``) and a
    record of the arrays behind it (``s0`` ``(3, Ho, Wo)``, ``aperture_weight`` ``(4, 3, Ho, Wo)``: the kernel
    weight of each aperture's own samples in step 5)."""
    s0, q = merge_intensity(field, hr_shape, sigma_n, scale=scale, steer=steer)
    half = 0.5 * _own_colour(at_samples(s0, field.pos), field.colour)  # (4, P): S0(q) / 2 of each sample's colour
    if polarization == "ratio":
        own = (field.values + RATIO_EPS) / (half.clamp_min(0.0) + RATIO_EPS)
    else:
        own = field.values - half
    iso = isotropic(hr_shape, scale, field.values.device)
    num, den, _ = kernel_sums(field, own, iso, POL_SIGMA, fallback=SATURATED_WEIGHT)
    if polarization == "ratio":
        image = (0.5 * s0 + RATIO_EPS)[None] * _divide(num, den, 1.0) - RATIO_EPS
    else:
        image = 0.5 * s0[None] + _divide(num, den, 0.0)
    return image, {"s0": s0, "aperture_weight": den}
