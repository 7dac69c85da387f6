"""The starts of ``caps-plus``'s solver (``-p init=NAME``; not the paper's): where the analyzers agree, eq. 24's
fusion of all 16 observations; where they disagree, the apertures demosaicked on their own.

The fusion (eq. 24, ``caps``'s start, ``init=fusion``) averages the four analyzers' polarization differences
away, which is right only where the analyzers see the same structure. The demosaicked apertures
(``init=naive``: each aperture's raw frame demosaicked on its own, Menon et al. 2007 as ``caps-naive``, resampled
onto the HR grid through the same registration, bicubic) keep each analyzer's own structure at each aperture's
own sampling. With ``alpha`` ``(H, W)`` the analyzers' agreement
(:mod:`capssim.reconstruct.model.analyzer_agreement`), ``P`` the mean over the analyzers of each colour:

- ``agree``: ``P fusion + (I - P) (alpha fusion + (1 - alpha) naive)``: the polarization differences blended,
  the analyzer mean from the fusion;
- ``agree-all``: ``alpha fusion + (1 - alpha) naive``: the whole image blended;
- ``fusion``, ``naive``: either alone;
- ``array-kr``: the fast camera-array method's image (:func:`~capssim.reconstruct.kernel_regression.fusion.demosaicked_fusion`:
  the demosaicked apertures fused, their mean as the intensity, each analyzer's own detail where the intensity does
  not explain it).

With a calibration (``--calibration``) the flat field is divided out before demosaicking and the registered
images are unmixed by the calibrated analyzer, as ``caps-naive`` does.
"""

from __future__ import annotations

import torch

from capssim.errors import InputError

from ..kernel_regression.fusion import demosaicked_fusion
from ..model.aperture_demosaic import bicubic_warp, demosaicked_frames
from ..model.observation_model import calibrated_analyzer, unmix_analyzer
from ..model.polarization_split import angle_mean
from ..run_context import RunContext
from .run import fused_initialization
from .slots import problem_agreement

__all__ = ["INITIALIZATIONS", "check_initialization", "demosaicked_initialization", "start_image"]

#: ``-p init=NAME`` (module docstring)
INITIALIZATIONS = ("agree", "agree-all", "fusion", "naive", "array-kr")
#: the Bayer demosaicking of the demosaicked start (``caps-naive``'s default)
INIT_BAYER_METHOD = "menon2007"


def check_initialization(name) -> str:
    """``name`` if it is one of :data:`INITIALIZATIONS`; :class:`InputError` naming ``option init`` otherwise."""
    text = str(name).strip()
    if text not in INITIALIZATIONS:
        raise InputError("option init", repr(name), "one of " + ", ".join(INITIALIZATIONS),
                         "Use -p init=agree (the default), agree-all, fusion (caps's start), naive or array-kr.")
    return text


def demosaicked_initialization(capture, context: RunContext, geometry, *, held_out=None) -> torch.Tensor:
    """``(12, H, W)`` float32 on the context device: ``caps-naive``'s image under ``geometry``.

    Each aperture's raw frame (flat field divided out with a calibration) is demosaicked on its own
    (:func:`~capssim.reconstruct.model.aperture_demosaic.demosaicked_frames`, Menon 2007) and resampled onto the
    HR reference grid by one bicubic warp through ``geometry.raw_homographies``; channel ``c = 3 p + k``;
    unmixed by a calibrated analyzer; clipped to [0, 1]. ``held_out`` ``(4, H, W)`` bool: raw pixels the
    start must not see, filled from their same-colour neighbours first
    (:func:`~capssim.reconstruct.model.aperture_demosaic.fill_held_out`).
    """
    rgb = demosaicked_frames(capture, context, INIT_BAYER_METHOD, held_out=held_out)
    image = bicubic_warp(rgb, geometry.raw_homographies, geometry.hr_shape).reshape(12, *geometry.hr_shape)
    analyzer = calibrated_analyzer(context)
    if analyzer is not None:
        image = unmix_analyzer(image, analyzer)
    return image.clamp(0.0, 1.0).contiguous()


def start_image(capture, context: RunContext, geometry, problem, options, name: str, *, held_out=None):
    """The start ``(12, H, W)`` of ``init=name`` for ``problem`` (module docstring), or ``None`` for ``fusion``
    (the pipeline's own start, eq. 24). ``held_out``: raw pixels the demosaicked apertures must not see."""
    if name == "fusion":
        return None
    if name == "array-kr":  # the fast method's image (issue 58): the apertures demosaicked and fused
        with context.timer.stage("init_array_kr"):
            image, _ = demosaicked_fusion(capture, context, geometry, held_out=held_out)
            image = image.reshape(12, *geometry.hr_shape)
            analyzer = calibrated_analyzer(context)
            if analyzer is not None:
                image = unmix_analyzer(image, analyzer)
            return image.clamp(0.0, 1.0).contiguous()
    with context.timer.stage("init_demosaic"):
        start = demosaicked_initialization(capture, context, geometry, held_out=held_out)
        if name in ("agree", "agree-all"):
            fusion = fused_initialization(problem)
            alpha = problem_agreement(problem, options=options, stage=context.timer.stage)
            start = start + alpha * (fusion - start)  # the fusion where the analyzers agree, the apertures where not
            if name == "agree":  # the analyzer mean from the fusion everywhere
                start = angle_mean(fusion) + start - angle_mean(start)
            start = start.clamp(0.0, 1.0)
        return start.contiguous()
