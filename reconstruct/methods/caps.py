"""The paper's CAPS reconstruction and two of its ablations (section 3-5, Fig. 3, Algorithm 1).

Reference: "Joint constraints of guided filtering based confidence and nonlocal sparse
tensor for color polarization super-resolution imaging", Optics Express 32(2), 2364 (2024).

Pipeline (each step its own module):

1. rearrangement of the 4 RGGB frames into 16 observations (``capssim.reconstruct.model.rearrange``, 3.1);
2. registration: the stored homographies (``--true-warps``) or ``capssim.reconstruct.registration``;
3. CAGF confidence between all channel pairs (``capssim.reconstruct.model.cagf``, eq. 12-14);
4. initialization fusing all 16 observations on the HR grid (``capssim.reconstruct.model.init_fusion``);
5. ADMM (``capssim.reconstruct.solvers.admm``, eq. 20-30) with the confidence-guided data term
   (``capssim.reconstruct.model.data_term``, eq. 15-16, 25-26) and the NLSTR prior
   (``capssim.reconstruct.priors.nlstr_prior`` with ``capssim.reconstruct.priors.nlstr``, 3.3).

Ablations (section 5.2), the same code with one switch each:

* ``caps-no-cagf``: the data term uses only the observations of the same channel;
* ``caps-no-nlstr``: data term only (steepest descent of eq. 16 from the same initialization,
  ``capssim.reconstruct.solvers.descent``).

``caps-iccp`` (the cascade) lives in :mod:`capssim.reconstruct.methods.caps_iccp`.

The sampling operator ``M`` is the shared observation model
``capssim.operators.lr_sampling_operator`` with the capture's PSF (the paper uses an
isotropic Gaussian kernel; simulated captures store a Gaussian PSF, and ``psf_sigma``
overrides it, e.g. for real captures).

With a calibration (``capssim reconstruct --calibration``; :mod:`capssim.reconstruct.model.observation_model`)
``M`` takes the per-aperture PSFs and multiplies each observation by its flat field, the data term
mixes the channels by the calibrated analyzer (``(16, 12)``, exact adjoint), the geometry is the
calibration's (when it has one), and CAGF and the initialization work on flat-field-corrected
observations; the initialization is unmixed per pixel by the inverse analyzer (12x12).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, fields, replace

import numpy as np
import torch

from capssim.allocator import reuse_freed_memory
from capssim.errors import InputError, UnknownNameError
from capssim.operators.camera import lr_sampling_operator
from capssim.reconstruct.model.cagf import CAGFParameters, cagf_confidence
from capssim.reconstruct.model.data_term import ConfidenceDataTerm, field_of_view_mask
from capssim.reconstruct.model.init_fusion import fuse_initial_estimate
from capssim.reconstruct.model.observation_model import (
    CAPTURE_PSF_SIGMA,
    calibrated_analyzer,
    lr_flat_field,
    method_geometry,
    method_psf_kernels,
    unmix_analyzer,
)
from capssim.reconstruct.model.rearrange import observations_from_capture
from capssim.reconstruct.priors.nlstr import NLSTRParameters, NonlocalSparseTensor
from capssim.reconstruct.priors.nlstr_prior import MatchSchedule, NLSTRPrior
from capssim.reconstruct.registry import MethodOutput, RunContext, register_method
from capssim.reconstruct.solvers.admm import ADMMParameters, admm
from capssim.reconstruct.solvers.descent import steepest_descent
from capssim.reconstruct.solvers.interfaces import DivergenceError

log = logging.getLogger(__name__)

REFERENCE = "Optics Express 32(2) 2364 (2024), sections 3-5"


@dataclass
class CapsOptions:
    """Every option of the CAPS methods: one parameter object per step, each with its own defaults.

    The paper's defaults (section 5.1, DESIGN.md) live in the parameter classes:
    :class:`ADMMParameters` (eq. 27-28), :class:`MatchSchedule` (NLSTR's block matching
    across iterations), :class:`NLSTRParameters` (section 3.3) and :class:`CAGFParameters`
    (section 3.2). The user-facing option names (``-p NAME=VALUE``, the ``params`` of the
    JSON record) are :meth:`option_names`: the fields of those classes, except that CAGF's
    ``radius`` and ``eps`` are ``cagf_radius`` and ``cagf_eps`` and NLSTR's ``eps`` is not an
    option.
    """

    admm: ADMMParameters = field(default_factory=ADMMParameters)
    matching: MatchSchedule = field(default_factory=MatchSchedule)
    nlstr: NLSTRParameters = field(default_factory=NLSTRParameters)
    cagf: CAGFParameters = field(default_factory=CAGFParameters)
    # observation model
    psf_sigma: float = CAPTURE_PSF_SIGMA  # the capture's PSF; >= 0: a Gaussian of this std (HR px)
    fov_mask: bool = True
    # diagnostics
    track_psnr: bool = False
    # named settings (PRESETS); explicit options override the preset's
    preset: str = "default"

    @staticmethod
    def option_names() -> tuple[str, ...]:
        """The option names, in the order of :meth:`to_dict`."""
        return tuple(_OPTIONS)

    @classmethod
    def from_options(cls, options: dict, **overrides) -> "CapsOptions":
        """Parse ``{name: value}`` (strings coerced to each option's type) over the typed defaults ``overrides``."""
        options = dict(options or {})
        preset = str(next((raw for key, raw in options.items() if str(key).replace("-", "_") == "preset"),
                          overrides.get("preset", "default"))).strip()
        if preset not in PRESETS:
            raise UnknownNameError("preset", preset, list(PRESETS))
        values = {**overrides, **PRESETS[preset], "preset": preset}
        for key, raw in options.items():
            name = str(key).replace("-", "_")
            if name not in _OPTIONS:
                raise UnknownNameError("option", key, list(_OPTIONS))
            values[name] = _coerce(name, raw, type(_default(name)))
        groups: dict[str, dict] = {group: {} for group in _GROUPS}
        top = {}
        for name, value in values.items():
            if name not in _OPTIONS:
                raise UnknownNameError("option", name, list(_OPTIONS))
            group, attr = _OPTIONS[name]
            (groups[group] if group else top)[attr] = value
        return cls(**{group: _GROUPS[group](**kw) for group, kw in groups.items()}, **top)

    def validated_parameters(self) -> tuple[ADMMParameters, NLSTRParameters]:
        """Check every parameter group (:class:`InputError` on a bad value); return the ADMM and NLSTR ones."""
        self.admm.validate()
        self.matching.validate()
        self.nlstr.validate()
        return self.admm, self.nlstr

    def to_dict(self) -> dict:
        """``{option name: value}`` for every option (the method's ``params`` record)."""
        return {name: getattr(getattr(self, group) if group else self, attr)
                for name, (group, attr) in _OPTIONS.items()}


#: named settings of the CAPS methods (``-p preset=NAME``): the options each sets; explicit options win.
#: ``default``: the paper's parameters (section 5.1), dictionaries every 5th iteration; ``literal``:
#: Algorithm 1 as written, dictionaries at every iteration (same metrics within 0.08 dB, slower);
#: ``fast``: 7 iterations, block matching on the 3 leading principal components of the channels and at
#: most every 4th iteration, dictionaries every 4th, reference blocks every 6 px: about 3.8x faster at
#: 512 px with stored warps, within 0.2 dB on kettle and textured (docs/notes/reconstruction-speed.md;
#: ``caps-fast`` in the ``ablation`` suite).
PRESETS: dict[str, dict] = {
    "default": {},
    "literal": {"dictionary_gap": 1},
    "fast": {"iterations": 7, "dictionary_gap": 4, "stride": 6, "match_components": 3, "rematch_min_gap": 4},
}

#: the parameter group of each CapsOptions field that holds one
_GROUPS = {"admm": ADMMParameters, "matching": MatchSchedule, "nlstr": NLSTRParameters, "cagf": CAGFParameters}


def _option_table() -> dict[str, tuple[str | None, str]]:
    """Option name -> (group field of CapsOptions or None, attribute), in the record's order."""
    renamed = {("cagf", "radius"): "cagf_radius", ("cagf", "eps"): "cagf_eps"}
    hidden = {("nlstr", "eps")}
    table = {}
    for group, kind in _GROUPS.items():
        for f in fields(kind):
            if (group, f.name) not in hidden:
                table[renamed.get((group, f.name), f.name)] = (group, f.name)
    for f in fields(CapsOptions):
        if f.name not in _GROUPS:
            table[f.name] = (None, f.name)
    return table


_OPTIONS = _option_table()


def _default(name: str):
    group, attr = _OPTIONS[name]
    return getattr(_GROUPS[group] if group else CapsOptions, attr)


def _coerce(name: str, raw, kind):
    if isinstance(raw, kind) and not (kind is int and isinstance(raw, bool)):
        return raw
    text = str(raw).strip()
    try:
        if kind is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError
        if kind is int:
            as_float = float(text)
            if not as_float.is_integer():
                raise ValueError
            return int(as_float)
        if kind is float:
            value = float(text)
            if not math.isfinite(value):
                raise ValueError
            return value
        return text
    except ValueError:
        raise InputError(f"option {name}", repr(raw), f"a value of type {kind.__name__}") from None


# -- shared steps ---------------------------------------------------------------------------------
def channel_mean_psnr(image: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean over the 12 channels of the PSNR (dB, data range 1, ``image`` clipped to [0, 1]).

    A diagnostic the methods record on the device while they run (``init_psnr_db``, ``psnr_db``,
    ``track_psnr``); scores are :func:`capssim.eval.metrics.score`'s.
    """
    mse = (image.clamp(0, 1) - gt).square().mean(dim=(-2, -1)).clamp(min=1e-20)
    return float((-10 * torch.log10(mse)).mean())


def psnr_observer(capture, device):
    """Per-iteration :func:`channel_mean_psnr`, when ground truth is loaded."""
    if capture.gt is None:
        return None
    gt = torch.as_tensor(capture.gt, dtype=torch.float32, device=device)
    return lambda i, x: {"psnr_db": channel_mean_psnr(x, gt)}


def mean_psnr(capture, image: torch.Tensor) -> float | None:
    """:func:`channel_mean_psnr` of ``image`` against the capture's ground truth (None without one)."""
    if capture.gt is None:
        return None
    return channel_mean_psnr(image, torch.as_tensor(capture.gt, dtype=torch.float32, device=image.device))


def explain_divergence(exc: DivergenceError, opts: CapsOptions, defaults: CapsOptions) -> DivergenceError:
    """``exc`` naming the options set away from ``defaults`` (the likely cause), or ``dt`` if none is."""
    base = defaults.to_dict()
    changed = {k: v for k, v in opts.to_dict().items()
               if k not in ("iterations", "track_psnr", "preset") and v != base[k]}
    if not changed:
        return exc
    names = ", ".join(changed)
    return DivergenceError(f"option {names}",
                           ", ".join(f"{k}={v}" for k, v in changed.items()), solver=exc.solver,
                           iteration=exc.iteration, peak=exc.peak, bound=exc.bound,
                           fix="Set " + names + " back towards the default (" +
                               ", ".join(f"{k}={base[k]}" for k in changed) + ").")


def _operator(capture, context: RunContext, geometry, psf_sigma: float):
    """The sampling operator ``M``, the analyzer mixing ``(16, 12)`` (``None``: ideal), the PSF record and
    the flat field ``(16, h, w)`` (``None``: ideal) of the array model (``context.calibration``)."""
    kernel, kernels, psf_record = method_psf_kernels(capture, context, psf_sigma)
    if context.calibration is None:
        return lr_sampling_operator(geometry, kernel), None, psf_record, None
    flat = lr_flat_field(capture, context)
    operator = lr_sampling_operator(geometry, kernel, psf_kernels=kernels, flat=flat)
    mixing = None if calibrated_analyzer(context) is None else context.calibration.rig.lr_channel_matrix()
    return operator, mixing, psf_record, flat


def run_caps(capture, context: RunContext, *, use_cagf: bool = True, use_nlstr: bool = True) -> MethodOutput:
    """The joint CAPS reconstruction (and its no-CAGF / no-NLSTR ablations)."""
    opts = CapsOptions.from_options(context.options)
    admm_params, nl_params = opts.validated_parameters()
    dev, timer = context.device, context.timer
    hr_shape = capture.hr_shape
    with timer.stage("rearrange"):
        obs = observations_from_capture(capture, device=dev)
        lr_images, lr_saturated = capture.lr_images()
    with timer.stage("registration"):
        geometry, reg_record = method_geometry(capture, context, images=lr_images, saturated=lr_saturated)
        homographies = geometry.lr_homographies
    with timer.stage("operator"):
        operator, mixing, psf_record, flat = _operator(capture, context, geometry, opts.psf_sigma)
        if opts.fov_mask:
            inside = field_of_view_mask(homographies, tuple(obs.images.shape[-2:]), hr_shape, half_extent=0.125)
            obs.weights = obs.weights * torch.as_tensor(inside, dtype=obs.weights.dtype, device=dev)
    seen = obs if flat is None else replace(obs, images=obs.images / torch.as_tensor(flat, dtype=obs.images.dtype,
                                                                                      device=dev))
    # the iterations allocate the same large temporaries again and again: keep freed memory for reuse
    with reuse_freed_memory(enabled=dev.type == "cpu"):
        confidence = None
        if use_cagf:
            with timer.stage("cagf"):
                confidence = cagf_confidence(seen.images, homographies, obs.channel_of, obs.n_channels, hr_shape,
                                             weights=obs.weights, nu=opts.cagf.nu, radius=opts.cagf.radius,
                                             eps=opts.cagf.eps)
        with timer.stage("init"):
            init = fuse_initial_estimate(seen, homographies, hr_shape)
            if mixing is not None:  # the fused channels see the calibrated analyzer: A x per pixel
                init = unmix_analyzer(init, calibrated_analyzer(context))
        data = ConfidenceDataTerm(obs, operator, confidence=confidence, mixing=mixing)
        nlstr = None
        if use_nlstr:
            with timer.stage("nlstr_setup"):
                nlstr = NonlocalSparseTensor((obs.n_channels, *hr_shape), nl_params, device=dev)
        observer = psnr_observer(capture, dev) if opts.track_psnr else None
        solver_hooks = {"stage": timer.stage, "progress": context.report, "observer": observer}
        try:
            if nlstr is None:  # the data term alone (eq. 16)
                image, history = steepest_descent(data, init, admm_params, **solver_hooks)
            else:
                image, history = admm(data, init, NLSTRPrior(nlstr, opts.matching), admm_params, **solver_hooks)
        except DivergenceError as exc:
            raise explain_divergence(exc, opts, CapsOptions()) from None
    params = opts.to_dict()
    params.update({"psf": psf_record, "use_cagf": use_cagf, "use_nlstr": use_nlstr, "channels": obs.n_channels,
                   "reference_image": 0, "n_groups": nlstr.n_ref if nlstr else 0,
                   "strips": len(nlstr.strips) if nlstr else 0})
    extra = {"registration": reg_record,
             "field_of_view_weight_fraction": float(obs.weights.mean())}
    init_psnr = mean_psnr(capture, init)
    if init_psnr is not None:
        extra["init_psnr_db"] = init_psnr
        extra["psnr_db"] = mean_psnr(capture, image)
    return MethodOutput(image=image.detach().cpu().numpy().astype(np.float32), params=params, history=history,
                        extra=extra, unobserved=data.unobserved_mask)


@register_method("caps", input_kind="caps", reference=REFERENCE,
                 description="CAPS: CAGF-confidence-guided data term + nonlocal sparse tensor regularization, ADMM "
                             "(joint demosaicking, 4x SR of each Bayer sub-image, denoising)")
def caps(capture, *, context: RunContext) -> MethodOutput:
    return run_caps(capture, context)


@register_method("caps-no-cagf", input_kind="caps", reference=REFERENCE + " (ablation 'No CAGF', 5.2)",
                 description="CAPS ablation: the data term uses only the observations of the same channel")
def caps_no_cagf(capture, *, context: RunContext) -> MethodOutput:
    return run_caps(capture, context, use_cagf=False)


@register_method("caps-no-nlstr", input_kind="caps", reference=REFERENCE + " (ablation 'No NLSTR', 5.2)",
                 description="CAPS ablation: confidence-guided data term only (no nonlocal sparse tensor prior)")
def caps_no_nlstr(capture, *, context: RunContext) -> MethodOutput:
    return run_caps(capture, context, use_nlstr=False)
