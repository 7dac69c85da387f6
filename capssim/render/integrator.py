"""The camera-RGB Stokes renderer: one pinhole view of a Mitsuba scene, box pixel filter,
Stokes vectors integrated against real camera sensitivities.

Why not Mitsuba's own film + ``stokes`` integrator: in spectral variants ``stokes`` converts
each Stokes component to linear sRGB (not camera RGB), and ``specfilm`` + ``stokes`` is
broken in Mitsuba 3.9.1 (``docs/notes/rendering-internals.md``). So this module drives the scene's own
(nested) integrator, ``volpath`` or ``path``, itself:

1. Rays: pixel ``(i, j)`` gets ``spp`` samples at ``(j - 0.5 + u, i - 0.5 + v)`` with
   ``(u, v)`` a scrambled (0,2)-sequence per pixel (:func:`stratified_samples`), i.e. an
   exact box pixel filter with stratified positions. The light paths use Mitsuba's
   ``multijitter`` sampler laid out per pixel (``set_samples_per_wavefront(spp)``), which
   stratifies every path dimension across a pixel's samples (far fewer samples for the same
   noise than ``independent``). ``spp`` must therefore be a perfect square (1, 4, 9, ...).
   Rays come from our own pinhole model
   (:class:`~capssim.render.pinhole_array.PinholeCamera`, pinned against Mitsuba's
   ``perspective`` sensor by a test), so the stored homographies and the renders agree.
2. Wavelengths: four per ray, importance-sampled from the camera sensitivities
   (:mod:`capssim.render.spectral`).
3. Polarization: the nested integrator returns a Mueller matrix; its first column is the
   Stokes vector of the (unpolarized-emitted) light reaching the camera. It is rotated from
   Mitsuba's implicit ray frame to the camera frame (0 deg = image right, +45 deg towards
   the image top), as ``stokes.cpp`` does.
4. Output per sample: ``S0, S1, S2`` x ``R, G, B``. ``mode="stokes"`` keeps them all;
   ``mode="analyzer"`` keeps only the RGB seen through one analyzer angle ``a``,
   ``(S0 + e (S1 cos 2a + S2 sin 2a)) / 2`` with ``e = (ER - 1) / (ER + 1)`` (1 if ideal),
   which is what one CAPS aperture sees through its own polarizer.
5. Per-pixel means and single-sample variances are reduced in numpy (float64) in a fixed
   order, so a fixed seed and variant give bit-identical images.

Kernel reuse: camera parameters, image width, spp, seeds and the chunk offset enter the
traced kernel as opaque values, so every chunk, pilot and aperture of one scene reuses one
compiled kernel (a scene renders with exactly one compile).
"""

from __future__ import annotations

import hashlib
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from capssim.errors import InputError
from capssim.render.pinhole_array import PinholeCamera
from capssim.render.spectral import CameraResponse
from capssim.stokes.polarization import twelve_from_stokes

log = logging.getLogger(__name__)

#: lanes (rays) traced per kernel launch; bounds memory at about 60 B/lane of output
DEFAULT_MAX_LANES = 1 << 21
STOKES_CHANNELS = ("S0.R", "S0.G", "S0.B", "S1.R", "S1.G", "S1.B", "S2.R", "S2.G", "S2.B")


def derive_seed(*parts) -> int:
    """A 32-bit seed from any parts (stable across runs and platforms)."""
    h = hashlib.blake2b(repr(parts).encode(), digest_size=4).digest()
    return int.from_bytes(h, "little")


@dataclass
class ViewRender:
    """One rendered view: ``mean`` ``(C, H, W)`` float64, per-sample ``variance`` of each
    output channel and, for Stokes mode, of the four analyzer images ``(12, H, W)``."""

    mean: np.ndarray
    sample_variance: np.ndarray
    spp: int
    seconds: float
    nonfinite_samples: int = 0
    lanes: int = 0
    extra: dict = field(default_factory=dict)

    def standard_error_rms(self) -> float:
        """RMS over pixels and channels of the Monte-Carlo standard error of the mean."""
        return float(np.sqrt(np.mean(self.sample_variance) / max(self.spp, 1)))


def _opaque_float(value: float):
    import drjit as dr
    import mitsuba as mi

    return dr.opaque(mi.Float, float(value))


def _opaque_vector(v) -> "object":
    import mitsuba as mi

    return mi.Vector3f(*(_opaque_float(x) for x in v))


def _reverse_bits(x):
    """Bit reversal of a ``UInt32`` array (radical inverse in base 2 before scaling)."""
    x = ((x >> 1) & 0x55555555) | ((x & 0x55555555) << 1)
    x = ((x >> 2) & 0x33333333) | ((x & 0x33333333) << 2)
    x = ((x >> 4) & 0x0F0F0F0F) | ((x & 0x0F0F0F0F) << 4)
    x = ((x >> 8) & 0x00FF00FF) | ((x & 0x00FF00FF) << 8)
    return (x >> 16) | (x << 16)


SAMPLER_TYPE = "multijitter"  # stratified per pixel along every path dimension; spp must be a square
SOBOL_BITS = 16   # enough for 65536 samples per pixel; fixed so spp does not change the kernel
RADICAL3_DIGITS = 11  # 3^11 > 65536


def _sobol2(j):
    """Second dimension of the Sobol sequence (bits reversed into the high end) for indices ``j``."""
    import mitsuba as mi

    y = mi.UInt32(0)
    v = 0x80000000
    for i in range(SOBOL_BITS):
        y = y ^ (((j >> i) & 1) * v)
        v ^= v >> 1
    return y


def _unit(bits):
    """``UInt32`` -> float in [0, 1) from the top 24 bits."""
    import mitsuba as mi

    return mi.Float(bits >> 8) * (1.0 / (1 << 24))


def _radical_inverse_3(j):
    """Base-3 radical inverse of ``UInt32`` indices (Halton's second dimension)."""
    import mitsuba as mi

    value = mi.Float(0.0)
    scale = 1.0 / 3.0
    rest = mi.UInt32(j)
    for _ in range(RADICAL3_DIGITS):
        value += mi.Float(rest % 3) * scale
        rest = rest // 3
        scale /= 3.0
    return value


def stratified_samples(pixel, j, seed, group_pixel=None, group_index=None):
    """Per-pixel stratified samples ``(u_x, u_y, u_lambda)`` for sample ``j`` of ``pixel``.

    Position: the first two Sobol dimensions (a (0,2)-sequence), XOR-scrambled by a hash of
    (pixel, seed); for ``spp`` a power of two they form a (0, m, 2)-net in every pixel (each
    elementary interval of area 1/spp holds one sample). Wavelength: the base-3 radical
    inverse with a random rotation, so it is stratified and not tied to the position; with
    ``group_pixel`` / ``group_index`` (an oversampled render) it is stratified over all the
    samples of the ground-truth pixel the render pixel belongs to.
    """
    import drjit as dr
    import mitsuba as mi

    sx, sy = mi.sample_tea_32(pixel, seed, 4)
    if group_pixel is None:
        group_pixel, group_index = pixel, j
    sl, _ = mi.sample_tea_32(group_pixel ^ 0x9E3779B9, seed, 4)
    u_l = _radical_inverse_3(group_index) + _unit(sl)
    u_l = u_l - dr.floor(u_l)
    return _unit(_reverse_bits(j) ^ sx), _unit(_sobol2(j) ^ sy), u_l


def _trace_chunk(scene, integrator, response: CameraResponse, camera: PinholeCamera, *, row0: int,
                 rows: int, spp: int, seed: int, group: int = 1):
    """Trace ``rows x width x spp`` lanes; returns per-lane numpy arrays ``[S0.RGB, S1.RGB, S2.RGB]``
    (``S1``, ``S2`` are ``None`` in unpolarized variants).

    Everything that changes between calls (camera, chunk, seed, spp, width) enters the kernel
    as an opaque value, so one compiled kernel serves every call on one scene.
    """
    import drjit as dr
    import mitsuba as mi

    width = camera.width
    n_lanes = rows * width * spp
    sampler = mi.load_dict({"type": SAMPLER_TYPE, "sample_count": int(spp)})
    sampler.set_samples_per_wavefront(int(spp))
    sampler.seed(dr.opaque(mi.UInt32, seed), n_lanes)
    idx = dr.arange(mi.UInt32, n_lanes)
    spp_o = dr.opaque(mi.UInt32, spp)
    width_o = dr.opaque(mi.UInt32, width)
    local = idx // spp_o
    j = idx - local * spp_o
    pix = local + dr.opaque(mi.UInt32, row0 * width)
    row_i = pix // width_o
    col_i = pix - row_i * width_o
    row = mi.Float(row_i)
    col = mi.Float(col_i)
    g = dr.opaque(mi.UInt32, group)
    group_pixel = (row_i // g) * dr.opaque(mi.UInt32, width // group) + col_i // g
    group_index = ((row_i % g) * g + col_i % g) * spp_o + j
    u_x, u_y, u_lambda = stratified_samples(pix, j, dr.opaque(mi.UInt32, seed), group_pixel, group_index)
    f = _opaque_float(camera.focal_px)
    xc = (col - 0.5 + u_x - _opaque_float(camera.cx)) / f
    yc = (row - 0.5 + u_y - _opaque_float(camera.cy)) / f
    right, down, fwd = (_opaque_vector(camera.rotation[:, k]) for k in range(3))
    d = dr.normalize(right * xc + down * yc + fwd)
    ray = mi.RayDifferential3f(_opaque_vector(camera.origin), d)
    ray.time = mi.Float(0.0)
    weights = None
    if mi.is_spectral:
        lams, weights = response.sample_wavelengths(u_lambda)
        ray.wavelengths = lams
    spec, _, _ = integrator.sample(scene, sampler, ray, None, True)

    if mi.is_polarized:
        up = -down
        current = mi.mueller.stokes_basis(-ray.d)
        target = dr.cross(ray.d, up)
        spec = mi.mueller.rotate_stokes_basis(-ray.d, current, target) @ spec
        stokes = [spec[0, 0], spec[1, 0], spec[2, 0]]
    else:
        stokes = [mi.UnpolarizedSpectrum(spec)]

    if mi.is_spectral:
        out = [dr.sum(s * weights[c]) for s in stokes for c in range(3)]
    else:  # neutral scene: R = G = B, transfer one channel
        out = [s[0] * _opaque_float(response.white_balance[0]) for s in stokes]
    dr.eval(*out)
    arrays = [np.asarray(v, dtype=np.float32) for v in out]
    if not mi.is_spectral:
        arrays = [a for a in arrays for _ in range(3)]
    arrays += [None] * (9 - len(arrays))
    return arrays


def _diattenuation(extinction_ratio) -> list[float]:
    """``(ER - 1) / (ER + 1)`` per colour R, G, B of one value or 3 (``None`` / inf: 1, an ideal polarizer)."""
    values = np.atleast_1d(np.asarray(math.inf if extinction_ratio is None else extinction_ratio, dtype=np.float64))
    if values.shape not in ((1,), (3,)) or np.any(np.isnan(values)) or np.any(values < 1.0):
        raise InputError("extinction_ratio", values.tolist(), "one value or 3 (R, G, B), each >= 1 (inf: ideal)")
    return [1.0 if math.isinf(er) else (er - 1.0) / (er + 1.0) for er in np.broadcast_to(values, (3,)).tolist()]


def _finite_lanes(lanes, rows: int, width: int, spp: int) -> tuple[list, int]:
    """The 9 traced lanes of a chunk (``S0, S1, S2`` x ``R, G, B``) as float64 ``(rows, width, spp)``
    arrays, non-finite samples set to 0, and how many there were; absent ``S1, S2`` lanes (an
    unpolarized variant) are zeros."""
    per, nonfinite = [], 0
    for v in lanes:
        if v is None:
            per.append(None)
            continue
        a = v.astype(np.float64).reshape(rows, width, spp)
        bad = ~np.isfinite(a)
        if bad.any():
            nonfinite += int(bad.sum())
            a = np.where(bad, 0.0, a)
        per.append(a)
    if per[3] is None:
        zero = np.zeros_like(per[0])
        per[3:] = [zero] * 6
    return per, nonfinite


def render_view(scene, camera: PinholeCamera, *, spp: int, seed: int, response: CameraResponse,
                mode: str = "stokes", analyzer_deg: float = 0.0, extinction_ratio=None,
                max_lanes: int = DEFAULT_MAX_LANES, progress: Callable[[int], None] | None = None,
                group: int = 1) -> ViewRender:
    """Render one view of ``scene`` (loaded in the active variant) through ``camera``.

    ``mode="stokes"``: 9 channels ``S0, S1, S2`` x ``R, G, B`` (camera RGB, D65 white
    balance, camera frame). ``mode="analyzer"``: 3 channels, RGB through an analyzer at
    ``analyzer_deg`` in the camera frame, with ``extinction_ratio`` (``None`` / inf: ideal; one
    value, or 3 per colour R, G, B: ``I = (S0 + d (S1 cos 2a + S2 sin 2a)) / 2`` with
    ``d = (ER - 1) / (ER + 1)``, as :func:`capssim.camera.rig.analyzer_row`). ``progress(n)`` is called with the number of
    lanes finished after each chunk. ``group``: the render is ``group`` times finer than the
    ground truth; wavelengths are then stratified per ``group x group`` block. Returns means
    in float64 ``(C, H, W)``.
    """
    import mitsuba as mi

    if mode not in ("stokes", "analyzer"):
        raise InputError("mode", mode, "'stokes' or 'analyzer'")
    if not (isinstance(spp, (int, np.integer)) and spp >= 1 and math.isqrt(int(spp)) ** 2 == spp):
        raise InputError("spp", spp, "a perfect square >= 1 (the multijitter sampler stratifies on a grid)")
    if response.white_balance is None or response.variant != mi.variant():
        response.calibrate()
    diattenuation = _diattenuation(extinction_ratio)
    integrator = scene.integrator()
    height, width = camera.height, camera.width
    if group < 1 or width % group or height % group:
        raise InputError("group", group, f"a factor >= 1 dividing the image size {height}x{width}")
    rows_per_chunk = max(1, min(height, max_lanes // max(1, width * spp)))
    rows_per_chunk = max(group, rows_per_chunk - rows_per_chunk % group)
    n_out = 9 if mode == "stokes" else 3
    sums = np.zeros((n_out, height, width))
    sq = np.zeros((12 if mode == "stokes" else 3, height, width))
    nonfinite = 0
    t0 = time.perf_counter()
    if mode == "analyzer":
        ca = [float(d) * np.cos(np.deg2rad(2 * analyzer_deg)) for d in diattenuation]
        sa = [float(d) * np.sin(np.deg2rad(2 * analyzer_deg)) for d in diattenuation]
    for chunk, row0 in enumerate(range(0, height, rows_per_chunk)):
        rows = min(rows_per_chunk, height - row0)
        lanes = _trace_chunk(scene, integrator, response, camera, row0=row0, rows=rows, spp=int(spp),
                             seed=derive_seed("chunk", seed, chunk), group=group)
        per, bad = _finite_lanes(lanes, rows, width, int(spp))
        nonfinite += bad
        if mode == "analyzer":
            per = [0.5 * (per[k] + ca[k] * per[3 + k] + sa[k] * per[6 + k]) for k in range(3)]
        for c, a in enumerate(per):
            sums[c, row0:row0 + rows] = a.sum(axis=2)
        if mode == "stokes":
            for p, ang in enumerate((0.0, 45.0, 90.0, 135.0)):
                cp, sp = np.cos(np.deg2rad(2 * ang)), np.sin(np.deg2rad(2 * ang))
                for k in range(3):
                    i_a = 0.5 * (per[k] + cp * per[3 + k] + sp * per[6 + k])
                    sq[3 * p + k, row0:row0 + rows] = np.square(i_a).sum(axis=2)
        else:
            for k in range(3):
                sq[k, row0:row0 + rows] = np.square(per[k]).sum(axis=2)
        if progress is not None:
            progress(rows * width * spp)
    seconds = time.perf_counter() - t0
    mean = sums / spp
    if mode == "stokes":
        i_mean = np.concatenate([0.5 * (mean[0:3] + np.cos(np.deg2rad(2 * a)) * mean[3:6]
                                        + np.sin(np.deg2rad(2 * a)) * mean[6:9]) for a in (0, 45, 90, 135)])
    else:
        i_mean = mean
    var = np.clip(sq / spp - np.square(i_mean), 0.0, None) * (spp / max(spp - 1, 1))
    if nonfinite:
        log.warning("%d non-finite radiance samples were set to 0 (a known Mitsuba bug in some scalar "
                    "variants; see docs/notes/rendering-internals.md)", nonfinite)
    return ViewRender(mean=mean, sample_variance=var, spp=int(spp), seconds=seconds, nonfinite_samples=nonfinite,
                      lanes=height * width * int(spp))


def combine_weighted(views: list[ViewRender], noise_rms: list[float]) -> ViewRender:
    """Pool independent renders of one view with inverse-variance weights ``1 / noise_rms^2``.

    ``extra["noise_rms"]`` of the result is the pooled RMS error ``(sum 1/sigma_i^2)^-1/2``.
    A render with zero noise gets all the weight.
    """
    sig = np.asarray(noise_rms, dtype=np.float64)
    if np.any(sig <= 0):
        w = (sig <= 0).astype(np.float64)
    else:
        w = 1.0 / np.square(sig)
    w = w / w.sum()
    mean = sum(wi * v.mean for wi, v in zip(w, views))
    var = sum(wi * v.sample_variance for wi, v in zip(w, views))
    pooled = 0.0 if np.any(sig <= 0) else float(1.0 / np.sqrt(np.sum(1.0 / np.square(sig))))
    return ViewRender(mean=mean, sample_variance=var, spp=int(sum(v.spp for v in views)),
                      seconds=sum(v.seconds for v in views), nonfinite_samples=sum(v.nonfinite_samples for v in views),
                      lanes=sum(v.lanes for v in views), extra={"noise_rms": pooled, "weights": w.tolist()})


def stokes_to_twelve(stokes9: np.ndarray) -> np.ndarray:
    """``(9 [S0.RGB, S1.RGB, S2.RGB], H, W)`` -> ``(12, H, W)`` analyzer images (Malus, c = 3p + k)."""
    s = stokes9.reshape(3, 3, *stokes9.shape[1:])
    return twelve_from_stokes(s)
