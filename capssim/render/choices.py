"""What each of the renderer's choices was, why, and the time it saved (``meta.json["render"]["choices"]``).

The choices: the cheapest Mitsuba variant the scene needs, the planar warp (or per-aperture
renders through each aperture's own polarizer only), and the spp from a target noise. Their
savings are estimated from the render times, or, with ``measure_savings``, measured by
rendering each alternative (compile time excluded from both sides).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from capssim.conventions import N_APERTURES
from capssim.render.camera_model import warp_margin
from capssim.render.integrator import derive_seed, render_view
from capssim.render.mitsuba_plugins import register_plugins
from capssim.render.sample_budget import SamplePlan, square_at_least
from capssim.render.scene_base import SceneInfo
from capssim.render.spectral import CameraResponse
from capssim.render.variants import VariantChoice, variant_name

#: the fixed spp per HR pixel the target-noise rule is compared with
FIXED_SPP_REFERENCE = 256
#: render time relative to the full spectral-polarized variant (docs/notes/rendering-internals.md);
#: used only to estimate the variant saving when it is not measured; scene-dependent
VARIANT_RELATIVE_COST = {"mono": 0.45, "mono_polarized": 0.96, "spectral": 0.91, "spectral_polarized": 1.0}


@dataclass
class RenderPath:
    """How the views were rendered: ``use_warp`` (planar warp) or per aperture, the reference
    render's ``fine`` grid factor and ``margin`` (HR pixels), and the measured parallax ``depth``
    (:func:`capssim.render.pinhole_array.parallax_residual`)."""

    use_warp: bool
    fine: int
    margin: int
    depth: dict

    @property
    def name(self) -> str:
        return "planar-warp" if self.use_warp else "per-aperture"


def _variant_choice(choice: VariantChoice, info: SceneInfo, rendered_s: float) -> dict:
    chosen_kind = choice.variant.split("_ad_")[-1] if "_ad_" in choice.variant else None
    full = variant_name(choice.backend, spectral=True, polarized=True)
    record = {"choice": "variant", "value": choice.variant, "instead_of": full,
              "reason": f"scene needs {'spectral' if info.spectral else 'no spectral'} and "
                        f"{'polarized' if info.polarizing else 'no polarized'} light transport"
                        + (f"; {choice.fallback_reason}" if choice.fallback_reason else "")}
    if chosen_kind and choice.variant != full:
        ratio = VARIANT_RELATIVE_COST["spectral_polarized"] / VARIANT_RELATIVE_COST[chosen_kind]
        record.update(saved_s=rendered_s * (ratio - 1.0),
                      saved_how=f"estimated: render time x {ratio:.2f} (measured relative variant cost) - 1")
    else:
        record.update(saved_s=0.0, saved_how="none (the full variant)")
    return record


def _path_choices(path: RenderPath, info: SceneInfo, main_s: float, aperture_s: list[float]) -> list[dict]:
    depth = path.depth
    if path.use_warp:
        return [{"choice": "planar-warp",
                 "value": f"reference rendered once at {path.fine}x with a {path.margin} px margin; apertures are its "
                          "plane-homography warps",
                 "instead_of": "three more aperture renders",
                 "reason": f"scene is planar; parallax residual {depth['max_hr_px']:.2g} HR px",
                 "saved_s": 3.0 * main_s, "saved_how": "estimated: 3 x the reference render (same samples "
                                                      "per HR pixel)"}]
    return [{"choice": "per-aperture",
             "value": "apertures 1-3 rendered from their own positions; aperture 0 is the ground-truth render",
             "instead_of": "four aperture renders besides the ground truth",
             "reason": ("scene is not planar" if not info.planar else "planar warp disabled")
                       + f"; parallax residual up to {depth['max_hr_px']:.3g} HR px",
             "saved_s": float(np.mean(aperture_s)), "saved_how": "estimated: one aperture render"},
            {"choice": "own-polarizer-only",
             "value": "each aperture keeps only what its own analyzer transmits (3 of 12 channels)",
             "instead_of": "four polarizer-plate renders per aperture",
             "reason": "an aperture only sees through its own polarizer",
             "saved_s": 3.0 * float(sum(aperture_s)), "saved_how": "estimated: 3 x the aperture renders"}]


def _spp_choice(spp: int | None, plan: SamplePlan, path: RenderPath, spp_hr: int, rendered_s: float) -> dict:
    main_spp_hr = spp_hr if path.use_warp else plan.aperture_spp
    if spp is not None:
        return {"choice": "spp", "value": main_spp_hr, "instead_of": None, "reason": "given (spp)",
                "saved_s": 0.0, "saved_how": "none"}
    noise_model = plan.noise_model
    return {"choice": "spp-from-target-noise", "value": main_spp_hr,
            "instead_of": f"a fixed {FIXED_SPP_REFERENCE} spp",
            "reason": f"pilot noise {[round(v, 5) for v in noise_model['pilot_noise_rms']]} at "
                      f"{noise_model['pilot_spp_per_hr_pixel']} spp per HR pixel (exponent "
                      f"{noise_model['convergence_exponent']:.2f}), target {plan.target:.3g}; ground truth "
                      f"{spp_hr} spp in all" + ("" if path.use_warp else f", apertures {plan.aperture_spp} spp"),
            "saved_s": rendered_s * (FIXED_SPP_REFERENCE / main_spp_hr - 1.0),
            "saved_how": "estimated: render time scaled by spp (negative: the target needed more)"}


def choice_records(choice: VariantChoice, info: SceneInfo, path: RenderPath, plan: SamplePlan, *,
                   spp: int | None, spp_hr: int, timing: dict) -> list[dict]:
    """One record per choice (``choice``, ``value``, ``instead_of``, ``reason``, ``saved_s``,
    ``saved_how``), the savings estimated from the stage times ``timing`` (seconds)."""
    main_s = timing["render_reference_s"] + timing.get("pilot_s", 0.0)  # the whole reference view
    aperture_s = [timing.get(f"render_aperture_{n}_s", 0.0) for n in range(1, N_APERTURES)]
    rendered_s = main_s + sum(aperture_s)
    return [_variant_choice(choice, info, rendered_s), *_path_choices(path, info, main_s, aperture_s),
            _spp_choice(spp, plan, path, spp_hr, rendered_s)]


def _timed_render(mscene, camera, *, spp, seed, response, **kwargs) -> float:
    """Seconds to render ``camera`` at ``spp``, not counting the kernel compile (done on a 4x4 crop first)."""
    render_view(mscene, replace(camera, width=4, height=4), spp=spp, seed=seed, response=response, **kwargs)
    t0 = time.perf_counter()
    render_view(mscene, camera, spp=spp, seed=seed, response=response, **kwargs)
    return time.perf_counter() - t0


def measure_savings(sc, params, choice: VariantChoice, array, main_camera, main_spp: int, path: RenderPath,
                    seed: int, *, response_name: str) -> dict:
    """Render what each choice avoided and time it (``measure_savings=True``); seconds saved per choice.

    Compile time is excluded from both sides of every comparison (:func:`_timed_render`).
    """
    import mitsuba as mi

    out = {}
    fine = path.fine
    response = CameraResponse(response_name).calibrate()
    mscene = mi.load_dict(sc.mitsuba_dict(params))
    chosen_main = _timed_render(mscene, main_camera, spp=main_spp, seed=derive_seed("measure-main", seed),
                                response=response)
    n_views = 1 if path.use_warp else 4
    if path.use_warp:
        # the alternative: three apertures rendered for real at the same samples per HR pixel
        cam = array.cameras[1].expanded(warp_margin(array.homographies, array.cameras[0].width, 0))
        spp_ap = square_at_least(main_spp * fine * fine)
        out["planar-warp"] = 3.0 * _timed_render(mscene, cam, spp=spp_ap, seed=derive_seed("measure-ap", seed),
                                                 response=response, mode="analyzer", analyzer_deg=45.0)
    fixed = square_at_least(FIXED_SPP_REFERENCE / (fine * fine))
    fixed_s = _timed_render(mscene, main_camera, spp=fixed, seed=derive_seed("measure-fixed", seed), response=response)
    out["spp-from-target-noise"] = n_views * (fixed_s - chosen_main)
    full = variant_name(choice.backend, spectral=True, polarized=True)
    if choice.variant != full:
        mi.set_variant(full)
        register_plugins()
        response_full = CameraResponse(response_name).calibrate()
        scene_full = mi.load_dict(sc.mitsuba_dict(params))
        full_s = _timed_render(scene_full, main_camera, spp=main_spp, seed=derive_seed("measure-main", seed),
                               response=response_full)
        mi.set_variant(choice.variant)
        out["variant"] = n_views * (full_s - chosen_main)
        out["variant_cost_ratio"] = full_s / max(chosen_main, 1e-9)
    return out


def apply_measured(choices: list[dict], measured: dict) -> None:
    """Replace the estimated savings of ``choices`` with the ``measured`` ones (in place)."""
    for c in choices:
        if c["choice"] in measured:
            c["saved_s"], c["saved_how"] = measured[c["choice"]], "measured (compile time excluded)"
        if c["choice"] == "variant" and "variant_cost_ratio" in measured:
            c["measured_cost_ratio"] = measured["variant_cost_ratio"]


__all__ = ["FIXED_SPP_REFERENCE", "RenderPath", "VARIANT_RELATIVE_COST", "apply_measured", "choice_records",
           "measure_savings"]
