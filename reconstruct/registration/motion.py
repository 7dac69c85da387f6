"""Motion models and cubic-spline interpolation of the registration engine
(:mod:`capssim.reconstruct.registration.engine`).

* **Motion models** (:data:`MOTION_MODELS`), parameterised in pixels of displacement at the
  image radius, so every parameter has the same scale for the optimiser.
* **Interpolation**: an interpolating cubic B-spline (:func:`spline_coefficients`,
  :func:`spline_sample`; Unser 1999, Sigg & Hadwiger 2005). torch's ``bicubic`` (Keys,
  a = -0.75) is *not* used: its shift bias depends on the sub-pixel phase
  (``docs/notes/registration-internals.md``), while the cubic spline reproduces polynomials up
  to degree 3.

All coordinates are ``(x=col, y=row)`` with pixel centres on integers.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from capssim.errors import UnknownNameError

from ..filters import correlate

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
    x = img
    for dim in (2, 1):  # along the width (a 1 x K kernel), then the height (K x 1)
        pad = min(taps, x.shape[dim] - 1)
        if pad > 0:
            weights = [math.sqrt(3.0) * _SPLINE_POLE ** abs(k) for k in range(-pad, pad + 1)]
            kernel = torch.tensor([w / sum(weights) for w in weights], dtype=torch.float64)
            x = correlate(x, kernel[None] if dim == 2 else kernel[:, None], padding="reflect")
    return x


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

    xs, ys = xy.unbind(-1)  # (not selects: their backward fills a zero tensor of the whole input each)
    (x0, x1), (gx0, gx1) = fold(xs)
    (y0, y1), (gy0, gy1) = fold(ys)
    sx, sy = 2.0 / max(ww - 1, 1), 2.0 / max(hh - 1, 1)
    gx = torch.cat([x0, x1, x0, x1], 1) * sx - 1
    gy = torch.cat([y0, y0, y1, y1], 1) * sy - 1
    taps = F.grid_sample(coeffs[:, None], torch.stack([gx, gy], -1), mode="bilinear", padding_mode="reflection",
                         align_corners=True)[:, 0]  # (B, 4, N)
    gx0, gx1, gy0, gy1 = gx0.squeeze(1), gx1.squeeze(1), gy0.squeeze(1), gy1.squeeze(1)
    t00, t01, t10, t11 = taps.unbind(1)
    out = gy0 * (gx0 * t00 + gx1 * t01) + gy1 * (gx0 * t10 + gx1 * t11)
    return out.reshape(out_shape)

