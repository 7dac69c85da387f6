"""Registration of a scene whose structure is in its polarization only (:mod:`~.estimate`, after the intensity
criteria).

When ``S0`` is flat (a polarization star, an AoP wheel, a patterned polarizer film), the sums of orthogonal
analyzer images ``I0 + I90 = I45 + I135 = S0`` carry no texture (:func:`~.criterion.intensity_texture_ratio`).
The relative warp within each orthogonal pair is still fixed (a misaligned pair no longer sums to a flat
``S0``), but a motion *common to the 45 and 135 deg apertures*, relative to the 0 and 90 deg pair, leaves every
intensity criterion unchanged: the registration can be pixels off there and cannot tell.

What does change is the linear polarization ``L = sqrt(S1^2 + S2^2)`` (``S1 = I0 - I90``, ``S2 = I45 - I135``):
a wrong common motion beats ``S2`` against ``S1`` and writes a pattern into ``L`` that the scene does not have
(on a polarization star ``L`` is constant inside the star; misaligned, it oscillates with every cycle). This step
sets the common motion ``M`` (a rotation and translation about the frame centre, raw pixels) of the 45 and 135
deg apertures, ``G_n -> G_n M``, to the one whose ``L`` has the least total variation,

    ``M* = argmin_M  sum_x |grad L_M(x)| / sum_x L_M(x)``,

searched over translations of up to ``polarization_cue_radius`` raw pixels on a half-pixel grid (on 2x-downsampled
images for frames of :data:`HALF_RESOLUTION_SEARCH` raw pixels or more), then refined with the rotation by L-BFGS
on the full-resolution images (a refinement that leaves the grid point's basin by more than a pixel is dropped).
Total variation as the measure of spurious structure: Rudin, Osher, Fatemi, "Nonlinear total variation based noise
removal algorithms", Physica D 60, 1992. The common *scale* is not
searched: a star, the typical flat-``S0`` target, looks the same at every scale about its centre. It is set by the
array instead (identical cameras): the 45/135 pair's mean scale is made that of the 0/90 pair. It is a prior on the
scene (its polarization magnitude has less structure than its components), not a measurement, so it runs only
when the intensity criteria cannot see the motion and both the 45 and the 135 deg warp came from them (not an
identity fallback), is kept only when it lowers that variation by :data:`MIN_IMPROVEMENT` inside the search and
its warps are plausible, and is recorded and announced either way.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from capssim.camera.array_geometry import raw_matrix
from capssim.camera.homography import rotation_and_scale

from .criterion import intensity_texture_ratio
from .engine import StackRegistration
from .lbfgs import minimize_lbfgs
from .parameters import RegistrationParameters
from .plausibility import is_plausible

__all__ = ["MIN_IMPROVEMENT", "POLARIZATION_ONLY_TEXTURE", "check_polarization_only", "polarization_roughness",
           "refine_common_motion"]

#: :func:`~capssim.reconstruct.registration.criterion.intensity_texture_ratio` below which the structure is taken to be
#: in the polarization only (S0 flat; the common motion of the 45 and 135 deg apertures is then set here, and the
#: registration says so): rendered polarization stars 0.02-0.03, every other scene of the benchmark suites 0.37
#: (strongly polarized photographs) to 1
POLARIZATION_ONLY_TEXTURE = 0.2
#: a found common motion is kept only if it lowers the roughness of ``L`` by at least this fraction
MIN_IMPROVEMENT = 0.1
#: the apertures whose common motion no intensity criterion sees (45 and 135 deg)
COMMON_APERTURES = (1, 3)
#: frames with at least this many raw pixels on both sides are searched on a 2x-downsampled grid first
HALF_RESOLUTION_SEARCH = 256
_EPS = 1e-4  # smoothing of |grad L| and of L's square root (image units; raw frames are on [0, 1])


def _similarity(q: torch.Tensor, centre: tuple[float, float], radius: float, scale: float = 1.0) -> torch.Tensor:
    """``(3, 3)`` similarity about ``centre``: ``q = (tx, ty, b)`` in raw pixels, the linear part
    ``scale [[1, -b / radius], [b / radius, 1]]`` (so ``b`` moves the frame's edge by about ``b`` pixels)."""
    cx, cy = centre
    s, r = q.new_tensor(scale), scale * q[2] / radius
    zero, one = q.new_zeros(()), q.new_ones(())
    row0 = torch.stack([s, -r, cx + q[0] - s * cx + r * cy])
    row1 = torch.stack([r, s, cy + q[1] - r * cx - s * cy])
    return torch.stack([row0, row1, torch.stack([zero, zero, one])])


def _pixel_points(images: torch.Tensor) -> torch.Tensor:
    """``(h, w, 3)`` homogeneous ``(x=col, y=row, 1)`` of every pixel of ``images`` ``(..., h, w)``."""
    h, w = images.shape[-2:]
    ys, xs = torch.meshgrid(torch.arange(h, dtype=images.dtype, device=images.device),
                            torch.arange(w, dtype=images.dtype, device=images.device), indexing="ij")
    return torch.stack([xs, ys, torch.ones_like(xs)], dim=-1)


def _sample(images: torch.Tensor, matrices: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """``images`` ``(B, h, w)`` read at ``matrices[b] (x, y, 1)`` for every pixel ``pts`` ``(h, w, 3)``
    (:func:`_pixel_points`), bilinear; differentiable in ``matrices``."""
    h, w = images.shape[-2:]
    src = torch.einsum("bij,hwj->bhwi", matrices, pts)
    grid = torch.stack([2 * src[..., 0] / src[..., 2] / max(w - 1, 1) - 1,
                        2 * src[..., 1] / src[..., 2] / max(h - 1, 1) - 1], dim=-1)
    return F.grid_sample(images[:, None], grid, mode="bilinear", padding_mode="border", align_corners=True)[:, 0]


def polarization_roughness(images: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Total variation of ``L = sqrt(S1^2 + S2^2)`` over its mean, on the pixels of ``mask`` ``(h, w)``;
    ``images`` ``(4, h, w)`` are the registered 0, 45, 90, 135 deg images."""
    s1, s2 = images[0] - images[2], images[1] - images[3]
    lin = (s1 * s1 + s2 * s2 + _EPS ** 2).sqrt()
    gx, gy = lin[:-1, 1:] - lin[:-1, :-1], lin[1:, :-1] - lin[:-1, :-1]
    m = mask[:-1, :-1] * mask[:-1, 1:] * mask[1:, :-1]
    return ((gx * gx + gy * gy + _EPS ** 2).sqrt() * m).sum() / ((lin[:-1, :-1] * m).sum() + 1e-12)


class _CommonMotion:
    """The roughness of ``L`` as a function of the common motion ``q`` of apertures 45 and 135."""

    def __init__(self, lum: torch.Tensor, valid: torch.Tensor, raw_warps: np.ndarray, margin: int, scale: float):
        self.lum, self.h, self.w, self.scale = lum, lum.shape[-2], lum.shape[-1], scale
        self.warps = torch.as_tensor(raw_warps, dtype=lum.dtype, device=lum.device)
        self.centre, self.radius = ((self.w - 1) / 2.0, (self.h - 1) / 2.0), max(self.h, self.w) / 2.0
        self.pts = _pixel_points(lum)
        reach = _sample(valid.to(lum.dtype), self.warps, self.pts).amin(dim=0) > 0.99
        mask = torch.zeros_like(reach)
        mask[margin:self.h - margin, margin:self.w - margin] = True
        self.mask = (mask & reach).to(lum.dtype)
        self.fixed = _sample(lum[[0, 2]], self.warps[[0, 2]], self.pts)

    def __call__(self, q: torch.Tensor, *, scale: float | None = None) -> torch.Tensor:
        """The roughness at motion ``q``, with the common scale ``scale`` (default: the one given at construction)."""
        motion = _similarity(q, self.centre, self.radius, self.scale if scale is None else scale)
        moved = _sample(self.lum[list(COMMON_APERTURES)], self.warps[list(COMMON_APERTURES)] @ motion, self.pts)
        images = torch.stack([self.fixed[0], moved[0], self.fixed[1], moved[1]])
        return polarization_roughness(images, self.mask)

    def objective(self, q: torch.Tensor) -> tuple[float, torch.Tensor]:
        with torch.enable_grad():  # the methods run under no_grad
            q = q.detach().requires_grad_(True)
            value = self(q)
            (grad,) = torch.autograd.grad(value, q)
        return float(value.detach()), grad

    def motion_matrix(self, q: torch.Tensor) -> np.ndarray:
        return _similarity(q.detach(), self.centre, self.radius, self.scale).cpu().numpy()


def _grid_search(lum: torch.Tensor, valid: torch.Tensor, raw_warps: np.ndarray, radius: float,
                 scale: float) -> torch.Tensor:
    """The translation ``(tx, ty)`` of least roughness on a half-raw-pixel grid of ``+- radius``, on the images
    downsampled by 2 when both sides have :data:`HALF_RESOLUTION_SEARCH` raw pixels."""
    factor = 2 if min(lum.shape[-2:]) >= HALF_RESOLUTION_SEARCH else 1
    small = F.avg_pool2d(lum[:, None], factor)[:, 0]
    small_valid = F.avg_pool2d(valid.to(lum.dtype)[:, None], factor)[:, 0] > 0.99
    down = np.array([[factor, 0, (factor - 1) / 2], [0, factor, (factor - 1) / 2], [0, 0, 1.0]])  # -> raw pixel
    coarse = _CommonMotion(small, small_valid, np.stack([np.linalg.inv(down) @ g @ down for g in raw_warps]),
                           margin=int(np.ceil(radius / factor)) + 2, scale=scale)
    steps = torch.arange(-radius, radius + 0.25, 0.5, dtype=lum.dtype)
    best, best_q = None, torch.zeros(3, dtype=lum.dtype)
    with torch.no_grad():
        for tx in steps:
            for ty in steps:
                q = torch.tensor([float(tx) / factor, float(ty) / factor, 0.0], dtype=lum.dtype, device=lum.device)
                value = float(coarse(q))
                if best is None or value < best:
                    best, best_q = value, torch.tensor([float(tx), float(ty), 0.0], dtype=lum.dtype)
    return best_q.to(lum.device)


def refine_common_motion(lum: torch.Tensor, valid: torch.Tensor, aperture: np.ndarray,
                         parameters: RegistrationParameters) -> tuple[np.ndarray, dict]:
    """The aperture warps ``(4, 3, 3)`` (HR reference -> aperture-HR) with the common motion of the 45 and 135 deg
    apertures set by the polarization cue, and its record.

    ``lum`` ``(4, h, w)``: the registration images at raw resolution; ``valid`` ``(4, h, w)`` bool, their usable
    pixels; ``aperture``: the warps the intensity criteria found. Returns ``aperture`` unchanged (and
    ``kept: False``) when the cue does not lower :func:`polarization_roughness` by :data:`MIN_IMPROVEMENT`, finds its
    minimum on the edge of the search (within half a pixel of ``polarization_cue_radius``) or gives an implausible
    warp."""
    radius = float(parameters.polarization_cue_radius)
    rmat = raw_matrix()
    raw_warps = np.stack([rmat @ h @ np.linalg.inv(rmat) for h in aperture])
    scales = [rotation_and_scale(h)[1] for h in aperture]
    scale = (scales[0] + scales[2]) / (scales[1] + scales[3])  # the 45/135 pair's mean scale -> the 0/90 pair's
    fine = _CommonMotion(lum, valid, raw_warps, margin=int(np.ceil(radius)) + 2, scale=scale)
    with torch.no_grad():  # the intensity criteria's warps as they are: no motion, no scale change
        before = float(fine(torch.zeros(3, dtype=lum.dtype, device=lum.device), scale=1.0))
    start = _grid_search(lum, valid, raw_warps, radius, scale)
    q, _, _ = minimize_lbfgs(fine.objective, start, max_iterations=60, tolerance_grad=1e-9, tolerance_change=1e-12)
    if not bool(torch.isfinite(q).all()) or float((q - start).abs().max()) > 1.0:  # left the grid point's basin
        q = start
    with torch.no_grad():
        after = float(fine(q))
    motion = np.linalg.inv(rmat) @ fine.motion_matrix(q) @ rmat  # in HR reference coordinates
    moved = aperture.copy()
    for n in COMMON_APERTURES:
        moved[n] = aperture[n] @ motion
        moved[n] /= moved[n][2, 2]
    inside = float(q[:2].abs().max()) < radius - 0.5  # a minimum on the search's edge is not one it found
    kept = bool(np.isfinite(after) and after <= (1 - MIN_IMPROVEMENT) * before and inside
                and all(is_plausible(moved[n], parameters) for n in COMMON_APERTURES))
    record = {"roughness": {"intensity_warps": before, "polarization_cue": after}, "kept": kept,
              "translation_raw_px": [float(v) for v in q[:2].cpu()], "rotation_deg": float(np.degrees(
                  float(q[2]) / fine.radius)), "scale": scale, "search_radius_raw_px": radius}
    return (moved if kept else aperture), record


def check_polarization_only(reg: StackRegistration, lum: torch.Tensor, valid: torch.Tensor, aperture: np.ndarray,
                            model: str, parameters: RegistrationParameters, diag: dict, *, warn,
                            fallbacks: frozenset = frozenset()) -> np.ndarray:
    """Record the registered images' :func:`~.criterion.intensity_texture_ratio` in ``diag``; when the structure is
    in the polarization only, set the 45/135 deg common motion by :func:`refine_common_motion` (unless
    ``polarization_cue_radius`` is 0, or the 45 or 135 deg warp is in ``fallbacks``, the apertures that fell back
    to the identity: then the pair's relative warp, which the cue keeps, is unknown) and ``warn(diag, message)``
    what was done. Returns the aperture warps."""
    ratio = diag["intensity_texture_ratio"] = intensity_texture_ratio(lum[0], lum[1:], torch.as_tensor(reg.params),
                                                                      model=model)
    if ratio >= POLARIZATION_ONLY_TEXTURE:
        return aperture
    what = (f"registration: the sums of orthogonal analyzer images are nearly flat (texture ratio {ratio:.3f} < "
            f"{POLARIZATION_ONLY_TEXTURE}): the scene's structure is in its polarization, and a motion common to the "
            "45 and 135 deg apertures leaves every intensity criterion unchanged")
    lost = sorted(set(COMMON_APERTURES) & set(fallbacks))
    if parameters.polarization_cue_radius > 0 and lost:
        diag["polarization_cue"] = {"kept": False, "skipped": f"apertures {lost} fell back to the identity, so the "
                                    "relative warp of the 45/135 pair is unknown"}
    elif parameters.polarization_cue_radius > 0:
        aperture, cue = refine_common_motion(lum, valid, aperture, parameters)
        diag["polarization_cue"] = cue
        if cue["kept"]:
            rough = cue["roughness"]
            warn(diag, f"{what}; it was set by the smoothness of the linear polarization (roughness "
                 f"{rough['intensity_warps']:.3g} -> {rough['polarization_cue']:.3g}), a prior on the scene that can "
                 "leave those warps a pixel or two off: use --true-warps or calibrated warps (capssim calibrate) "
                 "where it matters")
            return aperture
    warn(diag, f"{what}, so those warps can be pixels off; use --true-warps or calibrated warps (capssim calibrate)")
    return aperture
