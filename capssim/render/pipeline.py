"""``render_capture``: a library scene seen through the four apertures -> a capture folder's contents.

Pipeline (each choice is recorded in ``meta.json["render"]["choices"]`` with the time it saved):

1. **Variant** (:mod:`capssim.render.variants`): the cheapest variant the scene needs
   (mono / spectral, polarized or not) on the fastest working backend (cuda -> llvm -> scalar).
2. **Array** (:mod:`capssim.render.geometry`): four apertures with baseline, tilt, roll and
   focal-scale errors; the stored homographies are the exact plane-induced ones for the
   scene's reference plane. A one-ray-per-pixel depth pass measures the parallax that the
   homographies miss (``render.depth``).
3. **Planar scenes are rendered once**: when everything visible lies on the reference plane
   (scene flag ``planar`` *and* measured parallax residual below ``PLANAR_PARALLAX_TOL_PX``),
   the reference view is rendered once, ``oversample`` times finer than the ground truth and
   with a margin, and each aperture's view is the exact plane homography of it (the shared
   :class:`~capssim.operators.Warp`, bilinear on the finer grid, then box-integrated back).
   Otherwise apertures 1-3 are rendered from their own positions, each only through its own
   polarizer angle; aperture 0's view is the ground-truth render itself.
4. **spp from a target noise**: two pairs of small pilot renders (``s0`` and ``4 s0`` samples)
   measure the Monte-Carlo RMS error of the 12-channel ground truth and its convergence rate
   ``sigma ~ spp^-alpha`` (alpha in [0.5, 1]: stratification makes it faster than 1/sqrt);
   the main spp is the smallest square that reaches ``target_noise``; the pilots are pooled
   into the ground truth with inverse-variance weights.
5. **One observation model**: everything after the renderer uses the shared operators:
   ``Convolve`` (optical PSF, applied identically to the ground truth and to every aperture),
   ``IntegrateDecimate`` (2x2 box pixels), ``BayerMosaic`` (RGGB), ``DoFPMosaic``; then the
   sensor model (``capssim.sensor``, seeded numpy) exactly as ``simulate`` does.

Because the optical PSF is already in ``gt.tiff``, ``meta.json["psf"]`` is ``none``: applying
the stored homographies, 2x2 pixel integration and RGGB sampling to ``gt.tiff`` reproduces
the noiseless raw frames up to parallax, Monte-Carlo noise and warp interpolation (the
optics PSF is in ``meta.json["render"]["optics_psf"]``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from capssim.capture import Capture, build_meta
from capssim.conventions import N_APERTURES, POLARIZER_ANGLES_DEG
from capssim.errors import InputError
from capssim.operators import Analyzer, BayerMosaic, Convolve, IntegrateDecimate, Warp, dofp_raw_operator
from capssim.psf import as_psf
from capssim.render.geometry import RigTolerances, build_array, parallax_residual, scale_matrix, shift_matrix
from capssim.render.integrator import ViewRender, combine_weighted, derive_seed, render_view, stokes_to_twelve
from capssim.render.spectral import DEFAULT_CAMERA, CameraResponse
from capssim.render.variants import select_variant, variant_name
from capssim.sensor import NoNoiseSensor, Sensor, noise_sigma_estimate

log = logging.getLogger(__name__)

MIN_SIZE = 16
PLANAR_PARALLAX_TOL_PX = 0.01
#: default Monte-Carlo target (RMS std of the 12-channel ground truth, full scale) without sensor noise
DEFAULT_TARGET_NOISE = 0.004
#: with sensor noise: this fraction of the sensor's noise at mid grey (MC adds <= 12% to the total)
TARGET_NOISE_FRACTION_OF_SENSOR = 0.5
PILOT_SPP_HR = 4       # first pilot pair: about this many samples per HR pixel (second pair: 4x)
DEFAULT_MAX_SPP = 1024  # per HR ground-truth pixel
FIXED_SPP_REFERENCE = 256  # what the target-noise rule is compared with
#: planar warp: the reference is rendered this much finer than the ground truth (auto: 4 up to
#: ``OVERSAMPLE_4_MAX_SIZE``, else 2 to bound memory). Measured on siemens-star at 128 px, 256 spp
#: (``capssim render-bench``): RMS raw error of the warped apertures against real per-aperture renders
#: 4.0% of the mean at 1x, 1.1% at 2x, 0.30% at 4x (Monte-Carlo noise alone: 0.07-0.1%).
OVERSAMPLE_4_MAX_SIZE = 512
#: render time relative to the full spectral-polarized variant, measured with ``capssim render SCENE
#: --size 128 --spp 64 --measure-savings`` (llvm, 2 busy cores; README "Rendering"): siemens-star
#: (mono) 1/2.25, aop-wheel (mono_polarized) 1/1.04, colorchecker (spectral) 1/1.10. Used only to
#: estimate the variant saving when it is not measured; scene-dependent.
VARIANT_RELATIVE_COST = {"mono": 0.45, "mono_polarized": 0.96, "spectral": 0.91, "spectral_polarized": 1.0}


@dataclass
class _Timer:
    record: dict = field(default_factory=dict)

    def add(self, key: str, seconds: float) -> None:
        self.record[key] = self.record.get(key, 0.0) + float(seconds)


def _pooled_noise(sigmas) -> float:
    """RMS noise of inverse-variance-pooled independent estimates with RMS noise ``sigmas``."""
    sig = np.asarray(sigmas, dtype=np.float64)
    if sig.size == 0:
        return float("inf")
    if np.any(sig <= 0):
        return 0.0
    return float(1.0 / np.sqrt(np.sum(1.0 / np.square(sig))))


def _square_at_least(x: float) -> int:
    """Smallest perfect square >= x (>= 1): the multijitter sampler stratifies on a square grid."""
    r = max(1, math.isqrt(max(0, int(math.ceil(x - 1e-9)))))
    while r * r < x - 1e-9:
        r += 1
    return r * r


def _check_size(size) -> int:
    try:
        s = int(size)
    except (TypeError, ValueError):
        raise InputError("size", repr(size), "an integer") from None
    if s != size or s < MIN_SIZE or s % 4:
        raise InputError("size", size, f"a multiple of 4 that is at least {MIN_SIZE} (the HR ground-truth size)",
                         f"Try --size {max(MIN_SIZE, s - s % 4)}.")
    return s


def _psf(psf: dict | None) -> tuple[dict, np.ndarray]:
    value = as_psf(psf)
    spec, kernel = value.to_spec(), value.kernel()
    return spec, kernel


def _default_target(sensor: Sensor) -> float:
    sigma = noise_sigma_estimate(sensor, 0.5)
    if sigma <= 0:
        return DEFAULT_TARGET_NOISE
    return max(1e-3, TARGET_NOISE_FRACTION_OF_SENSOR * sigma)


def trace_hits(mscene, camera) -> tuple[np.ndarray, np.ndarray]:
    """World hit points ``(H, W, 3)`` and validity ``(H, W)`` of rays through pixel centres."""
    import mitsuba as mi

    rows, cols = np.meshgrid(np.arange(camera.height, dtype=np.float64), np.arange(camera.width, dtype=np.float64),
                             indexing="ij")
    d = camera.directions(np.stack([cols, rows], axis=-1).reshape(-1, 2)).astype(np.float32)
    n = d.shape[0]
    o = np.broadcast_to(camera.origin.astype(np.float32), (n, 3))
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(np.ascontiguousarray(o[:, k])) for k in range(3))),
                   mi.Vector3f(*(mi.Float(np.ascontiguousarray(d[:, k])) for k in range(3))))
    si = mscene.ray_intersect(ray)
    valid = np.asarray(si.is_valid(), dtype=bool).reshape(camera.height, camera.width)
    p = np.stack([np.asarray(si.p[k], dtype=np.float64) for k in range(3)], axis=-1).reshape(camera.height,
                                                                                                camera.width, 3)
    return p, valid


def _warp_margin(homographies: np.ndarray, size: int, psf_radius: int) -> int:
    """HR pixels of margin the reference render needs so every aperture's warp samples real content."""
    lo, hi = -psf_radius - 1.0, size - 1.0 + psf_radius + 1.0
    corners = np.array([[lo, lo, 1.0], [hi, lo, 1.0], [lo, hi, 1.0], [hi, hi, 1.0]])
    worst = 0.0
    for h in homographies:
        back = corners @ np.linalg.inv(h).T
        back = back[:, :2] / back[:, 2:3]
        worst = max(worst, float(np.max(-back)), float(np.max(back - (size - 1))))
    return int(math.ceil(max(worst, psf_radius))) + 2


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64))


def _blur_crop(image: torch.Tensor, kernel: np.ndarray, margin: int) -> torch.Tensor:
    """Optical PSF (shared ``Convolve``) on an image rendered with ``margin`` extra pixels, then crop."""
    out = Convolve(kernel, tuple(image.shape))(image)
    if margin:
        out = out[..., margin:-margin, margin:-margin]
    return out.contiguous()


class _Progress:
    def __init__(self, callback):
        self.callback = callback

    def __call__(self, stage: str, total: int):
        if self.callback is None:
            return None
        state = {"done": 0}
        self.callback(stage, 0, total)

        def advance(n):
            state["done"] += n
            self.callback(stage, state["done"], total)
        return advance


def render_capture(scene: str, *, size: int = 256, spp: int | None = None, seed: int = 0,
                   sensor: Sensor | None = None, variant: str = "auto", dofp_layout="sony",
                   scene_params: dict | None = None, geometry_params: dict | None = None,
                   target_noise: float | None = None, record_timing: bool = True,
                   progress: Callable[[str, int, int], None] | None = None, psf: dict | None = None,
                   extinction_ratio: float | None = None, planar: str = "auto",
                   oversample: int | None = None, camera: str = DEFAULT_CAMERA,
                   max_spp: int = DEFAULT_MAX_SPP, measure_savings: bool = False,
                   render_seed: int | None = None) -> Capture:
    """Render library scene ``scene`` through the CAPS array and the DoFP camera.

    ``size`` is the HR ground-truth size (raw frames are ``size/2``); ``spp`` samples per HR
    ground-truth pixel (``None``: from ``target_noise``, the RMS Monte-Carlo std wanted in
    the 12-channel ground truth on [0, 1] full scale; default 0.004 without sensor noise,
    half the sensor's mid-grey noise with it). ``sensor`` ``None`` is noiseless. ``planar``:
    ``auto`` (scene flag + measured parallax), ``on`` or ``off``; ``oversample``: the planar
    warp's render grid factor (``None``: 4 up to 512 px, else 2). ``psf``: optical PSF spec
    (``meta.json`` style, default Gaussian sigma 0.5 HR px). ``progress(stage, done, total)``
    is called as rays finish. With ``record_timing=False`` ``meta.json`` holds no wall times
    (byte-identical regeneration); they are on ``capture.render_timing`` either way.
    ``measure_savings`` also renders the alternatives each choice avoided and records the
    measured times (slow; for the README numbers). ``render_seed`` (default ``seed``) seeds only
    the Monte-Carlo sampling, so two renders of the same array geometry can differ in noise alone.

    Returns a :class:`~capssim.capture.Capture` of kind ``rendered`` (not yet written).
    """
    from capssim.scenes import get_scene

    t_start = time.perf_counter()
    timer = _Timer()
    sc = get_scene(scene)
    info = sc.info
    params = sc.params(scene_params)
    size = _check_size(size)
    sensor = sensor if sensor is not None else NoNoiseSensor()
    if not isinstance(sensor, Sensor):
        raise InputError("sensor", type(sensor).__name__, "a capssim.sensor.Sensor or None")
    geometry = RigTolerances.from_params(geometry_params)
    psf_spec, kernel = _psf(psf)
    psf_radius = kernel.shape[0] // 2
    if planar not in ("auto", "on", "off"):
        raise InputError("planar", planar, "'auto', 'on' or 'off'")
    k = (4 if size <= OVERSAMPLE_4_MAX_SIZE else 2) if oversample is None else oversample
    if k not in (1, 2, 3, 4):
        raise InputError("oversample", oversample, "1, 2, 3 or 4 (or None for automatic)")
    if spp is not None and not (isinstance(spp, (int, np.integer)) and 1 <= spp <= 1 << 16):
        raise InputError("spp", spp, "an integer in [1, 65536] (samples per HR pixel), or None for --target-noise")
    if target_noise is not None and not (math.isfinite(target_noise) and target_noise > 0):
        raise InputError("target_noise", target_noise, "a positive number (RMS std on [0, 1] full scale)")
    if extinction_ratio is not None and not extinction_ratio >= 1.0:
        raise InputError("extinction_ratio", extinction_ratio, "a number >= 1, or None for ideal polarizers")
    choices: list[dict] = []
    say = _Progress(progress)
    mc_seed = seed if render_seed is None else int(render_seed)

    # 1. variant ---------------------------------------------------------------------------
    t0 = time.perf_counter()
    choice = select_variant(variant, spectral=info.spectral, polarized=info.polarizing)
    import mitsuba as mi

    from capssim.render.scene_base import register_plugins

    register_plugins()
    response = CameraResponse(camera).calibrate()
    pose = sc.camera_pose(params)
    geo_rng, caps_rng, dofp_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    array = build_array(origin=pose.origin, target=pose.target, up=pose.up, fov_deg=pose.fov_deg, size=size,
                        geometry=geometry, rng=geo_rng, plane_point=pose.plane_point, plane_normal=pose.plane_normal)
    mscene = mi.load_dict(sc.mitsuba_dict(params))
    timer.add("load_s", time.perf_counter() - t0)

    # 2. depth and parallax ---------------------------------------------------------------------
    t0 = time.perf_counter()
    points, valid = trace_hits(mscene, array.cameras[0])
    depth = parallax_residual(array, points, valid)
    timer.add("depth_pass_s", time.perf_counter() - t0)

    if planar == "auto":
        use_warp = info.planar and depth["max_hr_px"] <= PLANAR_PARALLAX_TOL_PX
        if info.planar and not use_warp:
            log.warning("scene %s is declared planar but its parallax residual is %.3g HR px; rendering each "
                        "aperture", info.name, depth["max_hr_px"])
    else:
        use_warp = planar == "on"
    path = "planar-warp" if use_warp else "per-aperture"
    margin = _warp_margin(array.homographies, size, psf_radius) if use_warp else psf_radius
    if use_warp:
        main_camera = array.cameras[0].expanded(margin).supersampled(k)
        fine = k
    else:
        main_camera = array.cameras[0].expanded(margin)
        fine = 1
    crop = slice(margin, margin + size)

    def gt_estimate(view: ViewRender) -> np.ndarray:
        """12-channel HR estimate (before the PSF, cropped) of a main-view render."""
        twelve = _t(stokes_to_twelve(view.mean))
        if fine > 1:
            twelve = IntegrateDecimate(fine, tuple(twelve.shape))(twelve)
        return twelve[:, crop, crop].numpy()

    # 3. spp -------------------------------------------------------------------------------------
    # Pilot pairs at s0 and then 4 s0 samples per render pixel measure the Monte-Carlo RMS error
    # of one render and how fast it falls (sigma ~ spp^-alpha; alpha 0.5 for independent samples,
    # more when the stratification works). Rendering stops as soon as the pooled ground truth
    # (inverse-variance weights) reaches the target; otherwise one main render makes up the rest.
    target = target_noise if target_noise is not None else _default_target(sensor)
    pilot_views: list[ViewRender] = []
    pilot_sigmas: list[float] = []
    noise_model = None
    main_spp = 0
    t0 = time.perf_counter()
    if spp is None:
        s0 = _square_at_least(PILOT_SPP_HR / (fine * fine))
        levels = []
        for level, s_l in enumerate((s0, 4 * s0)):
            pair = [render_view(mscene, main_camera, spp=s_l, seed=derive_seed("pilot", mc_seed, level, i),
                                response=response, mode="stokes", group=fine,
                                progress=say(f"pilot {2 * level + i + 1}", main_camera.width * main_camera.height
                                             * s_l)) for i in range(2)]
            sigma = float(np.sqrt(np.mean(np.square(gt_estimate(pair[0]) - gt_estimate(pair[1]))) / 2.0))
            levels.append((s_l, sigma))
            pilot_views += pair
            pilot_sigmas += [sigma, sigma]
            if _pooled_noise(pilot_sigmas) <= target:
                break
        s_last, sig_last = levels[-1]
        alpha = 0.5
        if len(levels) == 2:
            (sa, sig_a), (sb, sig_b) = levels
            alpha = 1.0 if sig_b <= 0 else float(np.clip(math.log(max(sig_a, 1e-30) / sig_b) / math.log(sb / sa),
                                                          0.5, 1.0))
        cap = max(1, math.isqrt(max(1, max_spp // (fine * fine))) ** 2)
        aperture_spp = s_last
        if _pooled_noise(pilot_sigmas) > target:
            # the main render must bring the pooled noise to the target; apertures need the target alone
            rest = 1.0 / target ** 2 - sum(1.0 / sg ** 2 for sg in pilot_sigmas if sg > 0)
            sig_needed = 1.0 / math.sqrt(rest) if rest > 0 else target
            main_spp = _square_at_least(s_last * (sig_last / sig_needed) ** (1.0 / alpha))
            aperture_spp = _square_at_least(max(s_last, s_last * (sig_last / target) ** (1.0 / alpha)))
            if max(main_spp, aperture_spp) > cap:
                log.warning("scene %s: a Monte-Carlo noise of %.2g needs about %d spp per HR pixel; capped at %d "
                            "(max_spp)", info.name, target, max(main_spp, aperture_spp) * fine * fine,
                            cap * fine * fine)
                main_spp, aperture_spp = min(main_spp, cap), min(aperture_spp, cap)
        noise_model = {"pilot_spp_per_hr_pixel": [lv[0] * fine * fine for lv in levels],
                       "pilot_noise_rms": [lv[1] for lv in levels], "convergence_exponent": alpha}
        timer.add("pilot_s", time.perf_counter() - t0)
    else:
        main_spp = aperture_spp = _square_at_least(spp / (fine * fine))
        if main_spp * fine * fine != spp:
            log.info("spp %d rounded up to %d per HR pixel (%d per %dx finer render pixel, a perfect square for "
                     "the stratified sampler)", spp, main_spp * fine * fine, main_spp, fine)

    # 4. render ----------------------------------------------------------------------------------
    t0 = time.perf_counter()
    views, sigmas = list(pilot_views), list(pilot_sigmas)
    if main_spp > 0:
        views.append(render_view(mscene, main_camera, spp=main_spp, seed=derive_seed("main", mc_seed),
                                 response=response, mode="stokes", group=fine,
                                 progress=say("reference view", main_camera.width * main_camera.height * main_spp)))
        if noise_model is not None:
            s_l = noise_model["pilot_spp_per_hr_pixel"][-1] / (fine * fine)
            sigmas.append(noise_model["pilot_noise_rms"][-1] * (s_l / main_spp) ** noise_model["convergence_exponent"])
            noise_model["main_noise_rms_predicted"] = sigmas[-1]
    timer.add("render_reference_s", time.perf_counter() - t0)
    main = views[0] if len(views) == 1 else combine_weighted(views, sigmas)
    achieved = None if noise_model is None else _pooled_noise(sigmas)
    spp_hr = main.spp * fine * fine  # reference view, pilots included

    aperture_views: dict[int, ViewRender] = {}
    if not use_warp:
        for n in range(1, N_APERTURES):
            t1 = time.perf_counter()
            cam = array.cameras[n].expanded(margin)
            aperture_views[n] = render_view(mscene, cam, spp=aperture_spp, seed=derive_seed("aperture", mc_seed, n),
                                            response=response, mode="analyzer", analyzer_deg=POLARIZER_ANGLES_DEG[n],
                                            extinction_ratio=extinction_ratio,
                                            progress=say(f"aperture {n} ({POLARIZER_ANGLES_DEG[n]} deg)",
                                                         cam.width * cam.height * aperture_spp))
            timer.add(f"render_aperture_{n}_s", time.perf_counter() - t1)

    # 5. camera model (shared operators) --------------------------------------------------------
    t0 = time.perf_counter()
    with torch.no_grad():
        twelve = _t(stokes_to_twelve(main.mean))  # (12, Hm, Wm) on the render grid
        if use_warp:
            hr_margin = IntegrateDecimate(fine, tuple(twelve.shape))(twelve)
            gt = _blur_crop(hr_margin, kernel, margin)
            analyzed = Analyzer(twelve.shape[1], twelve.shape[2], extinction_ratio=extinction_ratio)(twelve)
            out_side = fine * (size + 2 * psf_radius)
            s_k = scale_matrix(fine)
            apertures = []
            for n in range(N_APERTURES):
                g = s_k @ shift_matrix(psf_radius, psf_radius) @ array.homographies[n] @ shift_matrix(
                    -margin, -margin) @ np.linalg.inv(s_k)
                warped = Warp(g[None], 3, tuple(twelve.shape[1:]), (out_side, out_side))(analyzed[n:n + 1])[0]
                hr = IntegrateDecimate(fine, tuple(warped.shape))(warped)
                apertures.append(_blur_crop(hr, kernel, psf_radius))
            aperture_hr = torch.stack(apertures)
        else:
            gt = _blur_crop(twelve, kernel, margin)
            ref = Analyzer(size, size, angles_deg=(POLARIZER_ANGLES_DEG[0],), extinction_ratio=extinction_ratio)(gt)[0]
            apertures = [ref]
            for n in range(1, N_APERTURES):
                apertures.append(_blur_crop(_t(aperture_views[n].mean), kernel, margin))
            aperture_hr = torch.stack(apertures)
        caps_irr = BayerMosaic((N_APERTURES, 3, size // 2, size // 2))(
            IntegrateDecimate(2, tuple(aperture_hr.shape))(aperture_hr))
        dofp_irr = dofp_raw_operator((size, size), np.ones((1, 1)), layout=dofp_layout,
                                     extinction_ratio=extinction_ratio)(gt)
    # irradiance cannot be negative: clip float rounding (about -1e-8) before the sensor
    gt_np = np.clip(gt.numpy(), 0.0, None).astype(np.float32)
    timer.add("camera_model_s", time.perf_counter() - t0)
    t0 = time.perf_counter()
    caps_raw = sensor.capture(np.clip(caps_irr.numpy(), 0.0, None), caps_rng)
    dofp_raw = sensor.capture(np.clip(dofp_irr.numpy(), 0.0, None), dofp_rng)
    timer.add("sensor_s", time.perf_counter() - t0)

    # 6. choices and what they saved ----------------------------------------------------------------
    main_s = timer.record["render_reference_s"] + timer.record.get("pilot_s", 0.0)  # the whole reference view
    aperture_s = [timer.record.get(f"render_aperture_{n}_s", 0.0) for n in range(1, N_APERTURES)]
    rendered_s = main_s + sum(aperture_s)
    chosen_kind = choice.variant.split("_ad_")[-1] if "_ad_" in choice.variant else None
    full = variant_name(choice.backend, spectral=True, polarized=True)
    variant_choice = {"choice": "variant", "value": choice.variant, "instead_of": full,
                      "reason": f"scene needs {'spectral' if info.spectral else 'no spectral'} and "
                                f"{'polarized' if info.polarizing else 'no polarized'} light transport"
                                + (f"; {choice.fallback_reason}" if choice.fallback_reason else "")}
    if chosen_kind and choice.variant != full:
        ratio = VARIANT_RELATIVE_COST["spectral_polarized"] / VARIANT_RELATIVE_COST[chosen_kind]
        variant_choice.update(saved_s=rendered_s * (ratio - 1.0),
                              saved_how=f"estimated: render time x {ratio:.2f} (measured relative variant cost) - 1")
    else:
        variant_choice.update(saved_s=0.0, saved_how="none (the full variant)")
    choices.append(variant_choice)
    if use_warp:
        choices.append({"choice": "planar-warp",
                        "value": f"reference rendered once at {fine}x with a {margin} px margin; apertures are its "
                                 "plane-homography warps",
                        "instead_of": "three more aperture renders",
                        "reason": f"scene is planar; parallax residual {depth['max_hr_px']:.2g} HR px",
                        "saved_s": 3.0 * main_s, "saved_how": "estimated: 3 x the reference render (same samples "
                                                             "per HR pixel)"})
    else:
        choices.append({"choice": "per-aperture",
                        "value": "apertures 1-3 rendered from their own positions; aperture 0 is the ground-truth "
                                 "render",
                        "instead_of": "four aperture renders besides the ground truth",
                        "reason": ("scene is not planar" if not info.planar else "planar warp disabled")
                                  + f"; parallax residual up to {depth['max_hr_px']:.3g} HR px",
                        "saved_s": float(np.mean(aperture_s)), "saved_how": "estimated: one aperture render"})
        choices.append({"choice": "own-polarizer-only",
                        "value": "each aperture keeps only what its own analyzer transmits (3 of 12 channels)",
                        "instead_of": "four polarizer-plate renders per aperture",
                        "reason": "an aperture only sees through its own polarizer",
                        "saved_s": 3.0 * float(sum(aperture_s)), "saved_how": "estimated: 3 x the aperture renders"})
    main_spp_hr = spp_hr if use_warp else aperture_spp
    if spp is None:
        choices.append({"choice": "spp-from-target-noise", "value": main_spp_hr,
                        "instead_of": f"a fixed {FIXED_SPP_REFERENCE} spp",
                        "reason": f"pilot noise {[round(v, 5) for v in noise_model['pilot_noise_rms']]} at "
                                  f"{noise_model['pilot_spp_per_hr_pixel']} spp per HR pixel (exponent "
                                  f"{noise_model['convergence_exponent']:.2f}), target {target:.3g}; ground truth "
                                  f"{spp_hr} spp in all" + ("" if use_warp else f", apertures {aperture_spp} spp"),
                        "saved_s": rendered_s * (FIXED_SPP_REFERENCE / main_spp_hr - 1.0),
                        "saved_how": "estimated: render time scaled by spp (negative: the target needed more)"})
    else:
        choices.append({"choice": "spp", "value": main_spp_hr, "instead_of": None, "reason": "given (spp)",
                        "saved_s": 0.0, "saved_how": "none"})

    measured = None
    if measure_savings:
        measured = _measure_savings(sc, params, choice, array, main_camera, max(main_spp, aperture_spp), fine,
                                    margin, use_warp, seed, response_name=camera)
        for c in choices:
            if c["choice"] in measured:
                c["saved_s"], c["saved_how"] = measured[c["choice"]], "measured (compile time excluded)"
            if c["choice"] == "variant" and "variant_cost_ratio" in measured:
                c["measured_cost_ratio"] = measured["variant_cost_ratio"]
        select_variant(choice.variant, spectral=info.spectral, polarized=info.polarizing)

    timer.add("total_s", time.perf_counter() - t_start)
    timing = dict(timer.record)

    # 7. meta ------------------------------------------------------------------------------------
    render_meta = {
        "renderer": "mitsuba3 + capssim camera-RGB Stokes integrator (capssim.render.integrator)",
        "render_seed": mc_seed,
        "variant": choice.to_meta(),
        "path": path,
        "oversample": fine,
        "margin_hr_px": margin,
        "spp_per_hr_pixel": spp_hr,
        "spp_per_render_pixel": main.spp,
        "spp_apertures_per_hr_pixel": None if use_warp else aperture_spp,
        "target_noise": None if spp is not None else target,
        "noise_model": noise_model,
        "mc_noise_rms_estimate": achieved,
        "nonfinite_samples": int(sum(v.nonfinite_samples for v in [*views, *aperture_views.values()])),
        "camera_response": response.to_meta(),
        "optics_psf": psf_spec,
        "pixel_filter": "box (exact pixel-area integration)",
        "extinction_ratio": extinction_ratio,
        "array": array.to_meta(),
        "depth": {"reference_depth_m": array.reference_depth_m, "depth_min_m": depth.get("depth_min_m"),
                  "depth_max_m": depth.get("depth_max_m"), "hit_fraction": depth["valid_fraction"],
                  "parallax_residual_max_hr_px": depth["max_hr_px"],
                  "parallax_residual_p95_hr_px": depth["p95_hr_px"],
                  "parallax_residual_per_aperture": depth["apertures"],
                  "note": "true projection of each reference-pixel surface point minus the stored homography"},
        "choices": choices if record_timing else [{k: v for k, v in c.items() if k not in ("saved_s",)}
                                                  for c in choices],
    }
    if record_timing:
        render_meta["timing_s"] = timing
    scene_meta = {"name": info.name, "description": info.description, "purpose": info.purpose,
                  "params": params, "planar": info.planar, "polarizing": info.polarizing, "spectral": info.spectral,
                  "truth_description": info.truth}
    scene_meta.update(sc.truth(params, array.cameras[0]))
    meta = build_meta(kind="rendered", hr_shape=(size, size), aperture_homographies=array.homographies,
                      psf={"type": "none", "note": "the optical PSF is already in gt.tiff and in the raw frames; "
                                                   "see render.optics_psf"},
                      sensor=sensor, dofp_layout_spec=dofp_layout, extinction_ratio=extinction_ratio, seed=seed,
                      source={"scene": info.name, "renderer": "mitsuba"},
                      extra={"render": render_meta, "scene": scene_meta})
    capture = Capture(meta=meta, caps_raw=caps_raw, dofp_raw=dofp_raw, gt=gt_np)
    capture.render_timing = {"timing_s": timing, "choices": choices}
    log.info("rendered %s (%s, %s, %d spp/HR px) in %.1f s", info.name, choice.variant, path, spp_hr,
             timing["total_s"])
    return capture


def _timed_render(mscene, camera, *, spp, seed, response, **kwargs) -> float:
    """Seconds to render ``camera`` at ``spp``, not counting the kernel compile (done on a 4x4 crop first)."""
    from dataclasses import replace

    render_view(mscene, replace(camera, width=4, height=4), spp=spp, seed=seed, response=response, **kwargs)
    t0 = time.perf_counter()
    render_view(mscene, camera, spp=spp, seed=seed, response=response, **kwargs)
    return time.perf_counter() - t0


def _measure_savings(sc, params, choice, array, main_camera, main_spp, fine, margin, use_warp, seed, *,
                     response_name) -> dict:
    """Render what each choice avoided and time it (``measure_savings=True``); seconds saved per choice.

    Compile time is excluded from both sides of every comparison (:func:`_timed_render`).
    """
    import mitsuba as mi

    from capssim.render.scene_base import register_plugins

    out = {}
    response = CameraResponse(response_name).calibrate()
    mscene = mi.load_dict(sc.mitsuba_dict(params))
    chosen_main = _timed_render(mscene, main_camera, spp=main_spp, seed=derive_seed("measure-main", seed),
                                response=response)
    n_views = 1 if use_warp else 4
    if use_warp:
        # the alternative: three apertures rendered for real at the same samples per HR pixel
        cam = array.cameras[1].expanded(_warp_margin(array.homographies, array.cameras[0].width, 0))
        spp_ap = _square_at_least(main_spp * fine * fine)
        out["planar-warp"] = 3.0 * _timed_render(mscene, cam, spp=spp_ap, seed=derive_seed("measure-ap", seed),
                                                 response=response, mode="analyzer", analyzer_deg=45.0)
    fixed = _square_at_least(FIXED_SPP_REFERENCE / (fine * fine))
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
