"""``dofp-eari``: edge-aware residual interpolation (EARI) for colour-polarization DoFP mosaics.

Reference: M. Morimatsu, Y. Monno, M. Tanaka, M. Okutomi, "Monochrome and color polarization
demosaicking using edge-aware residual interpolation", IEEE ICIP 2020 (arXiv:2007.14292). The
colour stage is residual interpolation: D. Kiku, Y. Monno, M. Tanaka, M. Okutomi, "Beyond color
difference: residual interpolation for color image demosaicking", IEEE TIP 25(3), 2016.
Implemented from the papers' descriptions (the authors' MATLAB code is research-only and was
only read to settle details).

Steps, for a mosaic ``M`` ``(H, W)`` on [0, 1]:

1. Colour (CPFA stage 1). Each polarizer sub-mosaic ``M[dr::2, dc::2]`` is an RGGB Bayer
   image; demosaick it by residual interpolation
   (:func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic`): directional (horizontal/vertical) MLRI
   estimates of the colour differences ``G - R``, ``G - B``, combined with gradient weights into
   a full green; then R and B by MLRI guided upsampling under the green, with bilinear residuals.
2. Put the RGB of each sub-mosaic back at its own lattice: the "RGB polarization mosaic" ``P``
   ``(3, H, W)``, every pixel carrying the three colours of its own polarizer angle.
3. Edge-aware guide, per colour (:func:`edge_aware_guide`). Any 2x2 window holds one pixel of
   each angle, and ``I0 + I90 = I45 + I135``, so its mean is the intensity ``S0/2`` there.
   Four directional intensities ``X_n, X_s, X_w, X_e`` are the means of the two 2x2 windows
   above / below / left / right of the pixel (2x3 kernels ``[1 2 1; 1 2 1]/8``). Their edge
   indicators are ``|(P_b - P_a) - (P_d - P_c)|`` over the same 2x3 window, which is zero for any
   polarization state on flat intensity (it cancels because ``I0 + I90 = I45 + I135``) and
   responds to intensity edges between the two rows (columns); averaged over the 3x5 (5x3)
   half-window on that side it gives ``w_d``. Guide ``= sum_d X_d / (w_d + eps_e) / sum_d 1 / (w_d + eps_e)``.
4. Residual interpolation of every (angle, colour) lattice under that colour's guide
   (:func:`capssim.reconstruct.dofp.residual_interpolation.residual_interpolation`): MLRI tentative estimate in 11x11
   windows with the step-2 Laplacian, clipped, plus the bilinearly interpolated residual.

Numerical choices where the descriptions are silent (their measured cost: docs, notes/dofp-eari.md):

* ``eps`` of the MLRI slope: 1e-10 (on [0, 1] data) instead of the reference code's 1e-32, which
  makes the slope a ratio of rounding noise where the guide's Laplacian vanishes;
* window weights ``1 / max(e_k, weight_floor)`` with ``weight_floor = 0.01 / 255^2``: the RI
  papers' threshold 0.01 on 8-bit-scale data rescaled to [0, 1] (``weight_floor=0.01`` gives the
  reference code's variant);
* intermediate estimates and the output are clipped to ``[0, max(1, max(M))]``;
* filters mirror-pad (``x[-k] = x[k]``), which keeps the mosaic phase at the borders.
"""

from __future__ import annotations

import torch

from capssim.captures.capture import Capture

from ..dofp.bilinear import dofp_unobserved
from ..dofp.method_body import run_dofp_method
from ..dofp.mosaic import (
    as_output,
    check_mosaic,
    clip_ceiling,
    merge_submosaics,
    split_submosaics,
    stack_12,
)
from ..dofp.residual_interpolation import (
    RI_BAYER_DEFAULTS,
    polarization_residual_interpolation,
    ri_bayer_demosaic,
)
from ..filters import correlate
from ..registry import MethodOutput, RunContext, register_method
from ..run_context import stage_factory

REFERENCE = ("Morimatsu, Monno, Tanaka, Okutomi, 'Monochrome and color polarization demosaicking using edge-aware "
             "residual interpolation', IEEE ICIP 2020; colour stage: Kiku et al., 'Beyond color difference: residual "
             "interpolation for color image demosaicking', IEEE TIP 25(3) 2016")

DEFAULTS = {"eps": RI_BAYER_DEFAULTS["eps"], "weight_floor": RI_BAYER_DEFAULTS["weight_floor"], "edge_eps": 1e-32,
            "bayer_sigma": RI_BAYER_DEFAULTS["bayer_sigma"]}


# 2x3 directional intensity kernel (mean of two 2x2 windows), north side; others by flip/transpose
_INTENSITY_N = ((1 / 8, 1 / 4, 1 / 8), (1 / 8, 1 / 4, 1 / 8), (0.0, 0.0, 0.0))
# directional edge indicator, north side: (P(y-1,x) - mean P(y-1,x+-1)) - (P(y,x) - mean P(y,x+-1))
_EDGE_N = ((-0.5, 1.0, -0.5), (0.5, -1.0, 0.5), (0.0, 0.0, 0.0))
# 3x5 smoothing of the edge indicator over the north half-window
_SMOOTH_N = tuple(tuple(1 / 15 for _ in range(5)) if r < 3 else tuple(0.0 for _ in range(5)) for r in range(5))


def _four_directions(kernel_north):
    """North, south, west, east versions of a kernel given for the north side."""
    k = torch.as_tensor(kernel_north, dtype=torch.float64)
    south = torch.flip(k, dims=(0,))
    return k, south, k.T, south.T


def edge_aware_guide(pol_mosaic: torch.Tensor, *, edge_eps: float = DEFAULTS["edge_eps"]) -> torch.Tensor:
    """EARI guide image (ICIP 2020, section 2.2) of polarization mosaics ``(..., H, W)``.

    ``pol_mosaic``: each pixel holds the value of its own polarizer angle (one colour). Returns
    the edge-aware intensity ``(..., H, W)``, an estimate of ``(I0 + I45 + I90 + I135) / 4``.
    """
    x = pol_mosaic
    intensities = [correlate(x, k.to(x.dtype)) for k in _four_directions(_INTENSITY_N)]
    edges = [correlate(x, k.to(x.dtype)).abs() for k in _four_directions(_EDGE_N)]
    smooth = _four_directions(_SMOOTH_N)
    weights = [1.0 / (correlate(e, s.to(x.dtype)) + edge_eps) for e, s in zip(edges, smooth)]
    num = sum(w * i for w, i in zip(weights, intensities))
    den = sum(weights)
    return num / (den + edge_eps)


def demosaic_dofp_eari(mosaic, *, layout="sony", device: str | torch.device | None = None,
                       eps: float = DEFAULTS["eps"], weight_floor: float = DEFAULTS["weight_floor"],
                       edge_eps: float = DEFAULTS["edge_eps"], bayer_sigma: float = DEFAULTS["bayer_sigma"],
                       dtype: torch.dtype | None = None, timer=None):
    """EARI demosaicking of a DoFP colour-polarization mosaic ``(H, W)`` -> ``(12, H, W)`` (``c = 3p + k``).

    ``mosaic``: float numpy array or tensor on [0, 1], even sides >= 12; numpy in gives float32
    numpy out, a tensor gives a tensor. ``layout``: the 2x2 polarizer cell. ``eps``,
    ``weight_floor``, ``edge_eps``, ``bayer_sigma``: see the module docstring. ``dtype``:
    computation precision (default float32, float64 for a float64 input).
    """
    stage = stage_factory(timer)
    x = check_mosaic(mosaic, device=device, dtype=dtype)
    ceiling = clip_ceiling(x)
    kw = dict(eps=eps, weight_floor=weight_floor, clip_max=ceiling)
    with stage("bayer_ri"):
        sub_rgb = ri_bayer_demosaic(split_submosaics(x, layout), sigma=bayer_sigma, **kw)  # (4, 3, h, w)
        pol_rgb = merge_submosaics(sub_rgb.transpose(0, 1), layout)  # (3, H, W)
    with stage("edge_aware_guide"):
        guide = edge_aware_guide(pol_rgb, edge_eps=edge_eps)  # (3, H, W)
    with stage("polarization_ri"):
        out = polarization_residual_interpolation(guide, pol_rgb, layout, **kw)  # (4, 3, H, W)
    return as_output(stack_12(out), mosaic)


@register_method("dofp-eari", input_kind="dofp", array_function=demosaic_dofp_eari,
                 description="DoFP colour-polarization camera, edge-aware residual interpolation (EARI) demosaicking",
                 reference=REFERENCE)
def dofp_eari(capture: Capture, *, context: RunContext) -> MethodOutput:
    """Demosaick ``capture.dofp_float()`` with :func:`demosaic_dofp_eari`.

    Options (``context.options``): ``eps``, ``weight_floor``, ``edge_eps``, ``bayer_sigma``,
    ``precision`` (``float32`` | ``float64``).
    """
    out = run_dofp_method(capture, context, demosaic_dofp_eari, DEFAULTS)
    out.unobserved = lambda: dofp_unobserved(capture.dofp_saturated(), capture.dofp_layout)
    return out
