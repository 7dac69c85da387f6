"""MTF from a sinusoidal Siemens star, limit resolution and SR magnification (paper fig. 14-15, Table 4).

Reference: ISO 12233:2014 Annex E (sinusoidal Siemens star, "s-SFR"); Loebich et al., "Digital camera
resolution measurement using sinusoidal Siemens stars", Proc. SPIE 6502 (2007). Star fits: :mod:`capssim.eval.star`.

Method (no resampling along arcs):

1. The centre comes from the caller or from :func:`~capssim.eval.star.find_star_center`.
2. Pixels are binned into rings of relative width ``ring_width`` (at least 1 pixel) and
   eight 45-degree segments centred on 0, 45, ..., 315 degrees (0 = +col, counter-clockwise),
   and fitted by :func:`~capssim.eval.star.fit_rings`. Modulation = ``sqrt(b^2 + c^2) / a``;
   the fit residual (RMS, per degree of freedom) is kept.
3. Segments are grouped: ``hv`` (segments centred on 0/90/180/270 deg: bars along the
   axes, frequency along an axis) and ``diagonal`` (45/135/225/315). A group's
   modulation is the mean of its segments'; its residual ratio the RMS of theirs. The
   headline figure is ``hv``: a square lattice resolves up to sqrt(2) x 0.5 cycles/pixel
   along its diagonals, so a plain image's diagonal "magnification" can exceed 1 without
   any super-resolution (it is reported, never used as the headline).
4. MTF = modulation / reference modulation. The reference is the target's modulation:
   given (``reference_modulation``), or extrapolated to f = 0 by a fit of
   ``log M = log M0 - alpha f^2`` over the lowest-frequency rings (exact for a Gaussian
   blur).

Not crediting aliasing (see shared RENDERING-NOTES "Siemens-star MTF: a trap"): a
known-frequency fit keeps "seeing" a star past Nyquist, because the samples of an ideal
point-sampled star *are* that star. So the measurement

* is made on the image's own grid and never credits a ring above ``nyquist`` (0.5
  cycles/pixel of this grid, along every direction, diagonals included);
* stops at the first ring (from low to high frequency) where the residual RMS reaches
  ``residual_limit`` (default 0.5) times the fitted sinusoid's RMS (``amplitude / sqrt 2``):
  aliasing, interpolation error or noise then rivals the modulation. Only rings before
  the stop count; white noise of std sigma stops the measurement where the amplitude falls
  below 2 sqrt(2) sigma. (How the stop behaves on upsampled and blurred stars: the docs'
  scoring notes, and :func:`validation_table`.)

Limit resolution = the frequency where the MTF first falls to ``threshold`` (0.03, the
paper's human-eye contrast threshold), linearly interpolated between rings; if it does
not fall that far before the stop, the limit is the last credited ring and
``limited_by`` says why (``"residual"``, ``"nyquist"`` or ``"star-centre"``).

SR magnification (paper section 5.3) = limit resolution / 0.5 with the frequency in
cycles per low-resolution sub-image pixel: ``magnification = limit * reference_pitch /
0.5`` where ``reference_pitch`` is the size of one reference pixel in pixels of this image
(4 for a capssim HR output: one Bayer sub-image pixel spans 4 HR pixels).
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from capssim.errors import InputError

from .star import find_star_center, fit_rings, ring_edges, sinusoidal_star

log = logging.getLogger(__name__)

GROUPS = {"hv": (0, 2, 4, 6), "diagonal": (1, 3, 5, 7)}
HECT = 0.03  # human-eye contrast threshold (paper section 5.3)
NYQUIST = 0.5  # cycles per pixel of the measured grid


# -- measurement ---------------------------------------------------------------------------------
@dataclass
class MTFResult:
    """Per-ring MTF of one image channel and its limit resolution per segment group."""

    cycles: int
    center_rowcol: tuple[float, float]
    radius_px: float
    frequency: np.ndarray  # (K,) cycles/pixel of this image, ascending
    radius: np.ndarray  # (K,) mean radius of each ring
    mtf: dict[str, np.ndarray]  # group -> (K,)
    residual_ratio: dict[str, np.ndarray]  # group -> (K,) residual RMS / sinusoid RMS
    credited: dict[str, np.ndarray]  # group -> (K,) bool: ring counts towards the limit
    limit: dict[str, float]  # group -> limit resolution, cycles/pixel of this image
    limited_by: dict[str, str]
    reference_modulation: float
    reference_source: str
    reference_pitch: float
    threshold: float = HECT
    residual_limit: float = 1.0
    notes: list[str] = field(default_factory=list)

    def magnification(self, group: str = "all") -> float:
        """Paper's SR magnification: limit (cycles per reference pixel) / 0.5."""
        return self.limit[group] * self.reference_pitch / NYQUIST

    def to_dict(self) -> dict:
        return {
            "cycles": self.cycles, "center_rowcol": list(self.center_rowcol), "radius_px": self.radius_px,
            "reference_modulation": self.reference_modulation, "reference_source": self.reference_source,
            "reference_pitch": self.reference_pitch, "threshold": self.threshold,
            "residual_limit": self.residual_limit,
            "frequency_cyc_per_px": self.frequency.tolist(),
            "frequency_cyc_per_ref_px": (self.frequency * self.reference_pitch).tolist(),
            "radius": self.radius.tolist(),
            "mtf": {g: _nan_to_none(v) for g, v in self.mtf.items()},
            "residual_ratio": {g: _nan_to_none(v) for g, v in self.residual_ratio.items()},
            "credited": {g: v.tolist() for g, v in self.credited.items()},
            "limit_cyc_per_px": dict(self.limit),
            "limit_cyc_per_ref_px": {g: v * self.reference_pitch for g, v in self.limit.items()},
            "magnification": {g: self.magnification(g) for g in self.limit},
            "limited_by": dict(self.limited_by),
            "notes": list(self.notes),
        }


def _nan_to_none(arr: np.ndarray) -> list:
    return [None if not np.isfinite(v) else float(v) for v in arr]


def _reference_from_low_frequencies(freq: np.ndarray, modulation: np.ndarray) -> tuple[float, str]:
    """Extrapolate ``log M = log M0 - alpha f^2`` to f = 0 over the lowest-frequency rings."""
    good = np.isfinite(modulation) & (modulation > 0)
    f, m = freq[good], modulation[good]
    if len(f) == 0:
        return float("nan"), "none"
    order = np.argsort(f)
    f, m = f[order], m[order]
    sel = f <= max(0.1, 1.6 * f[0])
    if sel.sum() < 3:
        sel = np.zeros_like(f, dtype=bool)
        sel[:min(3, len(f))] = True
    if sel.sum() < 2:
        return float(m[0]), "lowest ring"
    coef = np.polyfit(f[sel] ** 2, np.log(m[sel]), 1)
    return float(np.exp(coef[1])), f"extrapolated to f=0 from {int(sel.sum())} rings with f <= {f[sel][-1]:.3f}"


def _limit(freq: np.ndarray, mtf: np.ndarray, ratio: np.ndarray, *, threshold: float, residual_limit: float,
           nyquist: float) -> tuple[np.ndarray, float, str]:
    """Credited rings, limit resolution and what limited it (rings sorted by frequency)."""
    cred = np.zeros(len(freq), dtype=bool)
    why = None
    for i in range(len(freq)):
        if freq[i] > nyquist:
            why = "nyquist"
            break
        if not np.isfinite(ratio[i]) or not np.isfinite(mtf[i]) or ratio[i] >= residual_limit:
            why = "residual"
            break
        cred[i] = True
    fc, mc = freq[cred], mtf[cred]
    if why is None:  # ran out of rings: near Nyquist anyway, or the star's core is unusable
        why = "nyquist" if len(fc) and fc[-1] >= 0.85 * nyquist else "star-centre"
    if len(fc) == 0:
        return cred, 0.0, why
    below = np.nonzero(mc <= threshold)[0]
    if len(below):
        j = below[0]
        if j == 0:  # below the threshold already at the lowest measured frequency: nothing resolved
            return cred, 0.0, "mtf"
        f0, f1, m0, m1 = fc[j - 1], fc[j], mc[j - 1], mc[j]
        return cred, float(f0 + (m0 - threshold) * (f1 - f0) / (m0 - m1)), "mtf"
    return cred, float(fc[-1]), why


@dataclass
class StarMTF:
    """MTF of every channel of a star image plus the channel-mean curve (``results["mean"]``)."""

    results: dict[str, MTFResult]

    def to_dict(self) -> dict:
        return {name: r.to_dict() for name, r in self.results.items()}


@dataclass
class _Rings:
    """The rings shared by every channel of one star: ``order`` picks the usable rings by frequency."""

    cycles: int
    center_rowcol: tuple[float, float]
    r_max: float
    order: np.ndarray  # (K,) ring indices, ascending frequency
    frequency: np.ndarray  # (K,) cycles/pixel
    radius: np.ndarray  # (K,) mean ring radius (pixels)
    modulations: list[np.ndarray]  # per channel (rings, segments): amplitude / |mean|
    ratios: list[np.ndarray]  # per channel (rings, segments): residual RMS / sinusoid RMS


def _checked_star_inputs(images, cycles, names, reference_modulation) -> tuple[np.ndarray, int, list[str], list]:
    """The ``(C, H, W)`` float64 stack, the cycle count, one name and one reference (or None) per channel."""
    imgs = np.asarray(images, dtype=np.float64)
    if imgs.ndim == 2:
        imgs = imgs[None]
    if imgs.ndim != 3:
        raise InputError("images", f"shape {imgs.shape}", "a (C, H, W) stack or one (H, W) image")
    if not np.all(np.isfinite(imgs)):
        raise InputError("images", f"{int((~np.isfinite(imgs)).sum())} NaN/inf pixels", "finite images")
    if int(cycles) < 4:
        raise InputError("cycles", cycles, "the star's number of sinusoidal periods per turn (>= 4)")
    n_ch = imgs.shape[0]
    names = list(names) if names is not None else [str(c) for c in range(n_ch)]
    if len(names) != n_ch:
        raise InputError("names", len(names), f"{n_ch} channel names")
    refs = [None] * n_ch
    if reference_modulation is not None:
        ref_arr = np.broadcast_to(np.asarray(reference_modulation, dtype=np.float64), (n_ch,))
        refs = [float(v) for v in ref_arr]
    return imgs, int(cycles), names, refs


def _star_centre(imgs: np.ndarray, cycles: int, center_rowcol, notes: list[str]) -> tuple[float, float]:
    """The given centre ``(row, col)``, or the median of :func:`find_star_center` over the 4 most varied channels."""
    _, h, w = imgs.shape
    if center_rowcol is None:
        energy = [float(np.var(imgs[c])) for c in range(imgs.shape[0])]
        pick = np.argsort(energy)[::-1][:4]
        centres = np.array([find_star_center(imgs[c], cycles=cycles) for c in pick])
        center_rowcol = tuple(float(v) for v in np.median(centres, axis=0))
        notes.append(f"centre found automatically at row {center_rowcol[0]:.2f}, col {center_rowcol[1]:.2f}")
    cy, cx = float(center_rowcol[0]), float(center_rowcol[1])
    if not (0 <= cy <= h - 1 and 0 <= cx <= w - 1):
        raise InputError("center", f"({cy:.1f}, {cx:.1f})", f"a point inside the {h}x{w} image")
    return cy, cx


def _fit_star_rings(imgs: np.ndarray, centre: tuple[float, float], cycles: int, *, radius: float | None,
                    min_radius: float | None, ring_width: float, nyquist: float, notes: list[str]) -> _Rings:
    """Fit the sinusoid of every ring segment of every channel; keep the rings each direction group can use."""
    (_, h, w), (cy, cx) = imgs.shape, centre
    r_border = min(cy, cx, h - 1 - cy, w - 1 - cx)
    # a given radius is the star's edge: keep 1.5 px off it (edge pixels mix star and background)
    r_max = min(radius - 1.5, r_border) if radius is not None else r_border
    r_min = min_radius if min_radius is not None else max(1.5, cycles / (2 * math.pi * 2 * nyquist))
    if r_max <= r_min + 2:
        raise InputError("image", f"a star of usable radius {r_max:.1f} px around ({cy:.1f}, {cx:.1f})",
                         f"a star radius above {r_min + 2:.1f} px", "Check --center and --cycles.")
    edges = ring_edges(r_min, r_max, ring_width)
    fits = [fit_rings(imgs[c], (cy, cx), cycles, edges) for c in range(imgs.shape[0])]
    # a ring counts when each direction group has at least 3 of its 4 segments fitted
    ring_ok = np.logical_and.reduce([np.logical_and.reduce([f["ok"][:, list(segs)].sum(1) >= 3
                                                            for segs in GROUPS.values()]) for f in fits])
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mods = [np.where(f["ok"], f["amplitude"] / np.abs(f["mean"]), np.nan) for f in fits]
        ratios = [np.where(f["ok"], f["residual_rms"] / (f["amplitude"] / math.sqrt(2)), np.nan) for f in fits]
        n_tot = fits[0]["n"].sum(1)
        radius_mean = np.where(ring_ok, (fits[0]["radius"] * fits[0]["n"]).sum(1) / np.maximum(n_tot, 1), np.nan)
        freq = cycles / (2 * math.pi * radius_mean)
        mod_rings = np.nanmean(np.stack([np.nanmean(m, axis=1) for m in mods]), axis=0)
    # star edge when no radius was given: the modulation collapses beyond the star's disc
    if radius is None and np.isfinite(mod_rings[ring_ok]).any():
        masked = np.where(ring_ok, mod_rings, -np.inf)
        k_peak = int(np.argmax(masked))
        k = k_peak
        while k + 1 < len(masked) and masked[k + 1] >= 0.5 * masked[k_peak]:
            k += 1
        if k + 1 < len(masked):
            edge_r = float(edges[k + 1])
            ring_ok &= ~(edges[1:] > 0.97 * edge_r)
            r_max = edge_r
            notes.append(f"star edge found at radius {edge_r:.1f} px")
    if not ring_ok.any():
        raise InputError("image", "no ring with enough pixels", "a Siemens star", "Check --center and --cycles.")
    order = np.argsort(np.where(ring_ok, freq, np.inf))
    order = order[ring_ok[order]]
    return _Rings(cycles, (cy, cx), float(r_max), order, freq[order], radius_mean[order], mods, ratios)


def _channel_curves(rings: _Rings, c: int, ref_given: float | None, name: str
                    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float, str]:
    """Channel ``c``'s MTF and residual ratio per direction group, and its reference modulation and source."""
    mods, ratios = rings.modulations[c][rings.order], rings.ratios[c][rings.order]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        m_all = np.nanmean(mods, axis=1)
    if ref_given is None:
        ref, src = _reference_from_low_frequencies(rings.frequency, m_all)
    else:
        ref, src = ref_given, "given"
    if not (np.isfinite(ref) and ref > 1e-6):
        raise InputError("reference_modulation", ref, f"a positive target modulation (channel {name})",
                         "Is this channel a Siemens star with the given --cycles?")
    mtf, resid = {}, {}
    for g, segs in GROUPS.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mtf[g] = np.nanmean(mods[:, segs], axis=1) / ref
            resid[g] = np.sqrt(np.nanmean(ratios[:, segs] ** 2, axis=1))
    return mtf, resid, ref, src


def _mtf_result(rings: _Rings, mtf: dict, resid: dict, ref: float, src: str, *, reference_pitch: float,
                threshold: float, residual_limit: float, nyquist: float, notes: list[str]) -> MTFResult:
    """The :class:`MTFResult` of one curve per group: each group's limit resolution from :func:`_limit`."""
    credited, limit, why = {}, {}, {}
    for g in GROUPS:
        credited[g], limit[g], why[g] = _limit(rings.frequency, mtf[g], resid[g], threshold=threshold,
                                                residual_limit=residual_limit, nyquist=nyquist)
    return MTFResult(rings.cycles, rings.center_rowcol, rings.r_max, rings.frequency, rings.radius, mtf, resid,
                     credited, limit, why, float(ref), src, float(reference_pitch), threshold, residual_limit,
                     list(notes))


def measure_star(images: np.ndarray, cycles: int, *, names: list[str] | None = None,
                 center_rowcol: tuple[float, float] | None = None, radius: float | None = None,
                 reference_modulation=None, reference_pitch: float = 1.0, threshold: float = HECT,
                 residual_limit: float = 0.5, ring_width: float = 0.04, nyquist: float = NYQUIST,
                 min_radius: float | None = None) -> StarMTF:
    """MTF of each channel of a sinusoidal Siemens star, and their mean (the method and its limits: module docstring).

    Parameters
    ----------
    images, cycles : numpy.ndarray, int
        ``(C, H, W)`` star image; its periods per turn.
    names, center_rowcol, radius, min_radius, reference_modulation : optional
        Channel names; centre ``(row, col)`` (default: found); outer, inner radius (px); target modulation(s).
    reference_pitch : float
        One reference pixel in pixels of this image (4 for a capssim HR output).
    threshold : float
    residual_limit : float
    ring_width : float
    nyquist : float

    Returns
    -------
    StarMTF
        ``results``: one :class:`MTFResult` per channel and ``"mean"`` (``C > 1``: their MTFs averaged ring by ring).
    """
    imgs, cycles, names, refs = _checked_star_inputs(images, cycles, names, reference_modulation)
    notes: list[str] = []
    centre = _star_centre(imgs, cycles, center_rowcol, notes)
    rings = _fit_star_rings(imgs, centre, cycles, radius=radius, min_radius=min_radius, ring_width=ring_width,
                            nyquist=nyquist, notes=notes)
    limits = {"reference_pitch": reference_pitch, "threshold": threshold, "residual_limit": residual_limit,
              "nyquist": nyquist, "notes": notes}
    results: dict[str, MTFResult] = {}
    per_group_mtf: dict[str, list] = {g: [] for g in GROUPS}
    per_group_ratio: dict[str, list] = {g: [] for g in GROUPS}
    ref_used = []
    for c, name in enumerate(names):
        mtf, resid, ref, src = _channel_curves(rings, c, refs[c], name)
        ref_used.append(ref)
        for g in GROUPS:
            per_group_mtf[g].append(mtf[g])
            per_group_ratio[g].append(resid[g])
        results[name] = _mtf_result(rings, mtf, resid, ref, src, **limits)
    if len(names) > 1:
        mtf = {g: np.mean(per_group_mtf[g], axis=0) for g in GROUPS}
        resid = {g: np.sqrt(np.mean(np.square(per_group_ratio[g]), axis=0)) for g in GROUPS}
        results["mean"] = _mtf_result(rings, mtf, resid, float(np.mean(ref_used)), "mean of the channels' MTFs",
                                      **limits)
    return StarMTF(results)


def measure_mtf(image: np.ndarray, cycles: int, **options) -> MTFResult:
    """MTF of one ``(H, W)`` channel of a sinusoidal Siemens star (options of :func:`measure_star`)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise InputError("image", f"shape {img.shape}", "one 2-D channel")
    return measure_star(img[None], cycles, names=["image"], **options).results["image"]


def validation_table() -> str:
    """The measurement checked on analytic stars (``python -m capssim.eval.mtf``): the scoring notes' numbers."""
    import cv2

    lines = ["Gaussian blur, 160x160 point-sampled star, N = 36, centre found automatically:",
             "sigma_px  max|MTF-theory| hv  diag  limit_hv  theory  (reference modulation extrapolated)"]
    for sigma in (0.7, 1.0, 1.5):
        img = sinusoidal_star((160, 160), 36, center_rowcol=(79.3, 80.6), blur_sigma=sigma, modulation=0.8,
                              supersample=7)
        r = measure_mtf(img, 36)
        theory = np.exp(-2 * math.pi ** 2 * sigma ** 2 * r.frequency ** 2)
        errs = [float(np.max(np.abs(r.mtf[g] - theory)[r.credited[g]])) for g in ("hv", "diagonal")]
        lim = math.sqrt(math.log(1 / HECT) / (2 * math.pi ** 2 * sigma ** 2))
        lines.append(f"{sigma:8.2f}  {errs[0]:18.4f}  {errs[1]:.4f}  {r.limit['hv']:8.4f}  "
                     f"{lim if lim <= NYQUIST else float('nan'):6.4f}  ({r.limited_by['hv']})")
    lines += ["", "Box-pixel low-resolution star (96x96, Gaussian optics sigma 0.3 px) upsampled by bicubic "
                  "interpolation, measured on the upsampled grid, magnification over the low-resolution pixel:",
              "cycles  factor  mag_hv  mag_diag  mag_hv without the residual stop"]
    for cycles in (36, 72):
        for factor in (2, 4):
            lr = sinusoidal_star((96, 96), cycles, center_rowcol=(47.3, 48.1), pixel_box=1.0, blur_sigma=0.3,
                                 modulation=0.9, supersample=5)
            up = cv2.resize(lr, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)
            r = measure_mtf(up, cycles, reference_pitch=factor)
            naive = measure_mtf(up, cycles, reference_pitch=factor, center_rowcol=r.center_rowcol,
                                residual_limit=np.inf)
            lines.append(f"{cycles:6d}  {factor:6d}  {r.magnification('hv'):6.3f}  {r.magnification('diagonal'):8.3f}"
                         f"  {naive.magnification('hv'):6.3f}")
    return "\n".join(lines)


__all__ = ["GROUPS", "HECT", "NYQUIST", "MTFResult", "StarMTF", "find_star_center", "measure_mtf", "measure_star",
           "sinusoidal_star", "validation_table"]


if __name__ == "__main__":
    print(validation_table())
