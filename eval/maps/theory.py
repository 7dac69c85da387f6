"""The theory beside a design map: how much the array's sampling can resolve at a cell's poses, and eq. 5-8.

**Conditioning of the stacked sampling.** For a grey, unpolarized scene every one of the 16 Bayer sub-images
(4 apertures x 4 Bayer sites) sees the same HR image ``x``; the stacked operator

    A x = [M_0 x; ...; M_15 x],   M_m = Decimate_site(q) IntegrateDecimate_2 Blur_psf Warp_{H_n}   (eq. 11)

of :func:`capssim.operators.camera.lr_sampling_operator` then has as many rows as ``x`` has pixels. With the four
apertures at the same sub-pixel phase (all ``H_n`` equal up to whole raw pixels) the four apertures repeat one
another and ``rank A = N / 4``: the array carries no information beyond one aperture. At the half-pixel pattern
(offsets (0,0), (1,0), (0,1), (1,1) HR px) the samples fall on every HR phase and ``A`` is a 2x2 box filter
(times the PSF) sampled at every HR pixel, full rank except near the box's zero at the Nyquist frequency.

:func:`sampling_conditioning` builds ``A`` densely on a small ``n x n`` HR grid (default 16: 256 unknowns) at
the poses of a capture (each aperture's local shift, rotation and scale at the image centre, re-centred on the
small grid) and reports its singular values ``s``: ``sigma_min_rel = s_min / s_max`` and ``resolved_fraction``,
the share of ``s`` above ``0.1 s_max`` (1/4 for co-phased apertures, close to 1 at half-pixel phases).

**Design numbers.** :func:`design_numbers` gives eq. 5-8 of :mod:`capssim.camera.design` at the paper's
prototype (and at a map's ``depth_m``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.design import DesignInputs, system_design
from capssim.camera.homography import apply_homography, rotation_and_scale, similarity
from capssim.conventions import N_APERTURES, N_LR_IMAGES
from capssim.errors import InputError
from capssim.operators.camera import lr_sampling_operator

#: singular values above this share of the largest count as resolved
RESOLVED_THRESHOLD = 0.1
#: the small HR grid's side (HR px, a multiple of 4)
THEORY_GRID = 16


def local_poses(aperture_homographies, hr_shape) -> list[tuple[float, float, float, float]]:
    """``(dx, dy, rotation_deg, scale)`` of each aperture at the HR grid's centre: the displacement of the
    centre (HR px) and the rotation and scale of the linear part (:func:`rotation_and_scale`)."""
    h = np.asarray(aperture_homographies, dtype=np.float64)
    centre = np.array([(hr_shape[1] - 1) / 2.0, (hr_shape[0] - 1) / 2.0])
    poses = []
    for hom in h:
        moved = apply_homography(hom / hom[2, 2], centre)
        rot, scale = rotation_and_scale(hom / hom[2, 2])
        poses.append((float(moved[0] - centre[0]), float(moved[1] - centre[1]), -rot, scale))
    return poses


def stacked_sampling_matrix(poses, psf_kernel, *, n: int = THEORY_GRID) -> np.ndarray:
    """The dense ``(n^2, n^2)`` matrix of the stacked sampling ``A`` (module docstring) on an ``n x n`` HR grid.

    ``poses``: four ``(dx, dy, rotation_deg, scale)`` (HR px, degrees; :func:`local_poses`), each a similarity
    about the small grid's centre; ``psf_kernel``: the ``(k, k)`` HR PSF.
    """
    if n % 4 or n < 8:
        raise InputError("n", n, "a multiple of 4 that is at least 8")
    centre = ((n - 1) / 2.0, (n - 1) / 2.0)
    mats = np.stack([similarity((dx, dy), rot, scale, centre) for dx, dy, rot, scale in poses])
    op = lr_sampling_operator(ArrayGeometry(mats, (n, n)), np.asarray(psf_kernel, dtype=np.float64))
    side = n // 4  # a sub-image's side
    rows = np.empty((N_LR_IMAGES, side, side, n * n))
    probe = torch.zeros(N_LR_IMAGES, side, side, dtype=torch.float64)
    with torch.no_grad():  # slice m of the adjoint is M_m^T y_m: one call gives row (m, i, j) of every m
        for i in range(side):
            for j in range(side):
                probe.zero_()
                probe[:, i, j] = 1.0
                rows[:, i, j] = op.adjoint(probe).reshape(N_LR_IMAGES, -1).numpy()
    return rows.reshape(N_LR_IMAGES * side * side, n * n)


def sampling_conditioning(poses, psf_kernel, *, n: int = THEORY_GRID) -> dict:
    """Singular-value summary of :func:`stacked_sampling_matrix`: ``sigma_min_rel`` (``s_min / s_max``),
    ``resolved_fraction`` (share of ``s > 0.1 s_max``), ``condition`` (``s_max / s_min``, inf when singular)
    and ``grid`` (``n``)."""
    if len(poses) != N_APERTURES:
        raise InputError("poses", len(poses), f"{N_APERTURES} aperture poses")
    s = np.linalg.svd(stacked_sampling_matrix(poses, psf_kernel, n=n), compute_uv=False)
    s_max, s_min = float(s[0]), float(s[-1])
    rel = s_min / s_max if s_max > 0 else 0.0
    return {"sigma_min_rel": rel, "resolved_fraction": float(np.mean(s > RESOLVED_THRESHOLD * s_max)),
            "condition": (s_max / s_min) if s_min > 1e-12 * s_max else math.inf, "grid": int(n)}


def regular_offsets(offset_px: float) -> np.ndarray:
    """``(4, 3, 3)``: apertures 0-3 shifted by (0,0), (d,0), (0,d), (d,d) HR px (``d = offset_px``, x then y)."""
    d = float(offset_px)
    return np.stack([similarity(shift) for shift in ((0.0, 0.0), (d, 0.0), (0.0, d), (d, d))])


def design_numbers(*, depth_m: float | None = None) -> dict:
    """Eq. 5-8 at the paper's prototype (:class:`capssim.camera.design.DesignInputs`), at ``depth_m`` when given:
    ``r_sr`` (eq. 5), what limits it, the overlap width (m, eq. 6) and the horizontal field of view (deg, eq. 7)."""
    inputs = DesignInputs() if depth_m is None else DesignInputs(depth_m=float(depth_m))
    d = system_design(inputs)
    return {"r_sr": d["r_sr"], "sr_limited_by": d["sr_limited_by"], "overlap_width_m": d["overlap_width_m"],
            "fov_h_deg": d["fov_h_deg"], "depth_m": inputs.depth_m}
