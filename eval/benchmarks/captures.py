"""The captures of a benchmark suite: built once per (scene, noise, seed) and cached by content hash.

A suite scene's ``source`` says where its ground truth comes from: ``render`` (a noise-free
:func:`capssim.render.render_capture`, cached under ``CACHE/renders/<sha256>``; the sensor noise
is applied afterwards by :func:`apply_sensor`, so each noise level reuses one render),
``synthetic`` (:mod:`capssim.eval.synthetic`), ``shared-gt`` (a ground truth under
``../shared/data``) or ``gt`` (any ground-truth folder or 12-channel TIFF); the last three are
simulated by :func:`capssim.simulate.simulate_capture`. Captures are cached under
``CACHE/captures/<sha256>``; the hash covers the scene spec, the source data's bytes, the noise,
the seed and a fingerprint of capssim's capture code. All noise is drawn from the random streams
of :func:`capssim.operators.measurement.seed_streams` (paper section 5.2).

Renders are also kept in one store shared by every suite and output folder (:func:`shared_render_dir`:
``$CAPSSIM_RENDER_CACHE``, else ``$XDG_CACHE_HOME/capssim/renders`` or ``~/.cache/capssim/renders``;
``CAPSSIM_RENDER_CACHE=off`` turns it off), under the same content hash: a scene that one suite rendered
is not rendered again by another.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from capssim.camera.camera_setup import CameraSetup, sensor_from_mapping
from capssim.camera.psf import PSF
from capssim.camera.rig import RigModel
from capssim.captures.capture import Capture, read_capture, read_meta, write_capture
from capssim.errors import CapssimError, InputError
from capssim.files.imageio import atomic_write_json, read_gt_scene
from capssim.operators.measurement import CameraArrayMeasurement
from capssim.render import list_scenes, render_capture
from capssim.simulate import prepare_ground_truth, simulate_capture

from ..synthetic import synthetic_scene
from .provenance import REPO_ROOT, code_fingerprint, content_hash, shared_data_dir
from .rigs import (
    CALIBRATION_FILE,
    attach_calibration,
    calibration_for,
    rig_geometry,
)

log = logging.getLogger(__name__)

#: the source files whose change invalidates a cached render
RENDER_CODE = ("capssim/render", "scenes", "capssim/operators", "capssim/simulate.py", "capssim/captures/capture.py")


#: where renders are shared across suites and output folders (a path, or ``off``)
RENDER_CACHE_ENV = "CAPSSIM_RENDER_CACHE"


def shared_render_dir() -> Path | None:
    """The render store shared by every suite (module docstring), or None when ``CAPSSIM_RENDER_CACHE=off``."""
    value = os.environ.get(RENDER_CACHE_ENV, "").strip()
    if value.lower() == "off":
        return None
    if value:
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(base) if base else Path.home() / ".cache") / "capssim" / "renders"


def _share_render(source: Path, shared: Path | None) -> None:
    """Copy a written render folder into the shared store, whole or not at all (a temporary folder renamed
    into place; a store that cannot be written, or a copy another process placed first, is left alone)."""
    if shared is None or (shared / source.name / "meta.json").is_file():
        return
    tmp = None
    try:
        shared.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{source.name}-", dir=shared))
        shutil.copytree(source, tmp, dirs_exist_ok=True)
        os.replace(tmp, shared / source.name)
        tmp = None
    except OSError as exc:
        log.info("render %s not shared in %s (%s)", source.name, shared, exc)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


class Unavailable(Exception):
    """A scene's data or renderer is missing: the case is skipped, not failed."""


def suite_noise(entry) -> dict:
    """A suite's ``noise`` entry, checked: ``{name, noise: none|gaussian|poisson-gaussian, sigma, preset, ...}``
    (the sensor keys of :class:`capssim.camera.camera_setup.CameraSetup`; ``model``, the old spelling of
    ``noise``, is read as it)."""
    if not isinstance(entry, dict) or "name" not in entry or not ("noise" in entry or "model" in entry):
        raise InputError("suite noise", repr(entry)[:80], "{name, noise: none|gaussian|poisson-gaussian, sigma, preset}",
                         "For example {name: gauss-0.01, noise: gaussian, sigma: 0.01}.")
    entry = dict(entry)
    if "noise" not in entry:
        entry = {"name": entry.pop("name"), "noise": entry.pop("model"), **entry}
    _sensor(entry)  # refuses bad values before any capture is made
    return entry


def _sensor(noise: dict):
    """The sensor of a suite's ``noise`` entry (:func:`capssim.camera.camera_setup.sensor_from_mapping`)."""
    return sensor_from_mapping({k: v for k, v in noise.items() if k != "name"}, where=f"suite noise {noise['name']}")


def _setup(scene: dict, noise: dict) -> CameraSetup:
    """The camera set-up of a suite scene under a ``noise`` entry: its sensor, and the scene's
    ``psf_sigma_hr_px`` (default :data:`capssim.camera.psf.DEFAULT_SIGMA_HR_PX`) and ``rig``."""
    sigma = scene.get("psf_sigma_hr_px")
    return CameraSetup(sensor=_sensor(noise), psf=None if sigma is None else PSF.gaussian(float(sigma)),
                       rig=RigModel.from_spec(scene["rig"]) if scene.get("rig") else None)


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _resolve_gt_path(scene: dict) -> Path:
    if scene["source"] == "shared-gt":
        root = shared_data_dir()
        path = root / scene["path"]
        if not path.exists():
            raise Unavailable(f"shared data {path} not found (set CAPSSIM_SHARED_DATA or place ../shared/data "
                              "next to the repository)")
        return path
    path = Path(scene["path"]).expanduser()
    if not path.is_absolute():
        path = REPO_ROOT / path
    if not path.exists():
        raise Unavailable(f"ground truth {path} not found")
    return path


def rendered_scene_names() -> list[str]:
    """The renderer's scene names; :class:`Unavailable` when it cannot list them."""
    try:
        return list(list_scenes())
    except Exception as exc:  # a renderer that cannot even list its scenes is unavailable
        raise Unavailable(f"rendering unavailable: list_scenes failed ({exc})") from None


def apply_sensor(clean: Capture, sensor, seed: int) -> Capture:
    """Noise a noise-free capture with the CAPS and DoFP streams of ``seed`` (as :func:`simulate_capture`)."""
    measurement = CameraArrayMeasurement(sensor, seed=seed)
    meta = copy.deepcopy(clean.meta)
    meta["setup"] = clean.setup.replace(sensor=sensor).to_meta()
    meta["sensor"] = sensor.to_meta()
    meta["seed"] = seed
    meta.setdefault("bench", {})["noise_applied_by"] = ("capssim.eval.benchmarks.captures.apply_sensor "
                                                        "(after a noise-free render)")
    caps = measurement.sense_caps(np.asarray(clean.caps_raw, dtype=np.float64))
    dofp = measurement.sense_dofp(np.asarray(clean.dofp_raw, dtype=np.float64)) if clean.dofp_raw is not None else None
    return Capture(meta=meta, caps_raw=caps, dofp_raw=dofp, gt=clean.gt)


def _rig_options(scene: dict, hr_shape) -> dict:
    """``rig`` and ``aperture_homographies`` of a scene with a ``rig`` entry (:mod:`~capssim.eval.benchmarks.rigs`)."""
    if not scene.get("rig"):
        return {}
    return {"aperture_homographies": rig_geometry(scene["rig"], hr_shape).aperture_homographies}


@dataclass
class CaptureEntry:
    key: str
    path: Path
    scene_name: str
    info: dict


class CaptureFactory:
    """Builds (or finds in the cache) the capture folder of a (scene, noise, seed)."""

    def __init__(self, cache_dir: Path, events: Callable[..., None]):
        self.cache_dir = Path(cache_dir)
        self.events = events
        self.capture_code = code_fingerprint("capssim")
        self._digests: dict[str, str] = {}

    def _scene_identity(self, scene: dict, seed: int) -> dict:
        ident = {k: v for k, v in scene.items() if k not in ("fallback", "description")}
        ident["capture_code"] = self.capture_code
        if scene["source"] in ("shared-gt", "gt"):
            path = _resolve_gt_path(scene)
            if str(path) not in self._digests:
                self._digests[str(path)] = _file_digest(path)
            ident["data_sha"] = self._digests[str(path)]
        ident["seed"] = seed
        return ident

    def get(self, scene: dict, noise: dict, seed: int) -> CaptureEntry:
        ident = self._scene_identity(scene, seed)
        key = content_hash({"scene": ident, "noise": noise})[:20]
        path = self.cache_dir / "captures" / key
        info_path = path / "bench-capture.json"
        if (path / "meta.json").is_file() and info_path.is_file():
            try:
                read_meta(path)
                info = json.loads(info_path.read_text())
                info["cached"] = True
                return CaptureEntry(key, path, scene["name"], info)
            except (CapssimError, json.JSONDecodeError):
                log.warning("cached capture %s is corrupt; rebuilding", path)
        t0 = time.perf_counter()
        capture, info = self._build(scene, noise, seed)
        info["build_time_s"] = time.perf_counter() - t0
        if scene.get("rig"):
            capture.meta["calibration_file"] = CALIBRATION_FILE
        write_capture(path, capture, overwrite=path.exists())
        if scene.get("rig"):
            calibration, info["calibration"] = calibration_for(self.cache_dir, scene["rig"], capture.hr_shape,
                                                               _sensor(noise), noise, seed)
            attach_calibration(path, calibration)
        atomic_write_json(info_path, info)
        info["cached"] = False
        return CaptureEntry(key, path, scene["name"], info)

    def setup(self, scene: dict, noise: dict) -> CameraSetup:
        """The camera set-up of a capture of ``scene`` under ``noise`` (a design map's factory adds its axes)."""
        return _setup(scene, noise)

    def simulate(self, scene: dict, gt, setup: CameraSetup, *, seed: int, source: dict, extra: dict) -> Capture:
        """The capture of a ground truth (:func:`~capssim.simulate.simulate_capture`; a design map's factory sets
        the aperture poses)."""
        return simulate_capture(gt, setup, seed=seed, source=source, extra_meta=extra,
                                **_rig_options(scene, gt.shape[1:]))

    def _build(self, scene: dict, noise: dict, seed: int):
        setup = self.setup(scene, noise)
        src = scene["source"]
        info: dict[str, Any] = {"scene": scene["name"], "source": src, "noise": noise, "seed": seed}
        if src == "render":
            clean, render_info = self._render(scene, seed)
            info.update(render_info)
            return apply_sensor(clean, setup.sensor, seed), info
        if src == "synthetic":
            gt, scene_meta = synthetic_scene(scene.get("generator", "texture"), size=int(scene.get("size", 128)),
                                             seed=int(scene.get("scene_seed", seed)), cycles=int(scene.get("cycles", 36)))
            source = {"type": "synthetic", **{k: v for k, v in scene_meta.items() if k != "star"}}
        else:
            gt, source = read_gt_scene(_resolve_gt_path(scene))
            scene_meta = {}
            gt, crop_info = prepare_ground_truth(gt, crop=scene.get("crop"))
            source.update(crop_info)
        extra = {"scene": {"name": scene["name"], **scene_meta}}
        return self.simulate(scene, gt, setup, seed=seed, source=source, extra=extra), info

    def _render(self, scene: dict, seed: int):
        """Noise-free render, cached by content hash (scene spec, seed, render code)."""
        name = scene.get("scene", scene["name"])
        known = rendered_scene_names()
        if known and name not in known:
            raise Unavailable(f"scene {name!r} is not one of the renderer's scenes ({', '.join(map(str, known))})")
        params = {"scene": name, "size": int(scene.get("size", 256)), "spp": scene.get("spp"), "seed": seed,
                  "variant": scene.get("variant", "auto"), "scene_params": scene.get("scene_params")}
        if scene.get("geometry_params"):  # the array's geometry (render --geometry), e.g. a map's baseline_m
            params["geometry_params"] = scene["geometry_params"]
        if scene.get("rig"):
            params["rig"] = scene["rig"]
        key = content_hash({"render": params, "code": code_fingerprint(*RENDER_CODE)})[:20]
        path = self.cache_dir / "renders" / key
        shared = shared_render_dir()
        for where in [path] + ([] if shared is None else [shared / key]):
            if (where / "meta.json").is_file():
                try:
                    clean = read_capture(where, require_gt=True)
                    return clean, {"render": params, "render_cached": True, "render_variant": _variant_of(clean)}
                except CapssimError:
                    log.warning("cached render %s is corrupt; re-rendering", where)
        self.events("note", message=f"rendering {name} at {params['size']} px (cached afterwards)")
        t0 = time.perf_counter()
        extra = {k: scene[k] for k in ("scene_params", "geometry_params") if scene.get(k)}
        extra.update(_rig_options(scene, (params["size"], params["size"])))
        setup = _setup(scene, {"name": "clean", "noise": "none"})
        try:
            clean = render_capture(name, size=params["size"], spp=params["spp"], seed=seed, setup=setup,
                                   variant=params["variant"], record_timing=True, **extra)
        except ImportError as exc:
            raise Unavailable(f"rendering unavailable ({exc})") from None
        elapsed = time.perf_counter() - t0
        if clean.gt is None:
            raise CapssimError(f"render of {name!r} returned no ground truth")
        write_capture(path, clean, overwrite=path.exists())
        _share_render(path, shared)
        return clean, {"render": params, "render_cached": False, "render_time_s": elapsed,
                       "render_variant": _variant_of(clean)}


def expand_render_scenes(scenes: list[dict], emit: Callable[..., None]) -> list[dict]:
    """Replace a ``{source: render, scene: "*"}`` entry by one entry per scene the renderer lists."""
    out = []
    for sc in scenes:
        if sc["source"] != "render" or sc.get("scene") != "*":
            out.append(sc)
            continue
        try:
            names = rendered_scene_names()
        except Unavailable as exc:
            emit("note", message=f"{sc['name']}: {exc}")
            names = []
        if not names:
            out.append(dict(sc, scene="(all rendered scenes)"))
            continue
        prefix = sc.get("prefix", "")
        for name in names:
            out.append(dict(sc, name=f"{prefix}{name}", scene=name))
    return out


def _variant_of(capture) -> str | None:
    """The Mitsuba variant a render used (recorded by capssim.render in meta["render"])."""
    variant = (capture.meta.get("render") or {}).get("variant")
    return variant.get("variant") if isinstance(variant, dict) else variant
