"""``dofp-jcpd``: joint chromatic-polarimetric demosaicking (JCPD) by sparse coding over a joint dictionary.

Reference: S. Wen, Y. Zheng, F. Lu, "A Sparse Representation Based Joint Demosaicing Method for
Single-Chip Polarized Color Sensor", IEEE Trans. Image Processing 30, 2021 (cited as JCPD,
"Lu et al." [18] in the CAPS paper). Written from that description (no code copied).

Data: a DoFP mosaic ``M`` ``(H, W)`` on [0, 1] (full scale 1), one sample per pixel; pixel
``(r, s)`` observes channel ``c = 3 p + k`` (``p``: polarizer 0/45/90/135 deg, ``k``: R/G/B) given
by the layout (:func:`capssim.conventions.dofp_channel_map`, 4x4 period). Output ``(12, H, W)``.

1. Patches. The unknown image is cut into ``P x P x 12`` patches (``P = patch``, default 8),
   vectorized lexicographically: index ``c * P^2 + r * P + s`` (the vectorization the CAPS paper
   criticizes), with origins every ``stride`` pixels (4 or 8: a multiple of the DoFP period, so
   every patch sees the same sampling pattern). The mosaic is padded by whole 4x4 cells
   (``pad_rows_cols``: mirrored about the border, then moved by < 4 px to the pixel of the same
   mosaic phase), ``ceil((P - stride) / 4) * 4`` px on top/left and enough at the bottom/right
   that every pixel is covered by ``(P / stride)^2`` patches; the result is cropped back.
2. Dictionary ``D`` ``(12 P^2, K)``. Default (``dictionary=learned``): the shipped dictionary
   ``weights/jcpd-dictionary.npz`` (``P = 8``; 9 constant atoms and 256 atoms learned from the
   ground truths of the training dataset by MOD, :mod:`capssim.reconstruct.training.dictionary`,
   as JCPD learns its dictionary from full images). ``dictionary=analytic``: the joint dictionary
   (:func:`capssim.reconstruct.priors.sparse_coding.joint_dictionary`) ``kron(polarization, colour, DCT2)``,
   ``K = 9 P^2`` orthonormal atoms, each physically consistent (``I0 + I90 = I45 + I135``).
   ``dictionary=PATH``: a ``.npz`` holding ``D`` of that shape (e.g. ``capssim train`` with
   ``network: jcpd-dictionary``), columns normalized on load.
3. Observation. Patch ``y`` ``(P^2,)`` = the mosaic samples; as all patches share one sampling
   pattern, the masked dictionary ``D_m = D[c(q) * P^2 + q, :]`` ``(P^2, K)`` is one matrix.
4. Sparse coding. Batched OMP (:func:`~capssim.reconstruct.priors.sparse_coding.omp`) of every patch on
   ``D_m`` (column-normalized for the selection, least squares on the support). The spatially
   constant ("DC") atoms of ``D`` (9 for the analytic dictionary) are always in the support: the
   local mean colour-polarization state; without them the periodic sampling lets OMP explain a
   flat patch with aliased high-frequency atoms. For the same reason (the masked dictionary is 9x
   overcomplete and a DCT atom of frequency ``u`` and one of ``u +- P/4``... agree on a sampling
   lattice of period 4), the analytic atoms are chosen by the weighted correlation
   ``w_j |d_j^T r|``, ``w_j = exp(-20 (u^2 + v^2) / P^2)`` (:data:`FREQUENCY_FALLOFF`, a
   low-frequency prior standing in for the paper's learned dictionary; measured +1.5 to +3 dB over
   unweighted OMP on smooth scenes). On top of the DC atoms at most ``sparsity`` atoms
   (default 12), stopping once ``||y - D_m a||^2 <= P^2 (1.15 sigma)^2`` (or ``<= P^2 (1e-6 x)^2``
   of the patch scale ``x``, the rounding floor).
   ``sigma`` (noise std on [0, 1]): given, or estimated robustly (:func:`estimate_sigma`).
5. Synthesis. ``x = D a`` (all ``12 P^2`` values) per patch; overlapping patches are averaged
   into the ``(12, H, W)`` image, clipped to ``[0, max(1, max M)]``.

Patches are coded in chunks of about ``CHUNK_PATCHES`` (a few tens of MB); everything is torch on the
mosaic's device, batched over patches (the only Python loops are over OMP iterations and chunks).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from capssim.captures.capture import Capture
from capssim.conventions import dofp_channel_map
from capssim.errors import InputError

from ..dofp.bilinear import dofp_unobserved
from ..dofp.method_body import reject_unknown_options
from ..dofp.mosaic import angle_offsets, as_output, check_mosaic, clip_ceiling
from ..networks import WEIGHTS_DIR
from ..priors.sparse_coding import constant_atoms, joint_dictionary, omp
from ..registry import MethodOutput, RunContext, register_method
from ..run_context import stage_factory

REFERENCE = ("Wen, Zheng, Lu, 'A Sparse Representation Based Joint Demosaicing Method for Single-Chip Polarized "
             "Color Sensor', IEEE Trans. Image Processing 30, 2021 (JCPD)")

DEFAULTS = {"patch": 8, "stride": 4, "sparsity": 12, "sigma": "auto", "dictionary": "learned",
            "precision": "float32"}
#: the shipped dictionary, learned by ``capssim train examples/train-jcpd-dictionary.yaml``, and its patch side
LEARNED_DICTIONARY = WEIGHTS_DIR / "jcpd-dictionary.npz"
LEARNED_PATCH = 8
#: OMP tolerance factor: stop at residual norm^2 <= P^2 (TOLERANCE_FACTOR sigma)^2
TOLERANCE_FACTOR = 1.15
#: relative residual floor of the OMP stopping rule (float rounding; exact fits stop here)
RESIDUAL_FLOOR = 1e-6
#: low-frequency prior of the analytic dictionary: OMP selection weight exp(-falloff (u^2 + v^2) / P^2)
FREQUENCY_FALLOFF = 20.0
#: patches coded at once (bounds the OMP state to a few tens of MB)
CHUNK_PATCHES = 4096
#: noise gain of the diagonal Laplacian ``4 g - sum of 4 diagonal neighbours`` (sqrt(16 + 4))
_LAPLACIAN_GAIN = math.sqrt(20.0)


# -- options ---------------------------------------------------------------------------------------
def _int_option(name: str, raw, low: int, high: int, fix: str) -> int:
    try:
        value = int(raw)
        if isinstance(raw, float) and value != raw or isinstance(raw, bool):
            raise ValueError
    except (TypeError, ValueError):
        raise InputError(name, raw, f"an integer in [{low}, {high}]", fix) from None
    if not low <= value <= high:
        raise InputError(name, raw, f"an integer in [{low}, {high}]", fix)
    return value


def parse_options(options: dict) -> dict:
    """Validate the method options; returns ``patch, stride, sparsity, sigma (None: auto), dictionary, precision``.

    Raises :class:`~capssim.errors.InputError` naming the option (unknown options:
    :class:`~capssim.errors.UnknownNameError`).
    """
    opts = dict(options)
    patch = _int_option("patch", opts.pop("patch", DEFAULTS["patch"]), 4, 16, "Pass e.g. -p patch=8.")
    if patch % 2:
        raise InputError("patch", patch, "an even patch side in [4, 16]", "Pass e.g. -p patch=8.")
    stride = _int_option("stride", opts.pop("stride", DEFAULTS["stride"]), 4, 8, "Pass -p stride=4 or 8.")
    if stride % 4 or stride > patch:
        raise InputError("stride", stride, f"4 or 8 (a multiple of the 4x4 DoFP period), at most patch={patch}",
                         "Pass -p stride=4.")
    sparsity = _int_option("sparsity", opts.pop("sparsity", DEFAULTS["sparsity"]), 1, 64,
                           "Pass e.g. -p sparsity=12.")
    raw_sigma = opts.pop("sigma", DEFAULTS["sigma"])
    sigma = None
    if not (isinstance(raw_sigma, str) and raw_sigma.lower() == "auto") and raw_sigma is not None:
        try:
            sigma = float(raw_sigma)
        except (TypeError, ValueError):
            sigma = float("nan")
        if not (math.isfinite(sigma) and 0.0 <= sigma <= 1.0):
            raise InputError("sigma", raw_sigma, "auto or a noise std in [0, 1] (on the [0, 1] scale)",
                             "Pass -p sigma=auto or e.g. -p sigma=0.01.")
    dictionary = opts.pop("dictionary", DEFAULTS["dictionary"])
    precision = opts.pop("precision", DEFAULTS["precision"])
    if precision not in ("float32", "float64"):
        raise InputError("precision", precision, "float32 or float64")
    reject_unknown_options(opts, list(DEFAULTS))
    return {"patch": patch, "stride": stride, "sparsity": sparsity, "sigma": sigma,
            "dictionary": str(dictionary), "precision": precision}


def load_dictionary(source, patch: int, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """The joint dictionary ``(12 patch^2, K)``: ``'analytic'``, a ``.npz`` path (array ``D``) or an array.

    Columns are normalized; a wrong shape, non-finite values or a zero column raise
    :class:`~capssim.errors.InputError` naming the option ``dictionary``.
    """
    if isinstance(source, str) and source == "analytic":
        return joint_dictionary(patch, dtype=dtype, device=device)
    n = 12 * patch * patch
    fix = (f"Pass -p dictionary=analytic, or a .npz with an array 'D' of shape ({n}, atoms) for patch={patch}; "
           f"the shipped learned dictionary is for patch={LEARNED_PATCH}.")
    if source is None or isinstance(source, str) and source == "learned":
        source = LEARNED_DICTIONARY
    if isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise InputError("dictionary", str(source), "'analytic' or an existing .npz file", fix)
        try:
            with np.load(path, allow_pickle=False) as data:
                if "D" not in data.files:
                    raise InputError("dictionary", f"{path} with arrays {data.files}", "a .npz with an array 'D'",
                                     fix)
                array = np.asarray(data["D"])
        except (OSError, ValueError) as err:
            if isinstance(err, InputError):
                raise
            raise InputError("dictionary", str(source), "a readable .npz file", fix) from None
    else:
        array = np.asarray(source)
    if array.ndim != 2 or array.shape[0] != n or array.shape[1] < 1 or not np.issubdtype(array.dtype, np.number):
        raise InputError("dictionary", f"an array of shape {array.shape}", f"shape ({n}, atoms) for patch={patch}",
                         fix)
    d = torch.as_tensor(array.astype(np.float64), device=device)
    norms = d.norm(dim=0)
    if not bool(torch.isfinite(d).all()) or bool((norms <= 1e-12).any()):
        raise InputError("dictionary", "non-finite values or zero columns", "finite, non-zero atoms", fix)
    return (d / norms).to(dtype)


# -- geometry ----------------------------------------------------------------------------------------
def phase_padding_index(length: int, before: int, after: int) -> torch.Tensor:
    """Source index of each of ``before + length + after`` padded positions, keeping the phase mod 4.

    ``before`` must be a multiple of 4. Outside ``[0, length)``, a position is mirrored about the
    border (``-1 - i``, ``2 length - 1 - i``) and then moved by less than 4 px, towards the
    inside, to the pixel with the same index mod 4; repeated while out of range.
    """
    idx = np.arange(-before, length + after)
    src = idx.copy()
    for _ in range(64):
        low, high = src < 0, src >= length
        if not (low.any() or high.any()):
            break
        mirrored = np.where(low, -1 - src, 2 * length - 1 - src)
        shift = np.mod(src - mirrored, 4)
        src = np.where(low, mirrored + shift, np.where(high, mirrored - np.mod(mirrored - src, 4), src))
    if (src < 0).any() or (src >= length).any() or (np.mod(src - idx, 4) != 0).any():
        raise ValueError(f"phase_padding_index: cannot pad {length} px by {before}/{after}")
    return torch.as_tensor(src, dtype=torch.long)


def patch_grid(length: int, patch: int, stride: int) -> tuple[int, int, int]:
    """``(before, after, count)``: padding and number of patch origins along one axis."""
    before = 4 * math.ceil((patch - stride) / 4)
    span = before + length + (patch - stride)  # at least: every pixel in (patch/stride) patches
    count = max(1, math.ceil((span - patch) / stride) + 1)
    after = (count - 1) * stride + patch - before - length
    return before, after, count


def masked_rows(patch: int, layout) -> torch.Tensor:
    """Row of ``D`` observed at each patch pixel ``q = r * P + s``: ``c(q) * P^2 + q`` ``(P^2,)``."""
    cmap = torch.as_tensor(dofp_channel_map(patch, patch, layout)).flatten()
    return cmap * patch * patch + torch.arange(patch * patch)


def frequency_weights(patch: int) -> torch.Tensor:
    """OMP selection weights ``(9 P^2,)`` of the analytic atoms: ``exp(-FREQUENCY_FALLOFF (u^2 + v^2) / P^2)``."""
    u = torch.arange(patch, dtype=torch.float64)
    rho2 = (u[:, None] ** 2 + u[None, :] ** 2).flatten() / patch ** 2
    return torch.exp(-FREQUENCY_FALLOFF * rho2).repeat(9)


# -- noise ---------------------------------------------------------------------------------------
def estimate_sigma(mosaic: torch.Tensor, layout="sony") -> float:
    """Robust noise std of a DoFP mosaic: MAD / 0.6745 of a high-pass on the green lattices.

    In each polarizer sub-mosaic (RGGB) the G sites form a quincunx lattice (one channel); the
    diagonal Laplacian ``4 g - sum of its 4 diagonal G neighbours`` cancels constants and linear
    ramps and has noise gain ``sqrt(20)``. Values of all four angles are pooled.
    """
    x = mosaic.to(torch.float64)
    values = []
    for dr, dc in angle_offsets(layout):
        s = x[dr::2, dc::2]
        if min(s.shape) < 3:
            continue
        centre = s[1:-1, 1:-1]
        lap = 4 * centre - s[:-2, :-2] - s[:-2, 2:] - s[2:, :-2] - s[2:, 2:]
        rows = torch.arange(1, s.shape[0] - 1, device=s.device)[:, None]
        cols = torch.arange(1, s.shape[1] - 1, device=s.device)[None, :]
        values.append(lap[(rows + cols) % 2 == 1])
    if not values:
        return 0.0
    hp = torch.cat(values)
    return float(hp.abs().median() / 0.6745 / _LAPLACIAN_GAIN)


# -- the method ---------------------------------------------------------------------------------
def jcpd_reconstruct(x: torch.Tensor, *, layout="sony", patch: int = 8, stride: int = 4, sparsity: int = 12,
                     sigma: float | None = None, dictionary=None, timer=None) -> tuple[torch.Tensor, dict]:
    """JCPD of a checked mosaic tensor ``x`` ``(H, W)``: ``(image (12, H, W), parameters used)``.

    Computes in ``x.dtype`` on ``x.device``; see the module docstring for the steps.
    """
    stage = stage_factory(timer)
    h, w = x.shape
    with stage("dictionary"):
        d = load_dictionary(dictionary, patch, dtype=torch.float64, device=x.device)
        forced = constant_atoms(d)
        dm = d[masked_rows(patch, layout).to(x.device)].to(x.dtype)  # (P^2, K)
        d = d.to(x.dtype)
        analytic = isinstance(dictionary, str) and dictionary == "analytic"
        weights = frequency_weights(patch).to(device=x.device, dtype=x.dtype) if analytic else None
    with stage("noise_estimate"):
        sigma_used = estimate_sigma(x, layout) if sigma is None else float(sigma)
    top, bottom, nh = patch_grid(h, patch, stride)
    left, right, nw = patch_grid(w, patch, stride)
    rows = phase_padding_index(h, top, bottom).to(x.device)
    cols = phase_padding_index(w, left, right).to(x.device)
    padded = x[rows[:, None], cols[None, :]]
    tol_abs = patch * patch * (TOLERANCE_FACTOR * sigma_used) ** 2
    out = x.new_zeros((12, padded.shape[0], padded.shape[1]))
    weight = x.new_zeros((1, padded.shape[0], padded.shape[1]))
    band_rows = max(1, CHUNK_PATCHES // nw)
    n_atoms = 0
    with stage("sparse_coding"):
        for i0 in range(0, nh, band_rows):
            i1 = min(nh, i0 + band_rows)
            y0, y1 = i0 * stride, (i1 - 1) * stride + patch
            band = padded[y0:y1]
            patches = band.unfold(0, patch, stride).unfold(1, patch, stride).reshape(-1, patch * patch)
            scale2 = patches.square().mean(1)
            tol = torch.clamp(scale2 * (patch * RESIDUAL_FLOOR) ** 2, min=tol_abs)
            codes = omp(dm, patches, sparsity=sparsity, tolerance=tol, forced=forced, weights=weights)
            n_atoms += int((codes != 0).sum())
            recon = (codes @ d.T).T[None]  # (1, 12 P^2, n)
            size = (y1 - y0, padded.shape[1])
            out[:, y0:y1] += F.fold(recon, size, patch, stride=stride)[0]
            weight[:, y0:y1] += F.fold(torch.ones_like(recon[:, :patch * patch]), size, patch, stride=stride)[0]
    image = (out / weight)[:, top:top + h, left:left + w].clamp(0.0, clip_ceiling(x))
    params = {"patch": patch, "stride": stride, "sparsity": sparsity, "sigma": sigma_used,
              "sigma_estimated": sigma is None, "forced_atoms": int(forced.numel()), "atoms": int(d.shape[1]),
              "mean_atoms_per_patch": n_atoms / max(1, nh * nw), "tolerance_factor": TOLERANCE_FACTOR}
    return image, params


def demosaic_dofp_jcpd(mosaic, *, layout="sony", device: str | torch.device | None = None, patch: int = 8,
                       stride: int = 4, sparsity: int = 12, sigma: float | None = None, dictionary=None,
                       dtype: torch.dtype | None = None, timer=None):
    """JCPD demosaicking of a DoFP mosaic ``(H, W)`` -> ``(12, H, W)`` (``c = 3p + k``).

    ``mosaic``: float numpy array or tensor on [0, 1], even sides >= 12; numpy in gives float32
    numpy out, a tensor gives a tensor. ``layout``: the 2x2 polarizer cell. ``sigma``: noise std
    on [0, 1] (``None``: estimated). ``dictionary``: ``None``/``'learned'`` (shipped), ``'analytic'``, a ``.npz`` path or an
    array ``(12 patch^2, atoms)``. Options are validated as the method's (:func:`parse_options`).
    """
    opts = parse_options({"patch": patch, "stride": stride, "sparsity": sparsity,
                          "sigma": "auto" if sigma is None else sigma})
    x = check_mosaic(mosaic, device=device, dtype=dtype)
    image, _ = jcpd_reconstruct(x, layout=layout, patch=opts["patch"], stride=opts["stride"],
                                sparsity=opts["sparsity"], sigma=opts["sigma"], dictionary=dictionary, timer=timer)
    return as_output(image, mosaic)


@register_method("dofp-jcpd", input_kind="dofp", array_function=demosaic_dofp_jcpd,
                 description="DoFP colour-polarization camera, joint chromatic-polarimetric demosaicking (JCPD) by "
                             "sparse coding over a joint colour-polarization dictionary",
                 reference=REFERENCE)
def dofp_jcpd(capture: Capture, *, context: RunContext) -> MethodOutput:
    """Demosaick ``capture.dofp_float()`` with JCPD.

    Options (``context.options``): ``patch`` (even, 4..16), ``stride`` (4 | 8), ``sparsity``
    (1..64), ``sigma`` (``auto`` | std on [0, 1]), ``dictionary`` (``learned`` | ``analytic`` | .npz path),
    ``precision`` (``float32`` | ``float64``).
    """
    opts = parse_options(context.options)
    with context.timer.stage("load"):
        mosaic = torch.from_numpy(capture.dofp_float()).to(context.device)
        n_saturated = int(capture.dofp_saturated().sum())
    x = check_mosaic(mosaic, dtype=getattr(torch, opts["precision"]))
    image, params = jcpd_reconstruct(x, layout=capture.dofp_layout, patch=opts["patch"], stride=opts["stride"],
                                     sparsity=opts["sparsity"], sigma=opts["sigma"], dictionary=opts["dictionary"],
                                     timer=context.timer)
    with context.timer.stage("to_host"):
        image = image.to("cpu", torch.float32).numpy()
    params = {"layout": [list(r) for r in capture.dofp_layout], "precision": opts["precision"],
              "dictionary": opts["dictionary"], **params}
    return MethodOutput(image=image, params=params,
                        extra={"n_saturated_pixels": n_saturated,
                               "saturation_handling": "none (sparse coding uses saturated samples as they are)"},
                        unobserved=lambda: dofp_unobserved(capture.dofp_saturated(), capture.dofp_layout))
