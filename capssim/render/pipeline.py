"""``render_capture``: a library scene seen through the four apertures -> a capture folder's contents.

Pipeline (each choice is recorded in ``meta.json["render"]["choices"]`` with the time it saved,
:mod:`capssim.render.choices`):

1. **Variant** (:mod:`capssim.render.variants`): the cheapest variant the scene needs
   (mono / spectral, polarized or not) on the fastest working backend (cuda -> llvm -> scalar).
2. **Array** (:mod:`capssim.render.pinhole_array`): four apertures with baseline, tilt, roll and
   focal-scale errors, drawn from the pose stream of
   :class:`~capssim.operators.measurement.CameraArrayMeasurement`; the stored homographies are the exact
   plane-induced ones for the scene's reference plane. A one-ray-per-pixel depth pass measures
   the parallax that the homographies miss (``render.depth``).
3. **Planar scenes are rendered once**: when everything visible lies on the reference plane
   (scene flag ``planar`` *and* measured parallax residual below ``PLANAR_PARALLAX_TOL_PX``),
   the reference view is rendered once, finer than the ground truth and with a margin, and
   each aperture's view is its exact plane homography (:mod:`capssim.render.camera_model`).
   Otherwise apertures 1-3 are rendered from their own positions, each only through its own
   polarizer angle; aperture 0's view is the ground-truth render itself.
4. **spp from a target noise** (:mod:`capssim.render.sample_budget`): pilot renders measure the
   Monte-Carlo noise and its convergence rate; the main spp is the smallest square that
   reaches the target, and the pilots are pooled into the ground truth.
5. **One observation model** (paper eq. 9): everything after the renderer uses the shared
   operators, then the sensor of the measurement (CAPS and DoFP noise streams), exactly as
   ``simulate`` does.

Because the optical PSF is already in ``gt.tiff``, ``meta.json["psf"]`` is ``none``: applying
the stored homographies, 2x2 pixel integration and RGGB sampling to ``gt.tiff`` reproduces
the noiseless raw frames up to parallax, Monte-Carlo noise and warp interpolation (the
optics PSF is in ``meta.json["render"]["optics_psf"]``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from capssim.camera.camera_setup import as_setup
from capssim.camera.psf import PSF
from capssim.captures.capture import Capture, build_meta
from capssim.conventions import N_APERTURES, POLARIZER_ANGLES_DEG
from capssim.errors import InputError
from capssim.operators.measurement import CameraArrayMeasurement
from capssim.render.camera_model import aperture_kernels, observe, warp_margin
from capssim.render.choices import RenderPath, apply_measured, choice_records, measure_savings
from capssim.render.integrator import ViewRender, derive_seed, render_view
from capssim.render.mitsuba_plugins import register_plugins
from capssim.render.pinhole_array import ArrayCameras, PinholeCamera, RigTolerances, build_array, parallax_residual
from capssim.render.sample_budget import ReferenceRender, ReferenceView, SamplePlan, plan_samples, render_reference
from capssim.render.scene_base import Scene
from capssim.render.scene_registry import get_scene
from capssim.render.settings import RenderSettings
from capssim.render.spectral import CameraResponse
from capssim.render.variants import VariantChoice, select_variant

log = logging.getLogger(__name__)

#: a scene flagged planar is rendered once and warped when its measured parallax is at most this (HR px)
PLANAR_PARALLAX_TOL_PX = 0.01


@dataclass
class _Timer:
    record: dict = field(default_factory=dict)

    def add(self, key: str, seconds: float) -> None:
        self.record[key] = self.record.get(key, 0.0) + float(seconds)


class _Progress:
    """``progress(stage, done, total)`` as ``say(stage, total) -> advance(n)`` for one render."""

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


@dataclass
class _Loaded:
    """The variant in use, the camera response, the measurement (with its streams), the array and the scene."""

    choice: VariantChoice
    response: CameraResponse
    measurement: CameraArrayMeasurement
    array: ArrayCameras
    mscene: object


def _load(sc: Scene, params: dict, settings: RenderSettings) -> _Loaded:
    """Step 1-2: select the variant, draw the array from the pose stream, load the Mitsuba scene."""
    import mitsuba as mi

    info = sc.info
    choice = select_variant(settings.variant, spectral=info.spectral, polarized=info.polarizing)
    register_plugins()
    response = CameraResponse(settings.camera).calibrate()
    pose = sc.camera_pose(params)
    # the optical PSF is applied to the rendered views (camera_model), so the measurement has none
    measurement = CameraArrayMeasurement.from_setup(settings.setup, settings.seed, psf=PSF.none())
    array = build_array(origin=pose.origin, target=pose.target, up=pose.up, fov_deg=pose.fov_deg, size=settings.size,
                        geometry=RigTolerances.from_params(settings.geometry_params), rng=measurement.pose_rng,
                        plane_point=pose.plane_point, plane_normal=pose.plane_normal)
    mscene = mi.load_dict(sc.mitsuba_dict(params))
    return _Loaded(choice, response, measurement, array, mscene)


def _choose_path(loaded: _Loaded, info, settings: RenderSettings, timer: _Timer) -> tuple[RenderPath, PinholeCamera]:
    """Step 2-3: the depth pass, the planar-warp decision, and the reference render camera."""
    t0 = time.perf_counter()
    points, valid = trace_hits(loaded.mscene, loaded.array.cameras[0])
    depth = parallax_residual(loaded.array, points, valid)
    timer.add("depth_pass_s", time.perf_counter() - t0)
    if settings.planar == "auto":
        use_warp = info.planar and depth["max_hr_px"] <= PLANAR_PARALLAX_TOL_PX
        if info.planar and not use_warp:
            log.warning("scene %s is declared planar but its parallax residual is %.3g HR px; rendering each "
                        "aperture", info.name, depth["max_hr_px"])
    else:
        use_warp = settings.planar == "on"
    if not use_warp and settings.aperture_homographies is not None:
        raise InputError("aperture_homographies", "given for a scene rendered per aperture",
                         "explicit homographies only on the planar warp path", "Use a planar scene or --planar on.")
    psf_radius = max(k.shape[0] // 2 for k in aperture_kernels(settings.setup.psf.kernel(), settings.setup.rig))
    psf_radius = max(psf_radius, settings.setup.psf.kernel().shape[0] // 2)
    margin = warp_margin(_homographies(loaded, settings), settings.size, psf_radius) if use_warp else psf_radius
    camera = loaded.array.cameras[0].expanded(margin)
    fine = settings.oversample if use_warp else 1
    if use_warp:
        camera = camera.supersampled(fine)
    return RenderPath(use_warp, fine, margin, depth), camera


def _homographies(loaded: _Loaded, settings: RenderSettings) -> np.ndarray:
    """``(4, 3, 3)``: the explicit ``aperture_homographies`` of the settings, else the drawn array's."""
    if settings.aperture_homographies is not None:
        return np.asarray(settings.aperture_homographies, dtype=np.float64)
    return loaded.array.homographies


def _render_apertures(loaded: _Loaded, path: RenderPath, spp: int, settings: RenderSettings, say: _Progress,
                      timer: _Timer) -> dict[int, ViewRender]:
    """Apertures 1-3 rendered from their own positions, each through its own polarizer (per-aperture path)."""
    views: dict[int, ViewRender] = {}
    for n in range(1, N_APERTURES):
        t1 = time.perf_counter()
        cam = loaded.array.cameras[n].expanded(path.margin)
        angle_deg, extinction_ratio = _aperture_polarizer(settings, n)
        views[n] = render_view(loaded.mscene, cam, spp=spp, seed=derive_seed("aperture", settings.render_seed, n),
                               response=loaded.response, mode="analyzer", analyzer_deg=angle_deg,
                               extinction_ratio=extinction_ratio,
                               progress=say(f"aperture {n} ({POLARIZER_ANGLES_DEG[n]} deg)",
                                            cam.width * cam.height * spp))
        timer.add(f"render_aperture_{n}_s", time.perf_counter() - t1)
    return views


def _aperture_polarizer(settings: RenderSettings, n: int) -> tuple[float, object]:
    """Aperture n's polarizer for the renderer: its angle in the camera frame (degrees; nominal plus
    the rig's offset) and extinction ratio (the rig's 3 per colour, else the settings' one value)."""
    rig = settings.setup.rig
    if rig is None or rig.is_ideal:
        return POLARIZER_ANGLES_DEG[n], settings.setup.extinction_ratio
    return POLARIZER_ANGLES_DEG[n] + float(rig.angle_offsets_deg[n]), rig.extinction_ratio[n].tolist()


#: keyword options of render_capture that replace a field of the settings' camera set-up
SETUP_OPTIONS = ("sensor", "psf", "dofp_layout", "extinction_ratio", "rig")


def _with_options(settings: RenderSettings | None, options: dict) -> RenderSettings:
    """``settings`` with the keyword ``options`` of :func:`render_capture`: fields of
    :class:`RenderSettings`, or of its camera set-up (:data:`SETUP_OPTIONS`, given as themselves)."""
    fields = {k: v for k, v in options.items() if k not in SETUP_OPTIONS}
    settings = replace(settings or RenderSettings(), **fields)
    changes = {k: options[k] for k in SETUP_OPTIONS if options.get(k) is not None}
    if not changes:
        return settings
    setup = as_setup(settings.setup)
    setup = setup.replace(sensor=changes.pop("sensor")) if "sensor" in changes else setup
    return replace(settings, setup=as_setup(setup, **changes))


def check_render(scene: str, *, settings: RenderSettings | None = None, **options) -> tuple[dict, RenderSettings]:
    """Check everything :func:`render_capture` would check before any rendering, and render nothing.

    Returns the scene's parameters (defaults updated, coerced to their types) and the checked
    :class:`~capssim.render.settings.RenderSettings`; raises :class:`~capssim.errors.InputError`
    (or :class:`~capssim.errors.UnknownNameError`) naming the first bad option. A dry run
    (``capssim dataset --dry-run``) calls it for every drawn sample.
    """
    settings = _with_options(settings, options)
    params = get_scene(scene).params(settings.scene_params)
    return params, settings.checked()


def render_capture(scene: str, *, settings: RenderSettings | None = None, **options) -> Capture:
    """Render library scene ``scene`` through the CAPS array and the DoFP camera (Mitsuba).

    Parameters
    ----------
    scene : str
        A registered library scene (``capssim scenes`` lists them), e.g. ``siemens-star``.
    settings : RenderSettings, optional
        All options at once (:class:`~capssim.render.settings.RenderSettings`).
    **options
        Its fields (``size``, ``spp``, ``seed``, ``setup``, ...), replacing those of ``settings``, and the camera
        set-up's (:data:`SETUP_OPTIONS`: ``sensor``, ``psf``, ``dofp_layout``, ``extinction_ratio``, ``rig``).

    Returns
    -------
    Capture
        Of kind ``rendered`` (not yet written); the wall times are on ``capture.render_timing``.
    """
    t_start = time.perf_counter()
    sc = get_scene(scene)
    info = sc.info
    params, settings = check_render(scene, settings=settings, **options)
    timer, say = _Timer(), _Progress(settings.progress)

    t0 = time.perf_counter()
    loaded = _load(sc, params, settings)
    timer.add("load_s", time.perf_counter() - t0)
    path, main_camera = _choose_path(loaded, info, settings, timer)
    view = ReferenceView(loaded.mscene, main_camera, path.fine, slice(path.margin, path.margin + settings.size),
                         loaded.response, settings.render_seed, say)
    target = settings.target()
    t0 = time.perf_counter()
    plan = plan_samples(view, spp=settings.spp, target=target, max_spp=settings.max_spp, scene_name=info.name)
    if settings.spp is None:
        timer.add("pilot_s", time.perf_counter() - t0)
    t0 = time.perf_counter()
    reference = render_reference(view, plan)
    timer.add("render_reference_s", time.perf_counter() - t0)
    aperture_views = {} if path.use_warp else _render_apertures(loaded, path, plan.aperture_spp, settings, say, timer)

    t0 = time.perf_counter()
    kernel = settings.setup.psf.kernel()
    irradiance = observe(reference.pooled.mean, {n: v.mean for n, v in aperture_views.items()},
                         _homographies(loaded, settings), measurement=loaded.measurement, kernel=kernel,
                         size=settings.size, fine=path.fine, margin=path.margin, use_warp=path.use_warp,
                         rig=settings.setup.rig)
    # irradiance cannot be negative: clip float rounding (about -1e-8) before the sensor
    gt = np.clip(irradiance.gt.numpy(), 0.0, None).astype(np.float32)
    timer.add("camera_model_s", time.perf_counter() - t0)
    t0 = time.perf_counter()
    caps_raw = loaded.measurement.sense_caps(np.clip(irradiance.caps.numpy(), 0.0, None))
    dofp_raw = loaded.measurement.sense_dofp(np.clip(irradiance.dofp.numpy(), 0.0, None))
    timer.add("sensor_s", time.perf_counter() - t0)

    choices = choice_records(loaded.choice, info, path, plan, spp=settings.spp, spp_hr=reference.spp_hr,
                             timing=timer.record)
    if settings.measure_savings:
        apply_measured(choices, measure_savings(sc, params, loaded.choice, loaded.array, main_camera,
                                                max(plan.main_spp, plan.aperture_spp), path, settings.seed,
                                                response_name=settings.camera))
        select_variant(loaded.choice.variant, spectral=info.spectral, polarized=info.polarizing)
    timer.add("total_s", time.perf_counter() - t_start)
    timing = dict(timer.record)
    render_meta = _render_meta(loaded, path, plan, reference, [*reference.views, *aperture_views.values()], settings,
                               choices, timing)
    scene_meta = {"name": info.name, "description": info.description, "purpose": info.purpose,
                  "params": params, "planar": info.planar, "polarizing": info.polarizing, "spectral": info.spectral,
                  "truth_description": info.truth}
    scene_meta.update(sc.truth(params, loaded.array.cameras[0]))
    meta = build_meta(kind="rendered", hr_shape=(settings.size, settings.size),
                      aperture_homographies=_homographies(loaded, settings),
                      psf={"type": "none", "note": "the optical PSF is already in gt.tiff and in the raw frames; "
                                                   "see render.optics_psf"},
                      setup=settings.setup, seed=settings.seed, source={"scene": info.name, "renderer": "mitsuba"},
                      extra={"render": render_meta, "scene": scene_meta})
    capture = Capture(meta=meta, caps_raw=caps_raw, dofp_raw=dofp_raw, gt=gt)
    capture.render_timing = {"timing_s": timing, "choices": choices}
    log.info("rendered %s (%s, %s, %d spp/HR px) in %.1f s", info.name, loaded.choice.variant, path.name,
             reference.spp_hr, timing["total_s"])
    return capture


def _render_meta(loaded: _Loaded, path: RenderPath, plan: SamplePlan, reference: ReferenceRender,
                 views: list[ViewRender], settings: RenderSettings, choices: list[dict], timing: dict) -> dict:
    """``meta.json["render"]``: how the capture was rendered (wall times only with ``record_timing``)."""
    depth, array = path.depth, loaded.array
    render_meta = {
        "renderer": "mitsuba3 + capssim camera-RGB Stokes integrator (capssim.render.integrator)",
        "render_seed": settings.render_seed,
        "variant": loaded.choice.to_meta(),
        "path": path.name,
        "oversample": path.fine,
        "margin_hr_px": path.margin,
        "spp_per_hr_pixel": reference.spp_hr,
        "spp_per_render_pixel": reference.pooled.spp,
        "spp_apertures_per_hr_pixel": None if path.use_warp else plan.aperture_spp,
        "target_noise": None if settings.spp is not None else plan.target,
        "noise_model": plan.noise_model,
        "mc_noise_rms_estimate": reference.noise_rms,
        "nonfinite_samples": int(sum(v.nonfinite_samples for v in views)),
        "camera_response": loaded.response.to_meta(),
        "optics_psf": settings.setup.psf.to_spec(),
        "pixel_filter": "box (exact pixel-area integration)",
        "extinction_ratio": settings.setup.extinction_ratio,
        "array": array.to_meta(),
        "depth": {"reference_depth_m": array.reference_depth_m, "depth_min_m": depth.get("depth_min_m"),
                  "depth_max_m": depth.get("depth_max_m"), "hit_fraction": depth["valid_fraction"],
                  "parallax_residual_max_hr_px": depth["max_hr_px"],
                  "parallax_residual_p95_hr_px": depth["p95_hr_px"],
                  "parallax_residual_per_aperture": depth["apertures"],
                  "note": "true projection of each reference-pixel surface point minus the stored homography"},
        "choices": choices if settings.record_timing else [{k: v for k, v in c.items() if k not in ("saved_s",)}
                                                           for c in choices],
    }
    if settings.record_timing:
        render_meta["timing_s"] = timing
    return render_meta


__all__ = ["PLANAR_PARALLAX_TOL_PX", "RenderSettings", "check_render", "render_capture", "trace_hits"]
