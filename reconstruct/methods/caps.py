"""The paper's CAPS reconstruction and two of its ablations (section 3-5, Fig. 3, Algorithm 1).

Reference: "Joint constraints of guided filtering based confidence and nonlocal sparse
tensor for color polarization super-resolution imaging", Optics Express 32(2), 2364 (2024).

Pipeline (each step its own module):

1. rearrangement of the 4 RGGB frames into 16 observations (``reconstruct.rearrange``, 3.1);
2. registration: the stored homographies (``--true-warps``) or ``reconstruct.registration``;
3. CAGF confidence between all channel pairs (``reconstruct.cagf``, eq. 12-14);
4. initialization fusing all 16 observations on the HR grid (``reconstruct.init_fusion``);
5. ADMM (``reconstruct.admm``, eq. 20-30) with the confidence-guided data term
   (``reconstruct.data_term``, eq. 15-16, 25-26) and NLSTR (``reconstruct.nlstr``, 3.3).

Ablations (section 5.2), the same code with one switch each:

* ``caps-no-cagf``: the data term uses only the observations of the same channel;
* ``caps-no-nlstr``: data term only (steepest descent of eq. 16 from the same initialization).

``caps-iccp`` (the cascade) lives in :mod:`reconstruct.methods.caps_iccp`.

The sampling operator ``M`` is the shared observation model
``capssim.operators.lr_sampling_operator`` with the capture's PSF (the paper uses an
isotropic Gaussian kernel; simulated captures store a Gaussian PSF, and ``psf_sigma``
overrides it, e.g. for real captures).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields

import numpy as np
import torch

from capssim.errors import CapssimError, InputError, UnknownNameError
from capssim.reconstruct.admm import ADMMParameters
from capssim.reconstruct.nlstr import NLSTRParameters
from capssim.reconstruct.registry import MethodOutput, RunContext, register_method

log = logging.getLogger(__name__)

REFERENCE = "Optics Express 32(2) 2364 (2024), sections 3-5"


@dataclass
class CapsOptions:
    """Every option of the CAPS methods, with the paper's defaults (section 5.1, DESIGN.md)."""

    # ADMM (section 4, 5.1): defaults from reconstruct.admm.ADMMParameters
    iterations: int = ADMMParameters.iterations
    mu0: float = ADMMParameters.mu0
    grow_rate: float = ADMMParameters.grow_rate
    grow_step: int = ADMMParameters.grow_step
    dt: float = ADMMParameters.dt
    n_similar: int = ADMMParameters.n_similar
    n_similar_step: int = ADMMParameters.n_similar_step
    n_similar_min: int = ADMMParameters.n_similar_min
    rematch_change: float = ADMMParameters.rematch_change
    rematch_min_gap: int = ADMMParameters.rematch_min_gap
    rematch_max_gap: int = ADMMParameters.rematch_max_gap
    # NLSTR (section 3.3): defaults from reconstruct.nlstr.NLSTRParameters
    block: int = NLSTRParameters.block
    stride: int = NLSTRParameters.stride
    search_radius: int = NLSTRParameters.search_radius
    c1: float = NLSTRParameters.c1
    c2: float = NLSTRParameters.c2
    adaptive: str = NLSTRParameters.adaptive
    weight_bandwidth: float = NLSTRParameters.weight_bandwidth
    strip_mb: float = 48.0  # NLSTR working-set bound per strip (MiB)
    # CAGF (section 3.2)
    nu: float = 0.2
    cagf_radius: int = 4
    cagf_eps: float = 1e-4
    # observation model
    psf_sigma: float = -1.0  # < 0: the capture's PSF
    fov_mask: bool = True
    # diagnostics
    track_psnr: bool = False

    @classmethod
    def from_options(cls, options: dict, **overrides) -> "CapsOptions":
        known = {f.name: f for f in fields(cls)}
        values = dict(overrides)
        for key, raw in (options or {}).items():
            name = str(key).replace("-", "_")
            if name not in known:
                raise UnknownNameError("option", key, list(known))
            values[name] = _coerce(name, raw, type(getattr(cls, name)))
        return cls(**values)

    def admm_parameters(self) -> ADMMParameters:
        return ADMMParameters(**{f.name: getattr(self, f.name) for f in fields(ADMMParameters)})

    def nlstr_parameters(self) -> NLSTRParameters:
        shared = {f.name: getattr(self, f.name) for f in fields(NLSTRParameters) if hasattr(self, f.name)}
        return NLSTRParameters(**shared, strip_bytes=int(self.strip_mb * 2**20))

    def validated_parameters(self) -> tuple[ADMMParameters, NLSTRParameters]:
        """The ADMM and NLSTR parameters, each checked (:class:`InputError` on a bad value)."""
        admm_params, nl_params = self.admm_parameters(), self.nlstr_parameters()
        admm_params.validate()
        nl_params.validate()
        return admm_params, nl_params

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


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
def psf_kernel(capture, opts: CapsOptions) -> tuple[np.ndarray, dict]:
    """The sampling kernel on the HR grid and its description."""
    from capssim.operators.blur import gaussian_psf_kernel

    if opts.psf_sigma >= 0:
        return gaussian_psf_kernel(opts.psf_sigma), {"type": "gaussian", "sigma_hr_px": opts.psf_sigma,
                                                      "source": "option psf_sigma"}
    spec = dict(capture.meta.get("psf") or {"type": "none"})
    spec["source"] = "capture meta.json"
    return capture.psf_kernel(), spec


def truth_known(capture) -> bool:
    return capture.meta.get("kind") in ("simulated", "rendered")


def lr_homographies(capture, context: RunContext, *, images: np.ndarray, saturated: np.ndarray) -> tuple[np.ndarray, dict]:
    """The 16 HR-reference -> sub-image homographies (true or estimated) and a record of them."""
    from capssim.homography import registration_error_hr_px

    hr_shape = capture.hr_shape
    if context.true_warps:
        est = capture.true_lr_homographies()
        record = {"source": "true (meta.json)"}
    else:
        try:
            from capssim.reconstruct.registration import estimate_lr_homographies, registration_mode_arguments
        except ImportError as exc:
            raise CapssimError(
                "estimated warps need reconstruct.registration, which is not available in this build "
                f"({exc}); pass --true-warps (true_warps=True) to use the homographies stored in meta.json."
            ) from exc
        result = estimate_lr_homographies(images.astype(np.float32), hr_shape=hr_shape, saturated=saturated,
                                          model="similarity", device=str(context.device),
                                          **registration_mode_arguments(context.registration))
        est = np.asarray(result.lr_homographies, dtype=np.float64)
        if est.shape != (16, 3, 3) or not np.all(np.isfinite(est)):
            raise CapssimError(f"registration returned invalid homographies (shape {est.shape}, "
                               f"finite: {bool(np.all(np.isfinite(est)))})")
        record = {"source": "estimated (reconstruct.registration)", "mode": context.registration,
                  "luminance": result.diagnostics.get("luminance"), "time_s": result.diagnostics.get("time_s"),
                  "warnings": list(result.diagnostics.get("warnings", [])),
                  "fallbacks": {str(a["aperture"]): a["fallback"] for a in result.diagnostics.get("apertures", [])
                                if a.get("fallback") not in ("none", "reference")}}
    if truth_known(capture):
        err = registration_error_hr_px(est, capture.true_lr_homographies(), hr_shape)
        record.update({"error_hr_px_median": float(np.median(err)), "error_hr_px_max": float(np.max(err)),
                       "error_hr_px": [float(e) for e in err]})
    return est, record


def psnr_observer(capture, device):
    """Per-iteration mean PSNR of the 12 channels (data range 1), when ground truth is loaded."""
    if capture.gt is None:
        return None
    gt = torch.as_tensor(capture.gt, dtype=torch.float32, device=device)

    def observe(i, x):
        mse = (x.clamp(0, 1) - gt).square().mean(dim=(-2, -1)).clamp(min=1e-20)
        return {"psnr_db": float((-10 * torch.log10(mse)).mean())}

    return observe


def mean_psnr(capture, image: torch.Tensor) -> float | None:
    if capture.gt is None:
        return None
    gt = torch.as_tensor(capture.gt, dtype=torch.float32, device=image.device)
    mse = (image.clamp(0, 1) - gt).square().mean(dim=(-2, -1)).clamp(min=1e-20)
    return float((-10 * torch.log10(mse)).mean())


def run_caps(capture, context: RunContext, *, use_cagf: bool = True, use_nlstr: bool = True) -> MethodOutput:
    """The joint CAPS reconstruction (and its no-CAGF / no-NLSTR ablations)."""
    from capssim.operators.camera import lr_sampling_operator
    from capssim.reconstruct.admm import admm
    from capssim.reconstruct.cagf import cagf_confidence
    from capssim.reconstruct.data_term import ConfidenceDataTerm, field_of_view_mask
    from capssim.reconstruct.init_fusion import fuse_initial_estimate
    from capssim.reconstruct.nlstr import NonlocalSparseTensor
    from capssim.reconstruct.rearrange import observations_from_capture

    opts = CapsOptions.from_options(context.options)
    admm_params, nl_params = opts.validated_parameters()
    dev, timer = context.device, context.timer
    hr_shape = capture.hr_shape
    with timer.stage("rearrange"):
        obs = observations_from_capture(capture, device=dev)
        lr_images, lr_saturated = capture.lr_images()
    with timer.stage("registration"):
        homographies, reg_record = lr_homographies(capture, context, images=lr_images, saturated=lr_saturated)
    with timer.stage("operator"):
        kernel, psf_record = psf_kernel(capture, opts)
        operator = lr_sampling_operator(hr_shape, homographies, kernel)
        if opts.fov_mask:
            inside = field_of_view_mask(homographies, tuple(obs.images.shape[-2:]), hr_shape, half_extent=0.125)
            obs.weights = obs.weights * torch.as_tensor(inside, dtype=obs.weights.dtype, device=dev)
    confidence = None
    if use_cagf:
        with timer.stage("cagf"):
            confidence = cagf_confidence(obs.images, homographies, obs.channel_of, obs.n_channels, hr_shape,
                                         weights=obs.weights, nu=opts.nu, radius=opts.cagf_radius, eps=opts.cagf_eps)
    with timer.stage("init"):
        init = fuse_initial_estimate(obs, homographies, hr_shape)
    data = ConfidenceDataTerm(obs, operator, confidence=confidence)
    nlstr = None
    if use_nlstr:
        with timer.stage("nlstr_setup"):
            nlstr = NonlocalSparseTensor((obs.n_channels, *hr_shape), nl_params, device=dev)
    observer = psnr_observer(capture, dev) if opts.track_psnr else None
    image, history = admm(data, init, nlstr, admm_params, stage=timer.stage, progress=context.report,
                          observer=observer)
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
                        extra=extra)


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
