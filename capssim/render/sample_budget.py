"""How many Monte-Carlo samples the reference view needs, and its render (docs: guides/rendering.md).

With a target noise instead of a fixed spp, two pairs of small pilot renders (``s0`` and
``4 s0`` samples per render pixel) measure the Monte-Carlo RMS error of the 12-channel ground
truth and its convergence rate ``sigma ~ spp^-alpha`` (alpha in [0.5, 1]: 0.5 for independent
samples, more when the stratification works). Rendering stops as soon as the pooled ground
truth (inverse-variance weights) reaches the target; otherwise one main render, of the
smallest square spp that reaches it, makes up the rest. Aperture renders need the target
alone.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from capssim.operators import IntegrateDecimate
from capssim.render.integrator import ViewRender, combine_weighted, derive_seed, render_view, stokes_to_twelve
from capssim.render.pinhole_array import PinholeCamera
from capssim.render.spectral import CameraResponse

log = logging.getLogger(__name__)

#: first pilot pair: about this many samples per HR pixel (second pair: 4x)
PILOT_SPP_HR = 4

#: ``stage, total -> advance(n)`` (or None): progress reporting of one render
Progress = Callable[[str, int], Callable[[int], None] | None]


def pooled_noise(sigmas) -> float:
    """RMS noise of inverse-variance-pooled independent estimates with RMS noise ``sigmas``."""
    sig = np.asarray(sigmas, dtype=np.float64)
    if sig.size == 0:
        return float("inf")
    if np.any(sig <= 0):
        return 0.0
    return float(1.0 / np.sqrt(np.sum(1.0 / np.square(sig))))


def square_at_least(x: float) -> int:
    """Smallest perfect square >= x (>= 1): the multijitter sampler stratifies on a square grid."""
    r = max(1, math.isqrt(max(0, int(math.ceil(x - 1e-9)))))
    while r * r < x - 1e-9:
        r += 1
    return r * r


def to_tensor(x: np.ndarray) -> torch.Tensor:
    """``x`` as a contiguous float64 tensor."""
    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64))


@dataclass
class ReferenceView:
    """Where and how the reference view is rendered.

    ``camera``: the render camera (margin included, ``fine`` times finer than the ground
    truth); ``crop``: the ground-truth window on the HR grid; ``seed``: the Monte-Carlo seed.
    """

    mscene: object
    camera: PinholeCamera
    fine: int
    crop: slice
    response: CameraResponse
    seed: int
    progress: Progress

    def render(self, spp: int, seed: int, stage: str) -> ViewRender:
        """One Stokes render of the reference camera at ``spp`` samples per render pixel."""
        return render_view(self.mscene, self.camera, spp=spp, seed=seed, response=self.response, mode="stokes",
                           group=self.fine,
                           progress=self.progress(stage, self.camera.width * self.camera.height * spp))

    def gt_estimate(self, view: ViewRender) -> np.ndarray:
        """12-channel HR estimate (before the PSF, cropped) of a render of this view."""
        twelve = to_tensor(stokes_to_twelve(view.mean))
        if self.fine > 1:
            twelve = IntegrateDecimate(self.fine, tuple(twelve.shape))(twelve)
        return twelve[:, self.crop, self.crop].numpy()


@dataclass
class SamplePlan:
    """Samples per render pixel of the main reference render (0: the pilots suffice) and of each
    aperture render; the pilot renders with their RMS noise; the fitted ``noise_model`` (None
    for a given spp)."""

    target: float
    main_spp: int
    aperture_spp: int
    pilot_views: list[ViewRender]
    pilot_sigmas: list[float]
    noise_model: dict | None


def plan_samples(view: ReferenceView, *, spp: int | None, target: float, max_spp: int, scene_name: str) -> SamplePlan:
    """The spp of the main and aperture renders: ``spp`` if given, else from pilot renders and ``target``."""
    fine = view.fine
    if spp is not None:
        main_spp = square_at_least(spp / (fine * fine))
        if main_spp * fine * fine != spp:
            log.info("spp %d rounded up to %d per HR pixel (%d per %dx finer render pixel, a perfect square for "
                     "the stratified sampler)", spp, main_spp * fine * fine, main_spp, fine)
        return SamplePlan(target, main_spp, main_spp, [], [], None)
    s0 = square_at_least(PILOT_SPP_HR / (fine * fine))
    levels, pilot_views, pilot_sigmas = [], [], []
    for level, s_l in enumerate((s0, 4 * s0)):
        pair = [view.render(s_l, derive_seed("pilot", view.seed, level, i), f"pilot {2 * level + i + 1}")
                for i in range(2)]
        sigma = float(np.sqrt(np.mean(np.square(view.gt_estimate(pair[0]) - view.gt_estimate(pair[1]))) / 2.0))
        levels.append((s_l, sigma))
        pilot_views += pair
        pilot_sigmas += [sigma, sigma]
        if pooled_noise(pilot_sigmas) <= target:
            break
    s_last, sig_last = levels[-1]
    alpha = 0.5
    if len(levels) == 2:
        (sa, sig_a), (sb, sig_b) = levels
        alpha = 1.0 if sig_b <= 0 else float(np.clip(math.log(max(sig_a, 1e-30) / sig_b) / math.log(sb / sa),
                                                      0.5, 1.0))
    main_spp, aperture_spp = 0, s_last
    if pooled_noise(pilot_sigmas) > target:
        # the main render must bring the pooled noise to the target; apertures need the target alone
        rest = 1.0 / target ** 2 - sum(1.0 / sg ** 2 for sg in pilot_sigmas if sg > 0)
        sig_needed = 1.0 / math.sqrt(rest) if rest > 0 else target
        main_spp = square_at_least(s_last * (sig_last / sig_needed) ** (1.0 / alpha))
        aperture_spp = square_at_least(max(s_last, s_last * (sig_last / target) ** (1.0 / alpha)))
        cap = max(1, math.isqrt(max(1, max_spp // (fine * fine))) ** 2)
        if max(main_spp, aperture_spp) > cap:
            log.warning("scene %s: a Monte-Carlo noise of %.2g needs about %d spp per HR pixel; capped at %d "
                        "(max_spp)", scene_name, target, max(main_spp, aperture_spp) * fine * fine, cap * fine * fine)
            main_spp, aperture_spp = min(main_spp, cap), min(aperture_spp, cap)
    noise_model = {"pilot_spp_per_hr_pixel": [lv[0] * fine * fine for lv in levels],
                   "pilot_noise_rms": [lv[1] for lv in levels], "convergence_exponent": alpha}
    return SamplePlan(target, main_spp, aperture_spp, pilot_views, pilot_sigmas, noise_model)


@dataclass
class ReferenceRender:
    """The reference view pooled from all its renders (pilots included), and its noise.

    ``spp_hr``: samples per HR pixel in all; ``noise_rms``: predicted RMS Monte-Carlo noise
    of the ground truth (None for a given spp).
    """

    pooled: ViewRender
    views: list[ViewRender]
    spp_hr: int
    noise_rms: float | None


def render_reference(view: ReferenceView, plan: SamplePlan) -> ReferenceRender:
    """The main render of ``plan`` (if any), pooled with the pilots by inverse-variance weights.

    Adds ``main_noise_rms_predicted`` to ``plan.noise_model`` when there is a main render.
    """
    views, sigmas = list(plan.pilot_views), list(plan.pilot_sigmas)
    noise_model = plan.noise_model
    if plan.main_spp > 0:
        views.append(view.render(plan.main_spp, derive_seed("main", view.seed), "reference view"))
        if noise_model is not None:
            s_l = noise_model["pilot_spp_per_hr_pixel"][-1] / (view.fine * view.fine)
            sigmas.append(noise_model["pilot_noise_rms"][-1]
                          * (s_l / plan.main_spp) ** noise_model["convergence_exponent"])
            noise_model["main_noise_rms_predicted"] = sigmas[-1]
    pooled = views[0] if len(views) == 1 else combine_weighted(views, sigmas)
    noise_rms = None if noise_model is None else pooled_noise(sigmas)
    return ReferenceRender(pooled, views, pooled.spp * view.fine * view.fine, noise_rms)


__all__ = ["ReferenceRender", "ReferenceView", "SamplePlan", "plan_samples", "pooled_noise", "render_reference",
           "square_at_least"]
