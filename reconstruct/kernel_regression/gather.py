"""Raw Bayer samples of the four apertures gathered around every HR pixel, and their normalized kernel sums.

Reference: B. Wronski, I. Garcia-Dorado, M. Ernst, D. Kelly, M. Krainin, C.-K. Liang, M. Levoy, P. Milanfar,
"Handheld multi-frame super-resolution", ACM TOG 38(4) (SIGGRAPH 2019), section 5 (the merge as kernel
regression, written here as a gather: each output pixel reads the samples near it).

Geometry. ``raw_h[n]`` ``(3, 3)`` maps the HR reference pixel ``p = (x, y, 1)`` to the raw pixel coordinates of
aperture ``n`` (``capssim.camera.array_geometry.raw_matrix() @ H_n``; raw pixel centres on integers). Each raw
sample ``(i, j)`` of aperture ``n`` sits on the HR grid at ``q = raw_h[n]^-1 (j, i, 1)`` (exact, computed once,
:class:`SampleField`). An HR pixel ``p`` reads, in each aperture, the ``K x K`` raw window whose top-left pixel is
``floor(raw_h[n] p) - (K/2 - 1)`` (:data:`WINDOW` = 4: every colour of the Bayer cell appears in it); the sample's
offset is ``d = q - p`` in HR pixels. A window entry outside the raw frame (an HR pixel outside, or at the edge
of, the aperture's view) has weight exactly 0.

A pass (:func:`kernel_sums`) evaluates, for one value per sample, ``num[n, k] = sum w v`` and ``den[n, k] = sum w``
over aperture ``n``'s samples of colour ``k`` in the window, with ``w = valid * exp(-d^T Q d / (2 s_k^2))``:
``Q`` ``(2, 2)`` per HR pixel (the inverse kernel covariance in HR px^-2: isotropic or steered,
:mod:`.steering`) and ``s_k`` a scale per colour. Rows of the HR grid are processed in chunks of about
:data:`CHUNK_PIXELS` pixels, so memory stays bounded on any frame size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["CHUNK_PIXELS", "WINDOW", "SampleField", "kernel_sums"]

#: raw pixels on each side of the window an HR pixel reads in every aperture
WINDOW = 4
#: the total weight of valid samples at or below which saturated ones stand in (``kernel_sums(fallback=...)``)
FALLBACK_BELOW = 1e-3
#: HR pixels per chunk of rows (x 4 apertures x WINDOW^2 entries, about 10 float32 tensors of them alive)
CHUNK_PIXELS = 1 << 14


@dataclass
class SampleField:
    """The raw samples of the four apertures, flattened, with their HR positions and colours.

    ``values`` ``(4, H*W)`` float32; ``valid`` ``(4, H*W)`` float32 (1: usable, 0: saturated or masked);
    ``pos`` ``(4, 2, H*W)`` float32 HR ``(x, y)`` of each sample; ``colour`` ``(H*W,)`` int64 colour index
    (0 R, 1 G, 2 B) of each raw site; ``raw_h`` ``(4, 3, 3)`` float64 HR -> raw maps; ``raw_hw`` ``(H, W)``.
    """

    values: torch.Tensor
    valid: torch.Tensor
    pos: torch.Tensor
    colour: torch.Tensor
    raw_h: torch.Tensor
    raw_hw: tuple[int, int]

    @classmethod
    def build(cls, raw: torch.Tensor, valid: torch.Tensor, raw_h: np.ndarray, cfa_colours) -> "SampleField":
        """``raw`` ``(4, H, W)``, ``valid`` ``(4, H, W)`` (bool or float), ``raw_h`` ``(4, 3, 3)`` HR -> raw,
        ``cfa_colours`` the colour index of raw sites (0,0), (0,1), (1,0), (1,1)."""
        n_ap, h, w = raw.shape
        device = raw.device
        hmat = torch.as_tensor(np.asarray(raw_h, dtype=np.float64), device=device)
        inv = torch.linalg.inv(hmat)
        ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64, device=device),
                                torch.arange(w, dtype=torch.float64, device=device), indexing="ij")
        pts = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.ones(h * w, dtype=torch.float64, device=device)])
        hr = torch.einsum("nij,jp->nip", inv, pts)  # (4, 3, H*W)
        pos = (hr[:, :2] / hr[:, 2:3]).to(torch.float32)
        table = torch.as_tensor(np.asarray(cfa_colours, dtype=np.int64).reshape(2, 2), device=device)
        colour = table[torch.arange(h, device=device)[:, None] % 2, torch.arange(w, device=device)[None, :] % 2]
        return cls(raw.reshape(n_ap, -1).to(torch.float32), valid.reshape(n_ap, -1).to(torch.float32), pos,
                   colour.reshape(-1), hmat, (h, w))


def _window(field: SampleField, rows: tuple[int, int], width: int):
    """The window of every HR pixel of rows ``rows`` (``[r0, r1)``, ``width`` columns) in every aperture:
    flat sample indices ``(4, P, K*K)`` int64, in-frame mask ``(4, P, K*K)`` float32 and the HR pixels' ``(x, y)``
    ``(P,)`` each."""
    device = field.values.device
    h, w = field.raw_hw
    ys, xs = torch.meshgrid(torch.arange(rows[0], rows[1], dtype=torch.float64, device=device),
                            torch.arange(width, dtype=torch.float64, device=device), indexing="ij")
    px, py = xs.reshape(-1), ys.reshape(-1)
    src = torch.einsum("nij,jp->nip", field.raw_h, torch.stack([px, py, torch.ones_like(px)]))
    rx, ry = src[:, 0] / src[:, 2], src[:, 1] / src[:, 2]  # (4, P) raw coordinates
    base_x = torch.floor(rx).to(torch.int64) - (WINDOW // 2 - 1)
    base_y = torch.floor(ry).to(torch.int64) - (WINDOW // 2 - 1)
    offs = torch.arange(WINDOW, device=device)
    ix = (base_x[..., None, None] + offs[None, None, None, :]).expand(-1, -1, WINDOW, WINDOW)
    iy = (base_y[..., None, None] + offs[None, None, :, None]).expand(-1, -1, WINDOW, WINDOW)
    ix, iy = ix.reshape(*ix.shape[:2], -1), iy.reshape(*iy.shape[:2], -1)
    inside = ((ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)).to(torch.float32)
    flat = iy.clamp(0, h - 1) * w + ix.clamp(0, w - 1)
    return flat, inside, px.to(torch.float32), py.to(torch.float32)


def _moments(weight, v, dx, dy, onehot, linear: bool):
    """Per aperture and colour: ``sum w v`` and ``sum w`` (``linear``: with their first and second moments)."""
    wv = weight * v
    if linear:
        wv = torch.stack([wv, wv * dx, wv * dy])
        weight = torch.stack([weight, weight * dx, weight * dy, weight * dx * dx, weight * dx * dy, weight * dy * dy])
    return (torch.einsum("...npk,npkc->...ncp", wv, onehot), torch.einsum("...npk,npkc->...ncp", weight, onehot))


def kernel_sums(field: SampleField, values: torch.Tensor, inv_cov: torch.Tensor, colour_scale, *,
                fallback: float = 0.0, linear: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One pass of kernel regression (module docstring): ``(num, den, seen)``, each ``(4, 3, Ho, Wo)``; ``seen``
    (bool) says where an aperture's valid samples of a colour have a total weight above :data:`FALLBACK_BELOW`.

    Parameters
    ----------
    values : torch.Tensor
        ``(4, H*W)`` one value per raw sample (e.g. ``2 * raw``, or a ratio).
    inv_cov : torch.Tensor
        ``(3, Ho, Wo)``: ``(Qxx, Qxy, Qyy)`` of each output pixel, HR px^-2; the output grid is ``Ho x Wo``.
    colour_scale : sequence of 3 float
        The kernel's scale ``s_k`` per colour (its std multiplies by ``s_k``).
    fallback : float
        0: the samples with ``valid = 0`` (saturated ones) are left out; above 0: they are used (with their kernel
        weight) for an aperture and colour only where its valid samples' total weight is at most
        :data:`FALLBACK_BELOW` (none in reach: the clip level is then the best bound).
    linear : bool
        Also the first moments, for a local linear fit: ``num`` ``(3, 4, 3, Ho, Wo)`` holds ``sum w v (1, dx, dy)``
        and ``den`` ``(6, 4, 3, Ho, Wo)`` ``sum w (1, dx, dy, dx^2, dx dy, dy^2)``.
    """
    ho, wo = inv_cov.shape[-2:]
    device = values.device
    inv_s2 = torch.as_tensor([0.5 / float(s) ** 2 for s in colour_scale], dtype=torch.float32, device=device)
    onehot = torch.nn.functional.one_hot(field.colour, 3).to(torch.float32)  # (H*W, 3)
    lead = (3,) if linear else ()
    num = torch.empty(*lead, 4, 3, ho * wo, dtype=torch.float32, device=device)
    den = torch.empty(*((6,) if linear else ()), 4, 3, ho * wo, dtype=torch.float32, device=device)
    seen = torch.empty(4, 3, ho * wo, dtype=torch.float32, device=device)
    step = max(1, CHUNK_PIXELS // max(wo, 1))
    for r0 in range(0, ho, step):
        r1 = min(ho, r0 + step)
        flat, inside, px, py = _window(field, (r0, r1), wo)
        dx = torch.gather(field.pos[:, 0], 1, flat.reshape(4, -1)).reshape(flat.shape) - px[None, :, None]
        dy = torch.gather(field.pos[:, 1], 1, flat.reshape(4, -1)).reshape(flat.shape) - py[None, :, None]
        q = inv_cov[:, r0:r1].reshape(3, -1)
        form = (q[0][None, :, None] * dx * dx + 2 * q[1][None, :, None] * dx * dy + q[2][None, :, None] * dy * dy)
        col = field.colour[flat]  # (4, P, K*K)
        weight = torch.exp(-form * inv_s2[col])
        valid = torch.gather(field.valid, 1, flat.reshape(4, -1)).reshape(flat.shape)
        v = torch.gather(values, 1, flat.reshape(4, -1)).reshape(flat.shape)
        oh = onehot[flat]  # (4, P, K*K, 3)
        n_v, d_v = _moments(weight * inside * valid, v, dx, dy, oh, linear)
        if fallback > 0:  # the saturated samples, only where no valid one is in reach
            n_s, d_s = _moments(weight * inside * (1.0 - valid), v, dx, dy, oh, linear)
        seen[..., r0 * wo:r1 * wo] = d_v[0] if linear else d_v
        if fallback > 0:
            alone = seen[..., r0 * wo:r1 * wo] <= FALLBACK_BELOW
            n_v, d_v = torch.where(alone, n_v + n_s, n_v), torch.where(alone, d_v + d_s, d_v)
        num[..., r0 * wo:r1 * wo], den[..., r0 * wo:r1 * wo] = n_v, d_v
    return (num.reshape(*num.shape[:-1], ho, wo), den.reshape(*den.shape[:-1], ho, wo),
            seen.reshape(4, 3, ho, wo) > FALLBACK_BELOW)
