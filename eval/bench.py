"""The benchmark runner: scenes x noise levels x seeds x methods from a suite file.

A suite (``eval/suites/NAME.yaml`` or any YAML path; README "Benchmarks") names:

* ``scenes``: each ``{name, source, ...}`` with ``source`` one of
  ``render`` (``capssim.render.render_capture``: ``scene``, ``size``, ``spp``, ``scene_params``),
  ``shared-gt`` (a ground truth under ``../shared/data``: ``path``, ``crop``),
  ``gt`` (a ground-truth folder or 12-channel TIFF anywhere: ``path``, ``crop``),
  ``synthetic`` (:mod:`eval.synthetic`: ``generator``, ``size``, ``cycles``);
  optionally ``fallback: OTHER_SCENE_NAME`` (a scene of the same file used, and reported,
  when this one's data or renderer is unavailable) and ``psf_sigma`` (HR px, default 0.5);
* ``noise``: ``{name, model: none|gaussian|poisson-gaussian, sigma, preset}``;
* ``seeds``: list of integers (poses, noise and render seeds);
* ``methods``: names, or ``{name, label, options, true_warps, registration}`` for variants
  (``registration``: a :data:`reconstruct.registration.REGISTRATION_MODES` name).

Every case is ``(scene, noise, seed, method)``. Captures are built once per
``(scene, noise, seed)`` and cached under ``CACHE/captures/<sha256>`` (the hash covers the
scene spec, the source data's bytes, noise, seed and a fingerprint of capssim's capture
code); clean renders are cached under ``CACHE/renders/<sha256>`` and the sensor noise is
applied by the bench (same streams as :func:`capssim.simulate.simulate_capture`), so each
noise level reuses one render. ``results.jsonl`` holds one JSON line per case and is
rewritten atomically after every case: an interrupted run resumes where it stopped (cases
already ``ok`` with the same case hash are not redone; the hash covers capture, method,
options, device and fingerprints of the reconstruction and scoring code).

Peak memory is the peak resident set size of the process sampled every 5 ms by a thread
during the method (``peak_rss_mb``, and ``peak_rss_delta_mb`` above the level before it);
on CUDA also ``torch.cuda.max_memory_allocated``.

Regression check (:func:`check_against_baseline`): every quality metric of every case in
both the baseline and this run is compared with its stored value; a higher-is-better
metric fails when it falls more than its tolerance below, a lower-is-better one when it
rises more than its tolerance above (:data:`DEFAULT_TOLERANCES`, stored in the baseline
file and editable there). Timings are never a failure (shared CI machines are too noisy);
they are printed with their ratio to the baseline. Baseline cases skipped for missing data
(``../shared`` absent, renderer unavailable) are listed and not compared; a case that
errors, a method that is no longer registered, or a run that compares nothing fails.
"""

from __future__ import annotations

import copy
import datetime as _dt
import hashlib
import json
import logging
import os
import platform
import subprocess
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from capssim.errors import CapssimError, InputError, UnknownNameError
from capssim.imageio import atomic_write_json, atomic_write_text

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[1]
SUITES_DIR = Path(__file__).resolve().parent / "suites"
SCENE_SOURCES = ("render", "shared-gt", "gt", "synthetic")
BASELINE_SCHEMA = "capssim.bench-baseline"

#: Allowed drop (or rise, for lower-is-better metrics) before a metric counts as a regression.
DEFAULT_TOLERANCES: dict[str, float] = {
    "psnr_db": 0.10,  # every PSNR-type metric, dB
    "ssim": 0.005,  # SSIM, DoLP SSIM
    "aop_deg": 0.25,  # AoP RMSE / MAE, degrees
    "mtf_magnification": 0.05,  # SR magnification (absolute)
    "mtf_limit": 0.0125,  # limit resolution, cycles per sub-image pixel (= 0.05 / 4)
    "lpips": 0.005,
}


def shared_data_dir() -> Path:
    """``$CAPSSIM_SHARED_DATA`` or ``../shared/data`` next to the repository."""
    return Path(os.environ.get("CAPSSIM_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


# -- suites --------------------------------------------------------------------------------------
def available_suites() -> list[str]:
    return sorted(p.stem for p in SUITES_DIR.glob("*.yaml"))


def load_suite(name_or_path: str | Path) -> dict:
    """Read and validate a suite: a name in ``eval/suites`` or a path to a YAML file."""
    import yaml

    path = Path(name_or_path)
    if not (path.suffix in (".yaml", ".yml") and path.is_file()):
        if str(name_or_path) not in available_suites():
            raise UnknownNameError("suite", str(name_or_path), available_suites())
        path = SUITES_DIR / f"{name_or_path}.yaml"
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise InputError("suite", f"invalid YAML in {path} ({exc})", "a suite file (README 'Benchmarks')") from exc
    if not isinstance(spec, dict):
        raise InputError("suite", str(path), "a YAML mapping with scenes, noise, seeds and methods")
    spec = dict(spec)
    spec.setdefault("name", path.stem)
    spec["path"] = str(path)
    spec["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    spec.setdefault("convention", "capssim")
    spec.setdefault("seeds", [0])
    spec.setdefault("noise", [{"name": "clean", "model": "none"}])
    for key in ("scenes", "methods"):
        if not spec.get(key):
            raise InputError("suite", f"{path} without '{key}'", f"a non-empty '{key}' list")
    names = set()
    for sc in spec["scenes"]:
        if not isinstance(sc, dict) or "name" not in sc or sc.get("source") not in SCENE_SOURCES:
            raise InputError("suite scenes", repr(sc)[:120], f"{{name, source}} with source in {SCENE_SOURCES}")
        if sc["name"] in names:
            raise InputError("suite scenes", sc["name"], "unique scene names")
        names.add(sc["name"])
    for sc in spec["scenes"]:
        if sc.get("fallback") and sc["fallback"] not in names:
            raise InputError("suite scenes", f"fallback {sc['fallback']!r} of {sc['name']!r}", "a scene of this suite")
    methods = []
    for m in spec["methods"]:
        entry = {"name": m} if isinstance(m, str) else dict(m)
        if "name" not in entry:
            raise InputError("suite methods", repr(m),
                             "a method name or {name, label, options, true_warps, registration}")
        entry.setdefault("label", entry["name"])
        entry.setdefault("options", {})
        entry.setdefault("true_warps", False)
        entry.setdefault("registration", "local-correlation")
        from capssim.reconstruct.registration import registration_mode_arguments

        registration_mode_arguments(entry["registration"])  # UnknownNameError lists the modes
        methods.append(entry)
    if len({m["label"] for m in methods}) != len(methods):
        raise InputError("suite methods", [m["label"] for m in methods], "unique labels (give variants a 'label')")
    spec["methods"] = methods
    for nz in spec["noise"]:
        if not isinstance(nz, dict) or "name" not in nz or "model" not in nz:
            raise InputError("suite noise", repr(nz), "{name, model: none|gaussian|poisson-gaussian, sigma, preset}")
    return spec


# -- fingerprints and environment ----------------------------------------------------------------
def _sha(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def code_fingerprint(*parts: str) -> str:
    """sha256 of the source files under ``parts`` (paths relative to the repository)."""
    h = hashlib.sha256()
    for part in parts:
        base = REPO_ROOT / part
        files = [base] if base.is_file() else sorted(base.rglob("*.py")) if base.is_dir() else []
        for f in files:
            rel = f.relative_to(REPO_ROOT).as_posix()
            if rel.startswith("capssim/cli/") or rel in ("capssim/visualize.py", "capssim/design.py"):
                continue
            h.update(rel.encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _git_revision() -> dict:
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, timeout=5)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO_ROOT,
                               capture_output=True, text=True, timeout=5)
        if rev.returncode == 0:
            return {"revision": rev.stdout.strip(), "dirty": bool(dirty.stdout.strip())}
    except (OSError, subprocess.SubprocessError):
        pass
    return {"revision": None, "dirty": None}


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment(device: str = "cpu") -> dict:
    """Versions, git revision, CPU/GPU: recorded with every case."""
    import importlib.metadata as md

    import torch

    from capssim.capture import software_versions

    versions = software_versions()
    for pkg in ("scikit-image", "scipy", "opencv-contrib-python-headless"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    gpu = None
    if torch.cuda.is_available():
        gpu = torch.cuda.get_device_name(0)
    return {"versions": versions, "git": _git_revision(), "platform": platform.platform(), "cpu": _cpu_model(),
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(), "gpu": gpu, "device": device,
            "hostname": platform.node()}


# -- peak memory ---------------------------------------------------------------------------------
class PeakMemory:
    """Peak RSS of this process while the block runs (sampled by a thread), in MB."""

    def __init__(self, interval_s: float = 0.005, device: str = "cpu"):
        self.interval_s = interval_s
        self.device = device
        self.peak_mb = self.start_mb = float("nan")
        self.cuda_peak_mb = None

    def __enter__(self):
        import psutil

        self._proc = psutil.Process()
        self.start_mb = self.peak_mb = self._proc.memory_info().rss / 2**20
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        if self.device.startswith("cuda"):
            import torch

            torch.cuda.reset_peak_memory_stats()
        return self

    def _sample(self):
        while not self._stop.is_set():
            self.peak_mb = max(self.peak_mb, self._proc.memory_info().rss / 2**20)
            self._stop.wait(self.interval_s)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_mb = max(self.peak_mb, self._proc.memory_info().rss / 2**20)
        if self.device.startswith("cuda"):
            import torch

            self.cuda_peak_mb = torch.cuda.max_memory_allocated() / 2**20
        return False


# -- captures ------------------------------------------------------------------------------------
class Unavailable(Exception):
    """A scene's data or renderer is missing: the case is skipped, not failed."""


def _sensor(noise: dict):
    from capssim.sensor import make_sensor

    extra = {k: v for k, v in noise.items() if k not in ("name", "model", "sigma", "preset")}
    return make_sensor(noise["model"], sigma=noise.get("sigma"), preset=noise.get("preset"), **extra)


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


def _render_module():
    try:
        import capssim.render as render  # noqa: F401
    except ImportError as exc:
        raise Unavailable(f"rendering unavailable: capssim.render cannot be imported ({exc})") from None
    if not hasattr(render, "render_capture"):
        raise Unavailable("rendering unavailable: capssim.render has no render_capture")
    return render


def apply_sensor(clean, sensor, seed: int):
    """Noise a noise-free capture: the CAPS and DoFP streams of :func:`simulate_capture`."""
    from capssim.capture import Capture

    _, caps_rng, dofp_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    meta = copy.deepcopy(clean.meta)
    meta["sensor"] = sensor.to_meta()
    meta["seed"] = seed
    meta.setdefault("bench", {})["noise_applied_by"] = "capssim.eval.bench.apply_sensor (after a noise-free render)"
    caps = sensor.capture(np.asarray(clean.caps_raw, dtype=np.float64), caps_rng)
    dofp = sensor.capture(np.asarray(clean.dofp_raw, dtype=np.float64), dofp_rng) if clean.dofp_raw is not None else None
    return Capture(meta=meta, caps_raw=caps, dofp_raw=dofp, gt=clean.gt)


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
        from capssim.capture import read_meta

        ident = self._scene_identity(scene, seed)
        key = _sha({"scene": ident, "noise": noise})[:20]
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
        capture, info = self._build(scene, noise, seed, ident)
        info["build_time_s"] = time.perf_counter() - t0
        from capssim.capture import write_capture

        write_capture(path, capture, overwrite=path.exists())
        atomic_write_json(info_path, info)
        info["cached"] = False
        return CaptureEntry(key, path, scene["name"], info)

    def _build(self, scene: dict, noise: dict, seed: int, ident: dict):
        from capssim.simulate import prepare_ground_truth, simulate_capture

        sensor = _sensor(noise)
        psf_sigma = float(scene.get("psf_sigma", 0.5))
        psf = {"type": "gaussian", "sigma_hr_px": psf_sigma} if psf_sigma > 0 else {"type": "none"}
        src = scene["source"]
        info: dict[str, Any] = {"scene": scene["name"], "source": src, "noise": noise, "seed": seed}
        if src == "render":
            clean, render_info = self._render(scene, seed)
            info.update(render_info)
            return apply_sensor(clean, sensor, seed), info
        if src == "synthetic":
            from capssim.eval.synthetic import synthetic_scene

            gt, scene_meta = synthetic_scene(scene.get("generator", "texture"), size=int(scene.get("size", 128)),
                                             seed=int(scene.get("scene_seed", seed)), cycles=int(scene.get("cycles", 36)))
            source = {"type": "synthetic", **{k: v for k, v in scene_meta.items() if k != "star"}}
        else:
            from capssim.imageio import read_gt_scene

            gt, source = read_gt_scene(_resolve_gt_path(scene))
            scene_meta = {}
            gt, crop_info = prepare_ground_truth(gt, crop=scene.get("crop"))
            source.update(crop_info)
        extra = {"scene": {"name": scene["name"], **scene_meta}}
        capture = simulate_capture(gt, sensor, seed=seed, psf=psf, source=source, extra_meta=extra)
        return capture, info

    def _render(self, scene: dict, seed: int):
        """Noise-free render, cached by content hash (scene spec, seed, render code)."""
        from capssim.capture import read_capture, write_capture
        from capssim.sensor import make_sensor

        render = _render_module()
        name = scene.get("scene", scene["name"])
        if hasattr(render, "list_scenes"):
            try:
                known = list(render.list_scenes())
            except Exception as exc:  # a renderer that cannot even list its scenes is unavailable
                raise Unavailable(f"rendering unavailable: list_scenes failed ({exc})") from None
            if known and name not in known:
                raise Unavailable(f"scene {name!r} is not one of the renderer's scenes ({', '.join(map(str, known))})")
        params = {"scene": name, "size": int(scene.get("size", 256)), "spp": scene.get("spp"), "seed": seed,
                  "variant": scene.get("variant", "auto"), "scene_params": scene.get("scene_params")}
        key = _sha({"render": params, "code": code_fingerprint("capssim/render", "scenes", "capssim/operators",
                                                               "capssim/simulate.py", "capssim/capture.py")})[:20]
        path = self.cache_dir / "renders" / key
        if (path / "meta.json").is_file():
            try:
                clean = read_capture(path, require_gt=True)
                return clean, {"render": params, "render_cached": True, "render_variant": _variant_of(clean)}
            except CapssimError:
                log.warning("cached render %s is corrupt; re-rendering", path)
        self.events("note", message=f"rendering {name} at {params['size']} px (cached afterwards)")
        t0 = time.perf_counter()
        extra = {"scene_params": scene["scene_params"]} if scene.get("scene_params") else {}
        try:
            clean = render.render_capture(name, size=params["size"], spp=params["spp"], seed=seed,
                                          sensor=make_sensor("none"), variant=params["variant"], record_timing=True,
                                          **extra)
        except ImportError as exc:
            raise Unavailable(f"rendering unavailable ({exc})") from None
        elapsed = time.perf_counter() - t0
        if clean.gt is None:
            raise CapssimError(f"render of {name!r} returned no ground truth")
        write_capture(path, clean, overwrite=path.exists())
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
            render = _render_module()
            names = list(render.list_scenes()) if hasattr(render, "list_scenes") else []
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


# -- the run -------------------------------------------------------------------------------------
@dataclass
class BenchRun:
    spec: dict
    output: Path
    results_path: Path
    records: list[dict]  # this plan's records, in plan order
    environment: dict
    notes: list[str] = field(default_factory=list)
    wall_time_s: float = 0.0

    @property
    def n_errors(self) -> int:
        return sum(r["status"] == "error" for r in self.records)

    def ok_records(self) -> list[dict]:
        return [r for r in self.records if r["status"] == "ok"]


def case_key(scene: str, noise: str, seed: int, method_label: str) -> str:
    """Readable, stable identity of a case in baselines: ``scene/noise/seedN/method``."""
    return f"{scene}/{noise}/seed{seed}/{method_label}"


def _load_results(path: Path) -> dict[str, dict]:
    done: dict[str, dict] = {}
    if not path.is_file():
        return done
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            log.warning("ignoring a corrupt line of %s", path)
            continue
        if isinstance(rec, dict) and "case_id" in rec:
            done[rec["case_id"]] = rec
    return done


def _write_results(path: Path, records: list[dict]) -> None:
    atomic_write_text(path, "".join(json.dumps(r, default=_json_default) + "\n" for r in records))


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def run_suite(spec: dict, output: str | Path, *, methods: list[str] | None = None, scenes: list[str] | None = None,
              device: str = "cpu", cache_dir: str | Path | None = None, fresh: bool = False,
              events: Callable[..., None] | None = None) -> BenchRun:
    """Run (or resume) a suite into ``output``; see the module docstring."""
    from capssim.capture import read_capture, write_reconstruction
    from capssim.eval import metrics as M
    from capssim.eval.evaluate import SUB_IMAGE_PITCH_HR, flat_mtf, mtf_summary, star_geometry
    from capssim.eval.mtf import measure_star
    from capssim.reconstruct.registry import available_methods, reconstruct, resolve_device

    emit = events or (lambda kind, **info: None)
    t_start = time.perf_counter()
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    cache = Path(cache_dir) if cache_dir else output / "cache"
    results_path = output / "results.jsonl"
    dev = str(resolve_device(device))
    env = environment(dev)
    conv = M.get_convention(spec.get("convention", "capssim"))

    method_entries = spec["methods"]
    if methods:
        known = {m["label"] for m in method_entries} | {m["name"] for m in method_entries}
        unknown = sorted(set(methods) - known)
        if unknown:
            raise UnknownNameError("suite method", unknown[0], sorted(known))
        method_entries = [m for m in method_entries if m["label"] in methods or m["name"] in methods]
    spec_scenes = expand_render_scenes(spec["scenes"], emit)
    scene_by_name = {s["name"]: s for s in spec_scenes}
    fallback_targets = {s["fallback"] for s in spec_scenes if s.get("fallback")}
    plan_scenes = [s for s in spec_scenes if s["name"] not in fallback_targets]
    if scenes:
        unknown = sorted(set(scenes) - set(scene_by_name))
        if unknown:
            raise UnknownNameError("suite scene", unknown[0], sorted(scene_by_name))
        plan_scenes = [scene_by_name[n] for n in scenes]

    registered = available_methods()
    recon_code = code_fingerprint("reconstruct")
    scoring_code = code_fingerprint("eval/metrics.py", "eval/mtf.py", "eval/evaluate.py", "eval/bench.py")
    previous = {} if fresh else _load_results(results_path)
    factory = CaptureFactory(cache, emit)
    notes: list[str] = []
    records: list[dict] = []
    announced: set[str] = set()
    n_total = len(plan_scenes) * len(spec["noise"]) * len(spec["seeds"]) * len(method_entries)
    emit("start", total=n_total)

    def flush():
        keep = {r["case_id"] for r in records}
        extra = [r for cid, r in previous.items() if cid not in keep and r.get("status") == "ok"]
        _write_results(results_path, records + extra)

    for scene in plan_scenes:
        for noise in spec["noise"]:
            for seed in spec["seeds"]:
                base = {"suite": spec["name"], "noise": noise["name"], "seed": int(seed), "environment": env,
                        "convention": conv.name}
                # the capture (or its fallback)
                entry, used_scene, skip_reason, failure = None, scene, None, None
                chain = [scene] + ([scene_by_name[scene["fallback"]]] if scene.get("fallback") else [])
                for candidate in chain:
                    try:
                        emit("case", label=f"{candidate['name']}/{noise['name']}/seed{seed}: capture")
                        entry = factory.get(candidate, noise, int(seed))
                        used_scene = candidate
                        break
                    except Unavailable as exc:
                        msg = f"{candidate['name']}: {exc}"
                        skip_reason = msg if skip_reason is None else f"{skip_reason}; {msg}"
                        emit("skip", message=f"skipped {msg}")
                    except Exception as exc:  # building the capture failed: every case of it fails
                        failure = (f"capture {candidate['name']}/{noise['name']}/seed{seed}: "
                                   f"{type(exc).__name__}: {exc}", traceback.format_exc(limit=8))
                        emit("error", message=f"error: {failure[0]}")
                        break
                if entry is not None and used_scene is not scene:
                    note = f"{scene['name']} unavailable ({skip_reason}); used {used_scene['name']} instead"
                    if note not in notes:
                        notes.append(note)
                        emit("note", message=note)
                if entry is None:
                    for m in method_entries:
                        rec = dict(base, scene=scene["name"], method=m["label"], method_name=m["name"],
                                   key=case_key(scene["name"], noise["name"], seed, m["label"]),
                                   case_id=_sha([scene["name"], noise, seed, m, "unavailable"])[:20])
                        if failure is not None:
                            rec.update(status="error", reason=failure[0], traceback=failure[1])
                        else:
                            rec.update(status="skipped", skip_kind="data", reason=skip_reason)
                        records.append(rec)
                        emit("done")
                    flush()
                    continue
                capture = None
                gt_mtf = None
                star = None
                for m in method_entries:
                    key = case_key(used_scene["name"], noise["name"], seed, m["label"])
                    cid = _sha({"capture": entry.key, "method": m, "device": dev, "recon": recon_code,
                                "scoring": scoring_code, "convention": conv.name})[:20]
                    rec = dict(base, scene=used_scene["name"], requested_scene=scene["name"], method=m["label"],
                               method_name=m["name"], key=key, case_id=cid, capture=str(entry.path),
                               capture_key=entry.key, scene_source=used_scene["source"])
                    if cid in previous and previous[cid].get("status") == "ok":
                        records.append(previous[cid])
                        emit("done")
                        continue
                    if m["name"] not in registered:
                        rec.update(status="skipped", skip_kind="method",
                                   reason=f"method {m['name']!r} is not registered (available: "
                                          f"{', '.join(registered) or 'none'})")
                        if m["name"] not in announced:
                            announced.add(m["name"])
                            emit("skip", message=f"skipping every case of {m['label']}: {rec['reason']}")
                        records.append(rec)
                        flush()
                        emit("done")
                        continue
                    emit("case", label=key)
                    try:
                        if capture is None:
                            capture = read_capture(entry.path, require_gt=True)
                            star = star_geometry(capture.meta)
                            if star is not None:
                                try:
                                    gt_mtf = measure_star(capture.gt, star["cycles"],
                                                          names=[str(c) for c in range(12)],
                                                          center_rowcol=star.get("center_rowcol"),
                                                          radius=star.get("radius_px"),
                                                          reference_modulation=star.get("contrast"),
                                                          reference_pitch=SUB_IMAGE_PITCH_HR)
                                except CapssimError as exc:  # the scene is scored, only without its MTF
                                    note = f"{used_scene['name']}: ground-truth MTF not measured ({exc})"
                                    notes.append(note)
                                    emit("note", message=note)
                                    star = None
                        if registered[m["name"]].input_kind == "dofp" and capture.dofp_raw is None:
                            raise Unavailable("this capture has no DoFP frame")
                        with PeakMemory(device=dev) as mem:
                            out, record = reconstruct(capture, m["name"], device=dev, true_warps=bool(m["true_warps"]),
                                                      registration=m["registration"], **m["options"])
                        write_reconstruction(entry.path, m["label"], out.image, record)
                        scored = M.score(out.image, capture.gt, convention=conv)
                        rec.update(status="ok", metrics=M.flatten(scored), notes=scored["notes"],
                                   metric_settings=scored["settings"],
                                   wall_time_s=record["wall_time_s"], stages_s=record["stages_s"],
                                   peak_rss_mb=mem.peak_mb, peak_rss_delta_mb=mem.peak_mb - mem.start_mb,
                                   cuda_peak_mb=mem.cuda_peak_mb, params=record.get("params"),
                                   registration=record.get("registration"), capture_info=entry.info,
                                   recon=str(entry.path / "recon" / f"{m['label']}.tiff"))
                        if star is not None:
                            head = gt_mtf.results["mean"]
                            refs = [gt_mtf.results[str(c)].reference_modulation for c in range(12)]
                            rec["gt_mtf"] = mtf_summary(gt_mtf)["mean"]
                            rec["star"] = star
                            try:
                                res = measure_star(out.image, star["cycles"], names=[str(c) for c in range(12)],
                                                   center_rowcol=head.center_rowcol, radius=head.radius_px,
                                                   reference_modulation=refs, reference_pitch=SUB_IMAGE_PITCH_HR)
                                summ = mtf_summary(res)
                                rec["metrics"].update(flat_mtf(summ))
                                rec["mtf"] = summ["mean"]
                            except CapssimError as exc:
                                rec["mtf_error"] = str(exc)
                    except Unavailable as exc:
                        rec.update(status="skipped", skip_kind="data", reason=str(exc))
                        emit("skip", message=f"skipped {key}: {exc}")
                    except Exception as exc:  # a failing method must not stop the benchmark
                        rec.update(status="error", reason=f"{type(exc).__name__}: {exc}",
                                   traceback=traceback.format_exc(limit=8))
                        emit("error", message=f"error in {key}: {type(exc).__name__}: {exc}")
                    rec["finished"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
                    records.append(rec)
                    flush()
                    emit("done")
    flush()
    return BenchRun(spec=spec, output=output, results_path=results_path, records=records, environment=env,
                    notes=notes, wall_time_s=time.perf_counter() - t_start)


# -- baselines -----------------------------------------------------------------------------------
def tolerance_for(metric: str, tolerances: dict[str, float]) -> float | None:
    """Tolerance of a metric, or None when it is not a checked quality metric."""
    from capssim.eval.metrics import metric_direction

    head = metric.split(".", 1)[0]
    if head.startswith("mtf_magnification"):
        return tolerances["mtf_magnification"]
    if head.startswith("mtf_limit"):
        return tolerances["mtf_limit"]
    if metric_direction(metric) == 0:
        return None
    if "ssim" in head:
        return tolerances["ssim"]
    if "psnr" in head:
        return tolerances["psnr_db"]
    if head.startswith("aop_") and head.endswith("_deg"):
        return tolerances["aop_deg"]
    if head.startswith("lpips"):
        return tolerances["lpips"]
    return None


def write_baseline(run: BenchRun, path: str | Path) -> int:
    """Store this run's metrics as the regression baseline (atomic). Returns the number of cases."""
    cases = {}
    for r in run.ok_records():
        cases[r["key"]] = {"metrics": {k: v for k, v in r["metrics"].items() if v is not None},
                           "wall_time_s": r.get("wall_time_s"),
                           "render_variant": (r.get("capture_info") or {}).get("render_variant")}
    if not cases:
        raise InputError("update-baseline", "a run without any successful case", "at least one scored case")
    baseline = {"schema": BASELINE_SCHEMA, "version": 1, "suite": run.spec["name"], "suite_sha256": run.spec["sha256"],
                "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "environment": run.environment, "tolerances": dict(DEFAULT_TOLERANCES),
                "notes": "Regenerate with: capssim bench --suite NAME -o OUT --update-baseline PATH. "
                         "Tolerances may be edited here; timings are informational only.",
                "cases": cases}
    atomic_write_json(path, baseline)
    return len(cases)


@dataclass
class Verdict:
    passed: bool
    failures: list[str]
    compared: list[str]
    not_compared: list[str]
    new_cases: list[str]
    improvements: list[str]
    timings: list[str]
    notes: list[str] = field(default_factory=list)

    def text(self) -> str:
        lines = [f"regression check: {'PASSED' if self.passed else 'FAILED'} "
                 f"({len(self.compared)} case(s) compared, {len(self.failures)} failure(s))"]
        lines += [f"  FAIL {f}" for f in self.failures]
        lines += [f"  note: {n}" for n in self.notes]
        lines += [f"  not compared: {n}" for n in self.not_compared]
        lines += [f"  new (not in baseline): {n}" for n in self.new_cases]
        if self.improvements:
            lines.append(f"  {len(self.improvements)} metric(s) improved beyond tolerance (consider --update-baseline):")
            lines += [f"    {i}" for i in self.improvements[:20]]
        lines += [f"  time {t}" for t in self.timings]
        return "\n".join(lines)


def check_against_baseline(run: BenchRun, baseline_path: str | Path) -> Verdict:
    """Compare a run with a stored baseline (module docstring for the rules)."""
    from capssim.eval.metrics import metric_direction

    path = Path(baseline_path)
    if not path.is_file():
        raise InputError("check", str(path), "an existing baseline JSON",
                         "Create it with: capssim bench --suite NAME -o OUT --update-baseline PATH")
    try:
        base = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError("check", f"corrupt JSON in {path} ({exc})", "a baseline written by --update-baseline") from exc
    if base.get("schema") != BASELINE_SCHEMA:
        raise InputError("check", f"{path} (schema {base.get('schema')!r})", f"a {BASELINE_SCHEMA} file")
    tolerances = {**DEFAULT_TOLERANCES, **base.get("tolerances", {})}
    current = {r["key"]: r for r in run.records}
    failures, compared, not_compared, improvements, timings = [], [], [], [], []
    notes = []
    if base.get("suite") != run.spec["name"]:
        failures.append(f"baseline is for suite {base.get('suite')!r}, this run is {run.spec['name']!r}")
    elif base.get("suite_sha256") != run.spec.get("sha256"):
        notes.append("the suite file changed since the baseline was written; only cases present in both are compared")
    base_git = (base.get("environment") or {}).get("git", {}).get("revision")
    if base_git:
        notes.append(f"baseline written at git {base_git[:12]} on {base.get('created', '?')}")
    for key, stored in sorted(base.get("cases", {}).items()):
        rec = current.get(key)
        if rec is None:
            not_compared.append(f"{key} (not in this run)")
            continue
        if rec["status"] == "skipped":
            if rec.get("skip_kind") == "data":
                not_compared.append(f"{key} (skipped: {rec.get('reason')})")
            else:
                failures.append(f"{key}: skipped ({rec.get('reason')})")
            continue
        if rec["status"] == "error":
            failures.append(f"{key}: error ({rec.get('reason')})")
            continue
        base_variant = stored.get("render_variant")
        run_variant = (rec.get("capture_info") or {}).get("render_variant")
        if base_variant and run_variant and base_variant != run_variant:
            # another Mitsuba variant draws other Monte-Carlo samples: not the same capture
            not_compared.append(f"{key} (rendered with {run_variant}, baseline with {base_variant})")
            continue
        compared.append(key)
        cur = rec["metrics"]
        for metric, ref in sorted(stored["metrics"].items()):
            tol = tolerance_for(metric, tolerances)
            direction = metric_direction(metric)
            if tol is None or direction == 0 or ref is None:
                continue
            value = cur.get(metric)
            if value is None:
                failures.append(f"{key} {metric}: was {ref:.4g}, now undefined/missing")
                continue
            change = (value - ref) * direction  # > 0 is better
            if change < -tol:
                failures.append(f"{key} {metric}: {ref:.4f} -> {value:.4f} "
                                f"({'fell' if direction > 0 else 'rose'} by {abs(value - ref):.4f}, tolerance {tol})")
            elif change > tol:
                improvements.append(f"{key} {metric}: {ref:.4f} -> {value:.4f}")
        t_ref, t_now = stored.get("wall_time_s"), rec.get("wall_time_s")
        if t_ref and t_now:
            timings.append(f"{key}: {t_now:.2f} s vs {t_ref:.2f} s baseline (x{t_now / t_ref:.2f}, not checked)")
    new_cases = sorted(k for k, r in current.items() if r["status"] == "ok" and k not in base.get("cases", {}))
    if not compared:
        failures.append("no case could be compared with the baseline (all skipped or missing)")
    return Verdict(passed=not failures, failures=failures, compared=compared, not_compared=not_compared,
                   new_cases=new_cases, improvements=improvements, timings=timings, notes=notes)
