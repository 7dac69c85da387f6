"""One cell of a design map: its capture (built once per cell and seed, cached) and its cases.

A cell is a suite scene entry with the cell's conditions (:func:`cell_scene`); the suites' case runner
(:mod:`capssim.eval.benchmarks.runner`) runs it as one (scene, seed) group with the tasks below:

* :class:`MapCaptureFactory` builds the capture as a suite does (:class:`~capssim.eval.benchmarks.captures.CaptureFactory`:
  cached by content hash under ``CACHE/captures``, renders shared), with the cell's sensor, PSF, extinction ratio
  and aperture poses (``shift_max``/``rotation_max``/``scale_max``: random poses of that range, drawn from the
  seed's pose stream as ``capssim simulate`` does; ``offset_px``: the regular pattern of
  :func:`~.theory.regular_offsets`), and a rendered scene's ``depth_m`` (its ``scene_params``) and the array's
  ``baseline_m`` (its ``geometry_params``, as ``capssim render --geometry baseline_m=...``). It records
  the theory of the cell's poses (:func:`~.theory.sampling_conditioning`) and, with a ``registration_error_px``
  axis, the error the project's registration reaches on the capture (median over the 16 sub-images, HR px), and
  with a ``depth_m`` or ``baseline_m`` axis the render's parallax that no homography registers
  (``parallax_p95_hr_px``: the 95th percentile over the view, worst aperture, HR px);
* :func:`map_task` runs one method on it (:func:`~capssim.eval.benchmarks.cases.method_task`: reconstruct, score
  with the suites' metrics), after :func:`perturbed_warps` when the cell has a ``registration_error_px``: a
  camera-array method then runs with the true warps, apertures 1-3 each shifted by that many HR px in a direction
  drawn from the seed (``numpy.random.default_rng([seed, 56])``), so that registration is separated from the rest.
"""

from __future__ import annotations

import functools

import numpy as np

from capssim.captures.capture import Capture
from capssim.conventions import N_APERTURES
from capssim.reconstruct.registry import available_methods
from capssim.simulate import PoseRanges, simulate_capture

from ..benchmarks.captures import CaptureFactory
from ..benchmarks.cases import capture_task, method_task
from ..benchmarks.registration import run_registration_bench
from .spec import POSE_AXES, cell_noise, depth_params
from .theory import local_poses, regular_offsets, sampling_conditioning

#: the second word of the seed of the registration error's directions
PERTURB_STREAM = 56


def cell_label(axes: dict) -> str:
    """``name=value,...`` of a cell's axis values, e.g. ``shift_max=0.25,sigma=0.01``."""
    return ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in axes.items())


def cell_scene(scene: dict, cell: dict) -> dict:
    """The suite scene entry of a cell: ``scene`` named by the cell, its PSF (``psf_sigma_hr_px``), a render's
    ``depth_m`` (``scene_params``) and ``baseline_m`` (``geometry_params``) set, and ``map`` holding every condition (part of the capture's cache key)."""
    values = {**cell["fixed"], **cell["axes"]}
    out = dict(scene, name=cell_label(cell["axes"]))
    out.pop("fallback", None)
    if "psf_sigma_hr_px" in values:
        out["psf_sigma_hr_px"] = values["psf_sigma_hr_px"]
    if "depth_m" in values:
        out["scene_params"] = {**(scene.get("scene_params") or {}), **depth_params(scene["scene"], values["depth_m"])}
    if "baseline_m" in values:
        out["geometry_params"] = dict(scene.get("geometry_params") or {}, baseline_m=values["baseline_m"])
    out["map"] = {"axes": dict(cell["axes"]), "fixed": dict(cell["fixed"]), "noise": cell_noise(values)}
    return out


@functools.lru_cache(maxsize=256)
def _conditioning(poses: tuple, kernel_key: bytes, kernel_shape: tuple) -> dict:
    kernel = np.frombuffer(kernel_key, dtype=np.float64).reshape(kernel_shape)
    return sampling_conditioning(list(poses), kernel)


def pose_theory(capture: Capture) -> dict:
    """The conditioning of the stacked sampling at a capture's poses (:func:`~.theory.sampling_conditioning`;
    the poses rounded to 1e-9 HR px and cached, so co-posed cells are computed once per process)."""
    poses = tuple(tuple(round(v, 9) for v in p) for p in local_poses(capture.aperture_homographies(), capture.hr_shape))
    psf = capture.setup.psf if capture.meta.get("kind") == "rendered" else capture.psf
    kernel = np.ascontiguousarray(psf.kernel(), dtype=np.float64)
    return _conditioning(poses, kernel.tobytes(), kernel.shape)


class MapCaptureFactory(CaptureFactory):
    """The suites' capture factory with a design map cell's conditions (module docstring)."""

    def get(self, scene: dict, noise: dict, seed: int):
        """The cell's capture: ``noise`` (the runner's placeholder) is replaced by the cell's own."""
        return super().get(scene, scene["map"]["noise"], seed)

    def setup(self, scene: dict, noise: dict):
        setup = super().setup(scene, noise)
        values = {**scene["map"]["fixed"], **scene["map"]["axes"]}
        if "extinction_ratio" in values:
            setup = setup.replace(extinction_ratio=float(values["extinction_ratio"]))
        return setup

    def simulate(self, scene: dict, gt, setup, *, seed: int, source: dict, extra: dict) -> Capture:
        values = {**scene["map"]["fixed"], **scene["map"]["axes"]}
        ranges = PoseRanges(shift_max_px=float(values.get("shift_max", 2.0)),
                            rotation_max_deg=float(values.get("rotation_max", 0.5)),
                            scale_max=float(values.get("scale_max", 0.005)))
        homographies = None
        if "offset_px" in values:
            homographies = regular_offsets(values["offset_px"])
        elif scene.get("rig"):  # a rig's geometry, as in a suite
            return super().simulate(scene, gt, setup, seed=seed, source=source, extra=extra)
        return simulate_capture(gt, setup, seed=seed, source=source, extra_meta=extra, pose_ranges=ranges,
                                aperture_homographies=homographies)

    def _build(self, scene: dict, noise: dict, seed: int):
        capture, info = super()._build(scene, noise, seed)
        info["map"] = {"axes": scene["map"]["axes"], "fixed": scene["map"]["fixed"]}
        names = {*scene["map"]["axes"], *scene["map"]["fixed"]}
        if names & set(POSE_AXES) or not names & {"registration_error_px", "depth_m", "baseline_m"}:
            info["theory"] = pose_theory(capture)
        depth = (capture.meta.get("render") or {}).get("depth") or {}
        if names & {"depth_m", "baseline_m"} and "parallax_residual_p95_hr_px" in depth:
            info["parallax_p95_hr_px"] = depth["parallax_residual_p95_hr_px"]
        if "registration_error_px" in names:
            row = run_registration_bench([capture])["rows"][0]
            info["registration_reached_hr_px"] = row["median_hr_px"]
        return capture, info


#: the capture task of a map (the suites' :func:`~capssim.eval.benchmarks.cases.capture_task`, this factory)
map_capture_task = functools.partial(capture_task, factory_class=MapCaptureFactory)


def perturbed_warps(capture: Capture, error_px: float, seed: int) -> Capture:
    """``capture`` with apertures 1-3's stored warps shifted by ``error_px`` HR px each, in directions drawn
    from ``default_rng([seed, 56])`` (aperture 0, the reference grid, is kept); the frames are unchanged."""
    rng = np.random.default_rng([int(seed), PERTURB_STREAM])
    angles = rng.uniform(0.0, 2.0 * np.pi, size=N_APERTURES - 1)
    homographies = capture.aperture_homographies()
    for n, angle in enumerate(angles, start=1):
        shift = np.eye(3)
        shift[:2, 2] = float(error_px) * np.cos(angle), float(error_px) * np.sin(angle)
        homographies[n] = shift @ homographies[n]
    return capture.with_aperture_homographies(homographies)


def prepare_cell(capture: Capture, method: dict, capture_info: dict):
    """``method_task``'s ``prepare``: with a ``registration_error_px``, a camera-array method runs on the true
    warps perturbed (:func:`perturbed_warps`); anything else runs as in a suite."""
    values = {**capture_info["map"]["fixed"], **capture_info["map"]["axes"]}
    error = values.get("registration_error_px")
    if error is None or available_methods()[method["name"]].input_kind != "caps":
        return capture, method
    return perturbed_warps(capture, float(error), int(capture_info["seed"])), dict(method, true_warps=True)


def map_task(rec: dict, method: dict, capture_path: str, capture_key: str, capture_info: dict, *, device: str,
             convention: str) -> dict:
    """One case of a map: :func:`~capssim.eval.benchmarks.cases.method_task` with :func:`prepare_cell`; the
    record carries the cell's ``axes``, ``fixed`` conditions, the method's ``kind`` (``array`` or ``dofp``)
    and the cell's ``theory`` (and ``registration_reached_hr_px``, ``parallax_p95_hr_px`` when measured)."""
    spec = available_methods().get(method["name"])
    rec = dict(rec, axes=capture_info["map"]["axes"], fixed=capture_info["map"]["fixed"],
               kind=None if spec is None else ("array" if spec.input_kind == "caps" else "dofp"))
    for key in ("theory", "registration_reached_hr_px", "parallax_p95_hr_px"):
        if key in capture_info:
            rec[key] = capture_info[key]
    return method_task(rec, method, capture_path, capture_key, capture_info, device=device, convention=convention,
                       prepare=prepare_cell)


__all__ = ["MapCaptureFactory", "cell_label", "cell_scene", "map_capture_task", "map_task",
           "perturbed_warps", "pose_theory", "prepare_cell"]
