"""``caps-iccp``: the cascade ablation of the paper (section 5.2, 'ICCP').

"The Bayer demosaicking algorithm in [15] was adopted ... and SR reconstruction of the
monochromatic polarized images was performed independently per RGB channel, which
employed the joint constraints of (2) and (3)" with ``c1 = 0.001``, ``c2 = 0.01``.

1. each aperture's RGGB frame is demosaicked on its own by the Bayer demosaicking of [15]
   (Morimatsu et al., EARI), i.e. its colour stage, the residual interpolation of Kiku et al.
   (:func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic`, the settings of ``dofp-eari``);
   ``-p bayer_method=menon2007`` (or ``malvar2004``, ``bilinear``) swaps it
   (:func:`capssim.reconstruct.methods.caps_naive.demosaic_apertures`);
2. for each colour k, the 4 demosaicked frames (one per polarizer angle, raw resolution
   ``H x W``) are the observations of a 4-channel SR problem (polarizer angles of colour k)
   with the observation model ``IntegrateDecimate_2(Blur_psf(Warp_{H_n}(x_p)))``, i.e. the
   CAPS raw model of ``capssim.operators.camera.caps_raw_operator`` without the CFA (the
   cascade's assumption that demosaicking recovered full colour);
3. the same CAGF (between the 4 polarization channels), initialization, data term, NLSTR
   (blocks ``8 x 8 x 4``) and ADMM as ``caps``; the three results are interleaved into the
   12 channels ``c = 3 p + k``. Steps 1-2 are this configuration's front end
   (:func:`cascade_observations`); step 3 is the CAPS pipeline (:mod:`capssim.reconstruct.pipeline`),
   so ``-p prior=NAME`` and ``-p data_term=NAME`` swap its slots as for ``caps``.

A demosaicked pixel gets weight 0 if a saturated raw pixel lies in its 3x3 neighbourhood.

With a calibration (``--calibration``): the raw frames are divided by their flat fields before
demosaicking, the operator takes the per-aperture PSFs, the geometry is the calibration's (when it
has one), and colour k's data term mixes its 4 channels by the calibrated analyzer's 4x4 block
(exact adjoint); the initialization is unmixed per pixel by that block's inverse.
"""

from __future__ import annotations

import numpy as np
import torch

from capssim.camera.array_geometry import ArrayGeometry
from capssim.conventions import N_APERTURES
from capssim.operators.base import Composition, Reshape
from capssim.operators.blur import Convolve
from capssim.operators.sampling import IntegrateDecimate
from capssim.operators.warp import Warp

from ..model.data_term import field_of_view_mask
from ..model.observation_model import calibrated_analyzer, method_geometry, method_psf_kernels
from ..model.rearrange import Observations
from ..pipeline import FrontEnd, PipelineConfig, Problem, run_pipeline
from ..registry import MethodOutput, RunContext, register_method
from .caps import REFERENCE
from .caps_naive import bayer_demosaic_function, flat_corrected_raw
from .caps_naive import demosaic_apertures as demosaic

#: the paper's ICCP demosaicking: residual interpolation, the colour stage of [15]
DEFAULT_BAYER_METHOD = "ri"


def demosaic_apertures(raw: np.ndarray, saturated: np.ndarray, *, bayer_method: str = DEFAULT_BAYER_METHOD,
                       clip_max: float = 1.0, cfa: str = "RGGB") -> tuple[np.ndarray, np.ndarray]:
    """``(4, H, W)`` RGGB frames -> ``(4, 3, H, W)`` RGB (clipped to [0, ``clip_max``]) and ``(4, H, W)``
    data weights."""
    from scipy.ndimage import maximum_filter

    rgb = demosaic(raw, bayer_method=bayer_method, clip_max=clip_max, cfa=cfa)
    near_saturated = np.stack([maximum_filter(saturated[n].astype(np.uint8), size=3) > 0 for n in range(raw.shape[0])])
    return rgb, (~near_saturated).astype(np.float32)


def aperture_sampling_operator(geometry: ArrayGeometry, kernel):
    """``(4, 2H, 2W) -> (4, H, W)``: warp, PSF, 2x2 integration (the CAPS raw model without CFA).

    ``kernel``: one PSF, or a list of 4 (one per aperture, a calibrated rig's).
    """

    hh, ww = geometry.hr_shape
    n = N_APERTURES
    return Composition([
        Reshape((n, hh, ww), (n, 1, hh, ww)),
        Warp(geometry.aperture_homographies, 1, (hh, ww)),
        Convolve(kernel, (n, 1, hh, ww)),
        IntegrateDecimate(2, (n, 1, hh, ww)),
        Reshape((n, 1, hh // 2, ww // 2), (n, hh // 2, ww // 2)),
    ], name="aperture_sampling")


def cascade_observations(capture, context: RunContext, options, *, bayer_method: str = DEFAULT_BAYER_METHOD
                         ) -> FrontEnd:
    """The cascade's front end: each aperture demosaicked, then one 4-channel problem per colour.

    Parameters
    ----------
    capture : Capture
        The CAPS capture (4 RGGB raw frames ``(H/2, W/2)``).
    context : RunContext
        The run (device, timer, registration choices, calibration).
    options : CapsOptions
        The run's options (``psf_sigma``, ``fov_mask``).
    bayer_method : str
        The Bayer demosaicking (``-p bayer_method``; one of ``caps_naive.BAYER_METHODS``).

    Returns
    -------
    FrontEnd
        Three problems (colour k: the 4 demosaicked frames ``(4, H/2, W/2)`` of output channels
        ``k::3``), the registration and PSF records, ``params`` ``bayer_method`` and ``channels_per_problem``.
    """
    bayer_method = bayer_demosaic_function(bayer_method)[0]
    dev, timer, hr_shape = context.device, context.timer, capture.hr_shape
    analyzer = calibrated_analyzer(context)  # (12, 12) or None (ideal)
    with timer.stage("demosaic"):
        raw, clip_max = flat_corrected_raw(capture, context)  # gain and vignetting divided out (calibrated)
        rgb, weights = demosaic_apertures(raw, capture.caps_saturated(), bayer_method=bayer_method,
                                          clip_max=clip_max, cfa=capture.cfa)
        lr_images, lr_saturated = capture.lr_images()
    with timer.stage("registration"):
        geometry, reg_record = method_geometry(capture, context, images=lr_images, saturated=lr_saturated)
        raw_h = geometry.raw_homographies   # HR reference -> raw pixel of each aperture
    with timer.stage("operator"):
        kernel, kernels, psf_record = method_psf_kernels(capture, context, options.psf_sigma)
        operator = aperture_sampling_operator(geometry, kernel if kernels is None else kernels)
        inside = field_of_view_mask(raw_h, raw.shape[-2:], hr_shape, half_extent=0.25) if options.fov_mask else 1.0
        weights = weights * inside
    problems = []
    for k in range(3):
        obs = Observations(images=torch.as_tensor(rgb[:, k], device=dev),
                           weights=torch.as_tensor(np.ascontiguousarray(weights), dtype=torch.float32, device=dev),
                           channel_of=torch.arange(N_APERTURES, device=dev), n_channels=N_APERTURES)
        # a calibrated analyzer: aperture n sees sum_p A[3n+k, 3p+k] x_p in colour k (exact mixing)
        mixing = None if analyzer is None else analyzer[k::3, k::3]
        problems.append(Problem(obs=obs, operator=operator, homographies=raw_h, seen=obs, mixing=mixing,
                                unmix=mixing, channels=slice(k, None, 3), label=f"colour {'RGB'[k]}",
                                history_fields={"colour": "RGB"[k]}))
    return FrontEnd(problems=problems, registration=reg_record, psf=psf_record,
                    params={"bayer_method": bayer_method, "channels_per_problem": N_APERTURES})


#: ablation 'ICCP' (5.2): the cascade front end, the paper's c1 = 0.001, c2 = 0.01
ICCP = PipelineConfig(front_end=cascade_observations, defaults={"c1": 0.001, "c2": 0.01},
                      front_end_options={"bayer_method": DEFAULT_BAYER_METHOD})


@register_method("caps-iccp", input_kind="caps", reference=REFERENCE + " (ablation 'ICCP', 5.2)",
                 description="CAPS ablation: cascade - demosaic each aperture (residual interpolation), then SR per "
                             "RGB channel on its 4 polarization images (c1=0.001, c2=0.01)")
def caps_iccp(capture, *, context: RunContext) -> MethodOutput:
    return run_pipeline(capture, context, ICCP)
