"""``dofp-igri2``: intensity-guided residual interpolation (IGRI2), EARI's successor.

Reference: M. Morimatsu, Y. Monno, M. Tanaka, M. Okutomi, "Monochrome and color polarization
demosaicking based on intensity-guided residual interpolation", IEEE Sensors Journal 21(23),
2021 (IGRI2 is its two-step variant). Implemented from the paper's description; the authors'
MATLAB code (research-only) was only read to settle details.

IGRI2 replaces EARI's edge-aware guide (step 3 of :mod:`capssim.reconstruct.methods.dofp_eari`) by an
intensity guide built from two residual-interpolation passes. It relies on the orthogonal pairs
sitting on the diagonals of the 2x2 cell (true for both standard layouts): every pixel of the
quincunx ``(y + x)`` even carries one of an orthogonal pair (e.g. 90/0), the other quincunx the
other pair (45/135), and ``I_a + I_(a+90) = S0`` for any polarization state.

For each colour plane ``P`` of the RGB polarization mosaic (after EARI's colour stage):

1. Diagonal pass. Rotate each quincunx by 45 degrees onto a rectangular grid (pixel ``(y, x)``
   -> ``((y + x') / 2, (x' - y) / 2 + offset)``, ``x' = x - parity``); there the two angles of
   the pair form a checkerboard, like G against R/B in a Bayer image. Estimate each angle at the
   other's sites with the residual-interpolation green step of Kiku et al. (TIP 2016;
   :func:`capssim.reconstruct.dofp.residual_interpolation.ri_green`), which interpolates along the rotated axes, i.e. the
   image diagonals. Now each quincunx holds both angles of its pair.
2. Intensity. ``(I_a + I_(a+90)) / 2`` on each quincunx (= ``S0 / 2``).
3. Horizontal/vertical pass. For each angle: an image with that angle on its quincunx and the
   other quincunx's intensity on the rest; the same RI green step fills the angle everywhere,
   guided by the intensity (a "colour difference" of angle minus intensity).
4. Guide = mean of the four full images (an intensity estimate); final residual interpolation
   of each angle's own lattice under it, exactly as EARI step 4.

Numerical choices as in :mod:`capssim.reconstruct.methods.dofp_eari` (eps, weight floor, clipping,
mirror padding). Outside the rotated quincunx (the corners of the rotated grid) the values are
zero, as in the reference; this only affects pixels near the image border.
"""

from __future__ import annotations

import torch

from capssim.captures.capture import Capture
from capssim.conventions import dofp_layout
from capssim.errors import InputError

from ..dofp.bilinear import dofp_unobserved
from ..dofp.method_body import run_dofp_method
from ..dofp.mosaic import (
    angle_offsets,
    as_output,
    check_mosaic,
    clip_ceiling,
    merge_submosaics,
    split_submosaics,
    stack_12,
)
from ..dofp.residual_interpolation import (
    polarization_residual_interpolation,
    ri_bayer_demosaic,
    ri_green,
)
from ..registry import MethodOutput, RunContext, register_method
from ..run_context import stage_factory
from .dofp_eari import DEFAULTS

REFERENCE = ("Morimatsu, Monno, Tanaka, Okutomi, 'Monochrome and color polarization demosaicking based on "
             "intensity-guided residual interpolation', IEEE Sensors Journal 21(23) 2021 (IGRI2); colour stage: "
             "Kiku et al., IEEE TIP 25(3) 2016")


def check_diagonal_pairs(layout) -> None:
    """IGRI2 needs orthogonal angles on each diagonal of the 2x2 cell."""
    cell = dofp_layout(layout)
    for pair in ((cell[0][0], cell[1][1]), (cell[0][1], cell[1][0])):
        if abs(pair[0] - pair[1]) != 90:
            raise InputError("layout", f"{[list(r) for r in cell]}",
                             "a 2x2 cell with orthogonal angles on each diagonal (e.g. sony [[90,45],[135,0]])",
                             "Use dofp-eari or dofp-bilinear for this layout.")


class QuincunxRotation:
    """45-degree rotation of the quincunx ``(y + x) % 2 == parity`` of an ``(H, W)`` grid onto ``(U, V)``.

    Pixel ``(y, x)`` -> ``(u, v) = ((y + x') / 2, (x' - y) / 2 + offset)`` with ``x' = x - parity``;
    diagonal neighbours become horizontal/vertical neighbours. Sites with ``u + v`` odd are the
    cell offsets (1, 1) (parity 0) and (1, 0) (parity 1): the G sites of an RGGB grid. ``V`` is
    even so that a flip along ``v`` swaps the two checkerboards.
    """

    def __init__(self, height: int, width: int, parity: int, *, device=None):
        y, x = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
        sel = (y + x) % 2 == parity
        self.ys, self.xs = y[sel], x[sel]
        xp = self.xs - parity
        offset = 2 * ((height + 3) // 4)
        self.u = torch.div(self.ys + xp, 2, rounding_mode="floor")
        self.v = torch.div(xp - self.ys, 2, rounding_mode="floor") + offset
        v_size = offset + width // 2 + 1
        self.shape = ((height + width) // 2, v_size + v_size % 2)
        self.image_shape = (height, width)

    def rotate(self, image: torch.Tensor) -> torch.Tensor:
        """``(..., H, W)`` -> ``(..., U, V)``; zero outside the quincunx."""
        out = image.new_zeros((*image.shape[:-2], *self.shape))
        out[..., self.u, self.v] = image[..., self.ys, self.xs]
        return out

    def unrotate_into(self, target: torch.Tensor, rotated: torch.Tensor) -> torch.Tensor:
        """Write the quincunx values of ``rotated`` ``(..., U, V)`` into ``target`` ``(..., H, W)``."""
        target[..., self.ys, self.xs] = rotated[..., self.u, self.v]
        return target


def _green_on_even_sites(images: torch.Tensor, **kw) -> torch.Tensor:
    """RI green step targeting the ``u + v`` even checkerboard: flip along the last axis (even size)."""
    return torch.flip(ri_green(torch.flip(images, dims=(-1,)), **kw), dims=(-1,))


def intensity_guide(pol_mosaic: torch.Tensor, layout="sony", *, eps: float, weight_floor: float,
                    clip_max: float, sigma: float = DEFAULTS["bayer_sigma"]) -> torch.Tensor:
    """IGRI2 intensity guide (steps 1-4 above) of polarization mosaics ``(C, H, W)`` -> ``(C, H, W)``."""
    check_diagonal_pairs(layout)
    c, h, w = pol_mosaic.shape
    kw = dict(eps=eps, weight_floor=weight_floor, clip_max=clip_max, sigma=sigma)
    offsets = angle_offsets(layout)  # (dr, dc) per angle index p
    angle_at = {off: p for p, off in enumerate(offsets)}
    full = pol_mosaic.new_zeros((4, c, h, w))  # per angle, filled on its quincunx after step 1
    for parity in (0, 1):
        rot = QuincunxRotation(h, w, parity, device=pol_mosaic.device)
        rotated = rot.rotate(pol_mosaic)  # (C, U, V)
        odd_sites = ri_green(rotated, **kw)  # the angle at u+v odd, everywhere
        even_sites = _green_on_even_sites(rotated, **kw)  # the angle at u+v even, everywhere
        # cell offsets on this quincunx: (0,0)/(1,1) for parity 0, (0,1)/(1,0) for parity 1
        even_cell, odd_cell = ((0, 0), (1, 1)) if parity == 0 else ((0, 1), (1, 0))
        rot.unrotate_into(full[angle_at[even_cell]], even_sites)
        rot.unrotate_into(full[angle_at[odd_cell]], odd_sites)
    quincunx = ((torch.arange(h, device=pol_mosaic.device)[:, None] + torch.arange(w, device=pol_mosaic.device)[None])
                % 2).to(pol_mosaic.dtype)  # 1 on parity-1 sites
    # step 2: intensity of each quincunx = mean of its orthogonal pair (zero elsewhere after step 1)
    pair0 = [angle_at[(0, 0)], angle_at[(1, 1)]]
    pair1 = [angle_at[(0, 1)], angle_at[(1, 0)]]
    intensity = (full[pair0].sum(0) * (1 - quincunx) + full[pair1].sum(0) * quincunx) / 2  # (C, H, W)
    # step 3: each angle on its quincunx, the other quincunx's intensity elsewhere; RI green fills it
    estimates = []
    for p in range(4):
        parity = sum(offsets[p]) % 2
        own = quincunx if parity == 1 else 1 - quincunx
        mixed = full[p] * own + intensity * (1 - own)
        if parity == 1:  # own sites are the RGGB G sites ((y + x) odd)
            estimates.append(ri_green(mixed, **kw))
        else:
            estimates.append(torch.flip(ri_green(torch.flip(mixed, dims=(-1,)), **kw), dims=(-1,)))
    return torch.stack(estimates).mean(0)


def demosaic_dofp_igri2(mosaic, *, layout="sony", device: str | torch.device | None = None,
                        eps: float = DEFAULTS["eps"], weight_floor: float = DEFAULTS["weight_floor"],
                        bayer_sigma: float = DEFAULTS["bayer_sigma"], dtype: torch.dtype | None = None, timer=None):
    """IGRI2 demosaicking of a DoFP colour-polarization mosaic ``(H, W)`` -> ``(12, H, W)`` (``c = 3p + k``).

    Same interface and colour stage as :func:`capssim.reconstruct.methods.dofp_eari.demosaic_dofp_eari`;
    the layout must have orthogonal angles on its diagonals.
    """
    stage = stage_factory(timer)
    check_diagonal_pairs(layout)
    x = check_mosaic(mosaic, device=device, dtype=dtype)
    ceiling = clip_ceiling(x)
    kw = dict(eps=eps, weight_floor=weight_floor, clip_max=ceiling)
    with stage("bayer_ri"):
        sub_rgb = ri_bayer_demosaic(split_submosaics(x, layout), sigma=bayer_sigma, **kw)
        pol_rgb = merge_submosaics(sub_rgb.transpose(0, 1), layout)  # (3, H, W)
    with stage("intensity_guide"):
        guide = intensity_guide(pol_rgb, layout, sigma=bayer_sigma, **kw)
    with stage("polarization_ri"):
        out = polarization_residual_interpolation(guide, pol_rgb, layout, **kw)
    return as_output(stack_12(out), mosaic)


@register_method("dofp-igri2", input_kind="dofp", array_function=demosaic_dofp_igri2,
                 description="DoFP colour-polarization camera, intensity-guided residual interpolation (IGRI2)",
                 reference=REFERENCE)
def dofp_igri2(capture: Capture, *, context: RunContext) -> MethodOutput:
    """Demosaick ``capture.dofp_float()`` with :func:`demosaic_dofp_igri2`.

    Options (``context.options``): ``eps``, ``weight_floor``, ``bayer_sigma``, ``precision``.
    """
    out = run_dofp_method(capture, context, demosaic_dofp_igri2,
                          {k: DEFAULTS[k] for k in ("eps", "weight_floor", "bayer_sigma")})
    out.unobserved = lambda: dofp_unobserved(capture.dofp_saturated(), capture.dofp_layout)
    return out
