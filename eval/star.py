"""The sinusoidal Siemens star: synthesis, ring x segment fits and its centre (paper fig. 14-15).

Reference: ISO 12233:2014 Annex E (sinusoidal Siemens star, "s-SFR"); Loebich et al.,
"Digital camera resolution measurement using sinusoidal Siemens stars", Proc. SPIE 6502
(2007). The star's intensity is ``mean * (1 + m cos(N phi + phi0))`` with ``N`` cycles per
turn, so a circle of radius ``r`` carries ``f = N / (2 pi r)`` cycles per pixel. Angles: 0
along +col, counter-clockwise (up).

* :func:`sinusoidal_star`: an analytic star, optionally blurred and pixel-integrated (tests,
  examples, the synthetic benchmark scene);
* :func:`fit_rings`: in each ring x 45-degree segment the pixel values themselves are fitted
  by least squares with ``a + b cos(N phi) + c sin(N phi)`` at each pixel's exact angle
  (no resampling along arcs), in one vectorized pass of ``bincount`` sums;
* :func:`find_star_center`: where the bars' radial lines meet (a robust least-squares fit of
  the gradient directions), refined by the fitted phases of the ring segments.

:mod:`capssim.eval.mtf` turns the ring fits into the MTF.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter, sobel, uniform_filter

from capssim.errors import InputError

SEGMENT_CENTRES_DEG = tuple(range(0, 360, 45))
MIN_PIXELS_PER_FIT = 6


# -- a sinusoidal star, analytic (tests, examples) -----------------------------------------------
def sinusoidal_star(shape: tuple[int, int], cycles: int, *, center_rowcol: tuple[float, float] | None = None,
                    radius: float | None = None, mean: float = 0.5, modulation: float = 1.0,
                    phase_rad: float = 0.0, blur_sigma: float = 0.0, pixel_box: float = 0.0,
                    supersample: int = 8, background: float | None = None) -> np.ndarray:
    """A ``(H, W)`` float64 sinusoidal Siemens star ``mean * (1 + modulation cos(N phi + phase))``.

    ``blur_sigma`` (pixels) applies an exact Gaussian blur and ``pixel_box`` (pixels) a box
    (pixel integration) of that width; both are computed on a ``supersample``-times finer
    grid and the result is *point-sampled* at the pixel centres, so the only MTF is
    ``exp(-2 pi^2 sigma^2 f^2) * sinc(box f)``. Outside ``radius`` the value is
    ``background`` (default: ``mean``). Angles: 0 along +col, counter-clockwise (up).
    """
    h, w = shape
    cy, cx = center_rowcol if center_rowcol is not None else ((h - 1) / 2, (w - 1) / 2)
    s = int(supersample)
    # fine grid: s samples per pixel, the pixel centre at index s//2 of each group (odd s ideal)
    if s % 2 == 0:
        s += 1
    fine_r = (np.arange(h * s) - s // 2) / s
    fine_c = (np.arange(w * s) - s // 2) / s
    rr, cc = np.meshgrid(fine_r - cy, fine_c - cx, indexing="ij")
    phi = np.arctan2(-rr, cc)
    img = mean * (1.0 + modulation * np.cos(cycles * phi + phase_rad))
    if radius is not None:
        img = np.where(np.hypot(rr, cc) <= radius, img, mean if background is None else background)
    if blur_sigma > 0:
        img = gaussian_filter(img, blur_sigma * s, mode="nearest", truncate=5.0)
    if pixel_box > 0:
        img = uniform_filter(img, size=max(1, int(round(pixel_box * s))), mode="nearest")
    return img[s // 2::s, s // 2::s][:h, :w].copy()


# -- centre --------------------------------------------------------------------------------------
def find_star_center(image: np.ndarray, *, cycles: int | None = None,
                     initial_rowcol: tuple[float, float] | None = None) -> tuple[float, float]:
    """Centre ``(row, col)`` of a Siemens star: where the radial lines of its bars meet.

    Each strong-gradient pixel ``p`` contributes the constraint ``g . (c - p) = 0`` (its
    gradient ``g`` is tangential). The weighted least-squares solution is refined by
    iteratively reweighting with a shrinking tolerance on the angle between ``g`` and the
    radial direction, which rejects the star's outer rim, the aliased core and clutter.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise InputError("image", f"shape {img.shape}", "a 2-D image")
    sm = gaussian_filter(img, 1.0)
    gr, gc = sobel(sm, axis=0), sobel(sm, axis=1)
    mag2 = gr * gr + gc * gc
    if not np.any(mag2 > 0):
        raise InputError("image", "a flat image", "an image of a Siemens star")
    strong = mag2 >= np.quantile(mag2, 0.7)
    rows, cols = np.nonzero(strong)
    g = np.stack([gr[strong], gc[strong]], axis=1)
    p = np.stack([rows, cols], axis=1).astype(np.float64)
    gn = g / np.sqrt(np.maximum((g * g).sum(1, keepdims=True), 1e-300))

    def solve(weights):
        a = np.einsum("n,ni,nj->ij", weights, g, g)
        b = np.einsum("n,ni,nj,nj->i", weights, g, g, p)
        if np.linalg.cond(a) > 1e12:
            return None
        return np.linalg.solve(a, b)

    centre = np.asarray(initial_rowcol, dtype=np.float64) if initial_rowcol is not None else solve(np.ones(len(p)))
    if centre is None:
        centre = np.array([(img.shape[0] - 1) / 2, (img.shape[1] - 1) / 2])
    core = (cycles / math.pi) if cycles else 3.0  # radius of the aliased core (f > 0.5)
    for tol in (0.7, 0.5, 0.35, 0.25, 0.18, 0.12, 0.12, 0.12):
        d = p - centre
        dist = np.sqrt((d * d).sum(1))
        cosang = np.abs((gn * d).sum(1)) / np.maximum(dist, 1e-9)
        wts = np.where((cosang < tol) & (dist > core), (1 - (cosang / tol) ** 2) ** 2, 0.0)
        if wts.sum() < 10:
            break
        new = solve(wts)
        if new is None:
            break
        centre = new
    if cycles:
        for _ in range(3):
            centre = _refine_centre_by_phase(img, centre, int(cycles))
    return float(centre[0]), float(centre[1])


def _refine_centre_by_phase(img: np.ndarray, centre, cycles: int) -> np.ndarray:
    """One Gauss-Newton step on the centre from the fitted phases of the ring segments.

    With the assumed centre off by ``delta`` (row, col), the phase fitted in the segment at
    angle theta and radius r is ``psi0 - (N / r)(cos(theta) delta_row + sin(theta) delta_col)``;
    a weighted least-squares fit of (psi0, delta) over mid-frequency rings gives delta.
    """
    h, w = img.shape
    r_border = min(centre[0], centre[1], h - 1 - centre[0], w - 1 - centre[1])
    r_lo = max(5.0, cycles / (2 * math.pi * 0.25))
    if r_border < r_lo + 4:
        return np.asarray(centre)
    edges = ring_edges(r_lo, r_border, 0.06)
    fits = fit_rings(img, centre, cycles, edges)
    amp, ok = fits["amplitude"], fits["ok"]
    if not ok.any():
        return np.asarray(centre)
    ok &= amp > 0.2 * np.nanmax(np.where(ok, amp, np.nan))
    ok &= np.isfinite(fits["phase"])
    if ok.sum() < 12:
        return np.asarray(centre)
    theta = np.deg2rad(np.asarray(SEGMENT_CENTRES_DEG, dtype=np.float64))[None, :].repeat(len(amp), 0)[ok]
    rad = fits["radius"][ok]
    psi = fits["phase"][ok]
    wts = amp[ok] ** 2 * fits["n"][ok]
    ref = np.angle(np.sum(wts * np.exp(1j * psi)))
    dpsi = np.angle(np.exp(1j * (psi - ref)))
    design = np.stack([np.ones_like(rad), -(cycles / rad) * np.cos(theta), -(cycles / rad) * np.sin(theta)], axis=1)
    sw = np.sqrt(wts)
    sol, *_ = np.linalg.lstsq(design * sw[:, None], dpsi * sw, rcond=None)
    delta = sol[1:]
    if not np.all(np.isfinite(delta)) or np.hypot(*delta) > 2.0:
        return np.asarray(centre)
    return np.asarray(centre) - delta


def ring_edges(r_min: float, r_max: float, ring_width: float) -> np.ndarray:
    """Ring boundaries (px) from ``r_min`` to at most ``r_max``: each ring at least 1 px and ``ring_width`` r wide."""
    edges = [r_min]
    while edges[-1] < r_max:
        r = edges[-1]
        # at least 1 px, the relative width, and ~12 pixels per 45-degree segment (8 * 12 / 2 pi r)
        edges.append(r + max(1.0, ring_width * r, 15.0 / max(r, 1.0)))
    if len(edges) > 2 and edges[-1] > r_max:  # never reach past r_max: drop the partial outer ring
        edges.pop()
    return np.asarray(edges)


def fit_rings(img: np.ndarray, centre, cycles: int, edges: np.ndarray, segment_width_deg: float = 45.0):
    """Least-squares fits of ``a + b cos(N phi) + c sin(N phi)`` per ring x 45-degree segment.

    Returns a dict of ``(K, 8)`` arrays (K rings, segments centred on :data:`SEGMENT_CENTRES_DEG`):
    ``n`` pixels, ``mean`` (a), ``amplitude`` (sqrt(b^2 + c^2)), ``phase``, ``residual_rms`` (per
    degree of freedom), ``radius`` (mean pixel radius) and ``ok`` (the fit is determined).
    """
    h, w = img.shape
    rows = np.arange(h)[:, None] - centre[0]
    cols = np.arange(w)[None, :] - centre[1]
    rad = np.sqrt(rows * rows + cols * cols)
    inside = (rad >= edges[0]) & (rad < edges[-1])
    r = rad[inside]
    v = img[inside]
    phi = np.arctan2(-np.broadcast_to(rows, img.shape)[inside], np.broadcast_to(cols, img.shape)[inside])
    ring = np.searchsorted(edges, r, side="right") - 1
    seg_deg = (np.rad2deg(phi) + 22.5) % 360.0
    seg = (seg_deg // 45.0).astype(np.int64)
    off_centre = np.abs(seg_deg - seg * 45.0 - 22.5) <= segment_width_deg / 2
    k_rings = len(edges) - 1
    idx = ring * 8 + seg
    keep = off_centre & (ring >= 0) & (ring < k_rings)
    idx, r, v, phi = idx[keep], r[keep], v[keep], phi[keep]
    co, si = np.cos(cycles * phi), np.sin(cycles * phi)
    n_bins = k_rings * 8

    def s(x):
        return np.bincount(idx, weights=x, minlength=n_bins)

    n = np.bincount(idx, minlength=n_bins).astype(np.float64)
    sc, ss, scc, sss, scs = s(co), s(si), s(co * co), s(si * si), s(co * si)
    sv, svc, svs, svv = s(v), s(v * co), s(v * si), s(v * v)
    sr = s(r)
    a = np.empty((n_bins, 3, 3))
    a[:, 0, 0], a[:, 0, 1], a[:, 0, 2] = n, sc, ss
    a[:, 1, 0], a[:, 1, 1], a[:, 1, 2] = sc, scc, scs
    a[:, 2, 0], a[:, 2, 1], a[:, 2, 2] = ss, scs, sss
    rhs = np.stack([sv, svc, svs], axis=1)
    ok = n >= MIN_PIXELS_PER_FIT
    ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], a, np.eye(3)))) > 1e-9 * np.maximum(n, 1) ** 3
    beta = np.full((n_bins, 3), np.nan)
    if ok.any():
        beta[ok] = np.linalg.solve(a[ok], rhs[ok][..., None])[..., 0]
    ss_res = svv - np.einsum("ni,ni->n", np.nan_to_num(beta), rhs)
    ss_res = np.maximum(ss_res, 0.0)
    dof = np.maximum(n - 3, 1)
    out = {
        "n": n.reshape(k_rings, 8),
        "mean": beta[:, 0].reshape(k_rings, 8),
        "amplitude": np.hypot(beta[:, 1], beta[:, 2]).reshape(k_rings, 8),
        "phase": np.arctan2(-beta[:, 2], beta[:, 1]).reshape(k_rings, 8),
        "residual_rms": np.sqrt(ss_res / dof).reshape(k_rings, 8),
        "radius": (sr / np.maximum(n, 1)).reshape(k_rings, 8),
        "ok": ok.reshape(k_rings, 8),
    }
    return out
