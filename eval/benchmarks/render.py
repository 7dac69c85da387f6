"""Measurements behind the rendering choices (``capssim bench render`` prints them as tables).

* :func:`scene_costs`: per scene, the variant, path, spp and wall time of ``render_capture``, and
  the seconds each choice saved, measured by rendering the alternative (``measure_savings``).
* :func:`warp_accuracy`: for a planar scene, the RMS difference between the raw frames of the
  planar warp (at several oversampling factors) and of real per-aperture renders, next to the
  Monte-Carlo noise and to the shared observation model applied to the ground truth.
* :func:`sampler_gain`: RMS error of the reference view against a high-spp render, for Mitsuba's
  ``independent`` sampler and for the per-pixel ``multijitter`` layout the renderer uses.
"""

from __future__ import annotations

import time

import numpy as np
import torch

import capssim.render.integrator as integrator
from capssim.camera.psf import PSF
from capssim.operators import caps_raw_operator
from capssim.render import get_scene, render_capture
from capssim.render.mitsuba_plugins import register_plugins
from capssim.render.pinhole_array import RigTolerances, build_array
from capssim.render.spectral import CameraResponse
from capssim.render.variants import select_variant


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def scene_costs(scenes, *, size: int, spp: int | None, target_noise: float | None, measure: bool) -> list[dict]:
    """Per scene: variant, path, spp, render and wall time (s), and the seconds each choice saved."""
    rows = []
    for name in scenes:
        t0 = time.perf_counter()
        cap = render_capture(name, size=size, spp=spp, target_noise=target_noise, measure_savings=measure)
        wall = time.perf_counter() - t0
        r = cap.meta["render"]
        timing = cap.render_timing["timing_s"]
        render_s = timing.get("render_reference_s", 0) + timing.get("pilot_s", 0) + sum(
            v for k, v in timing.items() if k.startswith("render_aperture"))
        row = {"scene": name, "variant": r["variant"]["variant"], "path": r["path"], "spp": r["spp_per_hr_pixel"],
               "render_s": render_s, "total_s": timing["total_s"] if not measure else None, "wall_s": wall}
        for c in cap.render_timing["choices"]:
            row[f"saved:{c['choice']}"] = (c.get("saved_s"), c.get("saved_how", ""))
        rows.append(row)
    return rows


def warp_accuracy(scene: str, *, size: int, spp: int, oversamples=(1, 2, 4), border: int = 4) -> list[dict]:
    """RMS raw-frame difference of the planar warp (per oversampling) and of the model vs per-aperture renders."""
    ref = render_capture(scene, size=size, spp=spp, planar="off", psf=PSF.none())
    inner = (slice(1, None), slice(border, -border), slice(border, -border))
    mean = float(ref.caps_raw.mean())
    rows = []
    for k in oversamples:
        t0 = time.perf_counter()
        warped = render_capture(scene, size=size, spp=spp, planar="on", oversample=k, psf=PSF.none())
        seconds = time.perf_counter() - t0
        diff = (warped.caps_raw - ref.caps_raw)[inner]
        noise = _rms((warped.caps_raw - ref.caps_raw)[0, border:-border, border:-border]) / np.sqrt(2)
        rows.append({"method": f"planar warp, {k}x render", "rms": _rms(diff), "relative": _rms(diff) / mean,
                     "mc_noise_rms": noise, "seconds": seconds})
    gt = torch.from_numpy(ref.gt.astype(np.float64))
    model = caps_raw_operator((size, size), ref.aperture_homographies(), ref.psf_kernel())(gt).numpy()
    diff = (model - ref.caps_raw)[inner]
    rows.append({"method": "caps_raw_operator(gt) (HR bilinear warp)", "rms": _rms(diff), "relative": _rms(diff) / mean,
                 "mc_noise_rms": None, "seconds": None})
    return rows


def sampler_gain(scene: str, *, size: int, spp_values=(16, 64), reference_spp: int = 1024) -> list[dict]:
    """RMS error of the reference view against a ``reference_spp`` render, per sampler and spp."""
    sc = get_scene(scene)
    params = sc.params(None)
    select_variant("auto", spectral=sc.info.spectral, polarized=sc.info.polarizing)
    register_plugins()
    import mitsuba as mi

    pose = sc.camera_pose(params)
    cam = build_array(origin=pose.origin, target=pose.target, up=pose.up, fov_deg=pose.fov_deg, size=size,
                      geometry=RigTolerances(), rng=np.random.default_rng(0)).cameras[0]
    mscene = mi.load_dict(sc.mitsuba_dict(params))
    response = CameraResponse().calibrate()
    saved = integrator.SAMPLER_TYPE
    rows = []
    try:
        integrator.SAMPLER_TYPE = "multijitter"
        ref = integrator.render_view(mscene, cam, spp=reference_spp, seed=12345, response=response).mean
        for sampler in ("independent", "multijitter"):
            integrator.SAMPLER_TYPE = sampler
            for spp in spp_values:
                view = integrator.render_view(mscene, cam, spp=spp, seed=1, response=response)
                rows.append({"sampler": sampler, "spp": spp, "rms_error": _rms(view.mean - ref)})
    finally:
        integrator.SAMPLER_TYPE = saved
    return rows
