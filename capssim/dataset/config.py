"""The dataset config (YAML): reading, validation, and the parameters of each sample.

Format (docs: guides/datasets.md; ``examples/dataset-small.yaml``)::

    name: small                  # optional; default: the file name
    seed: 7                      # master seed (integer >= 0)
    samples: 6                   # number of samples (>= 1)
    selection: cycle             # cycle: sample i uses source i % n; random: by source weight
    defaults:                    # parameters shared by all sources; a source may replace any key
      sensor: {noise: {choice: [none, gaussian]}, sigma: {log_uniform: [0.002, 0.02]}}
      dofp_layout: {choice: [sony, 0-45-135-90]}
      pose: {shift_max_px: {uniform: [0.5, 2.0]}, rotation_max_deg: 0.5, scale_max: 0.005}   # gt sources
      psf_sigma_hr_px: 0.5                                                                # gt sources
      extinction_ratio: null                                                              # gt sources
      rig: {preset: realistic, seed: 2, gain: [1.05, 0.95, 1, 1]}   # imperfect array (guides/calibration.md)
    sources:
      - gt: ../shared/data/gt/qiu-kettle     # folder of 0/45/90/135.png, a 12-channel TIFF, or a glob
        size: 64                             # HR crop (multiple of 4); null = whole image
        crop_position: random                # or center
        augment: {rot90: {int_uniform: [0, 3]}, flip: {choice: [false, true]}}
      - scene: siemens-star                  # a scene of capssim.render (``capssim scenes``)
        size: 64
        spp: 16
        scene_params: {material: {choice: [gold, plastic]}}
        geometry_params: {depth_m: {uniform: [2, 10]}}

Any value may be a distribution (see :mod:`capssim.dataset.distributions`). Relative paths are
relative to the config file. Errors name the key path, e.g. ``sources[1].size``.
"""

from __future__ import annotations

import copy
import difflib
import glob
import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from capssim.camera.camera_setup import DEFAULT_DOFP_LAYOUT, DEFAULT_NOISE, DEFAULT_SENSOR_PRESET
from capssim.camera.psf import DEFAULT_SIGMA_HR_PX
from capssim.camera.rig import RigModel
from capssim.conventions import POLARIZER_ANGLES_DEG
from capssim.dataset.config_specs import (  # noqa: F401  (re-exported: the config's keys and limits)
    COLOUR_AUGMENTS,
    DEFAULT_SCENE_SIZE,
    GT_ONLY_KEYS,
    GT_SOURCE_SPEC,
    MIN_SIZE,
    RENDER_OPTICS_KEYS,
    SCENE_SOURCE_SPEC,
    SHARED_KEYS,
    SIZE_MULTIPLE,
    TOP_SPEC,
)
from capssim.dataset.distributions import Choice, Const, Dist, draw_tree, key_rng
from capssim.errors import InputError
from capssim.files.imageio import GT_IMAGE_SUFFIXES
from capssim.files.schema import ConfigError, join, show
from capssim.render import list_scenes
from capssim.simulate import PoseRanges

log = logging.getLogger(__name__)

def _possible_values(dist: Dist) -> list | None:
    """Every value a discrete distribution can draw (None for a continuous one)."""
    return [dist.value] if isinstance(dist, Const) else list(dist.values) if isinstance(dist, Choice) else None


# -- the parsed config ------------------------------------------------------------------------
@dataclass
class Source:
    """One source of ground truth: a GT folder/glob (``kind == 'gt'``) or a rendered scene."""

    index: int
    kind: str
    label: str
    weight: float
    spec: dict                       # validated fields: Dist trees and plain values
    gt_paths: list[str] = field(default_factory=list)       # as written (relative to the config)
    gt_resolved: list[str] = field(default_factory=list)    # absolute

    @property
    def key(self) -> str:
        return f"sources[{self.index}]"


@dataclass
class DatasetConfig:
    name: str
    seed: int
    samples: int
    selection: str
    defaults: dict
    sources: list[Source]
    raw: dict
    config_file: str | None = None
    base_dir: Path = field(default_factory=Path.cwd)

    def fingerprint(self) -> str:
        """sha256 of the config without ``samples``: samples of two configs with the same
        fingerprint are identical, so a dataset may be extended by raising ``samples``."""
        raw = {k: v for k, v in self.raw.items() if k != "samples"}
        return hashlib.sha256(json.dumps(raw, sort_keys=True, default=str).encode()).hexdigest()

    @property
    def name_width(self) -> int:
        return max(6, len(str(self.samples - 1)))

    def sample_name(self, index: int) -> str:
        return f"{index:0{self.name_width}d}"

    def source_of(self, index: int) -> Source:
        if self.selection == "cycle":
            return self.sources[index % len(self.sources)]
        weights = np.asarray([s.weight for s in self.sources], dtype=np.float64)
        k = int(key_rng(self.seed, index, "source").choice(len(self.sources), p=weights / weights.sum()))
        return self.sources[k]

    def sample_spec(self, index: int) -> dict:
        """Everything a worker needs to make sample ``index``: its name, seed and drawn parameters.

        Deterministic in (config, index) only.
        """
        if not 0 <= index < self.samples:
            raise IndexError(f"sample index {index} outside 0..{self.samples - 1}")
        src = self.source_of(index)
        seed_state = key_rng(self.seed, index, "capture_seed").integers(0, 2**63, dtype=np.int64)
        capture_seed = int(seed_state)
        params: dict = {}
        shared = {k: src.spec.get(k, self.defaults.get(k)) for k in SHARED_KEYS}
        shared_path = {k: (join(src.key, k) if k in src.spec else k) for k in SHARED_KEYS}
        drawn = {k: draw_tree(v, self.seed, index, shared_path[k]) for k, v in shared.items() if v is not None}
        params["sensor"] = _canonical_sensor(drawn.get("sensor") or {})
        params["dofp_layout"] = drawn.get("dofp_layout", DEFAULT_DOFP_LAYOUT)
        params["rig"] = drawn.get("rig")
        # refuses bad values before any sample is made
        rig_model(params["rig"], key_path=join(src.key, "rig") if "rig" in src.spec else "defaults.rig")
        resolved: dict = {}
        if src.kind == "gt":
            fields = draw_tree({k: v for k, v in src.spec.items() if k in ("size", "crop_position", "augment")},
                               self.seed, index, src.key)
            k = 0
            if len(src.gt_paths) > 1:
                k = int(key_rng(self.seed, index, join(src.key, "gt")).integers(len(src.gt_paths)))
            uv = key_rng(self.seed, index, join(src.key, "crop_uv")).random(2)
            augment = fields.get("augment") or {}
            params["source"] = {
                "type": "gt", "name": src.label, "path": src.gt_paths[k], "size": fields.get("size"),
                "crop_position": fields.get("crop_position", "center"),
                "crop_uv": [float(uv[0]), float(uv[1])],
                "rot90": int(augment.get("rot90", 0)), "flip": bool(augment.get("flip", False)),
                **{name: float(augment[name]) for name in COLOUR_AUGMENTS if name in augment},
            }
            pose = {**PoseRanges().__dict__, **(drawn.get("pose") or {})}
            params["pose"] = {key: float(value) for key, value in pose.items()}
            params["psf_sigma_hr_px"] = float(drawn.get("psf_sigma_hr_px", DEFAULT_SIGMA_HR_PX))
            params["extinction_ratio"] = drawn.get("extinction_ratio")
            resolved["gt_path"] = src.gt_resolved[k]
        else:
            fields = draw_tree({k: v for k, v in src.spec.items()
                                if k in ("size", "spp", "target_noise", "scene_params", "geometry_params")},
                               self.seed, index, src.key)
            for key in RENDER_OPTICS_KEYS:  # None: the renderer's default
                params[key] = drawn.get(key)
            params["source"] = {
                "type": "scene", "name": src.label, "scene": src.spec["scene"],
                "size": int(fields.get("size", DEFAULT_SCENE_SIZE)), "spp": fields.get("spp"),
                "variant": src.spec.get("variant", "auto"), "target_noise": fields.get("target_noise"),
                "scene_params": fields.get("scene_params") or {}, "geometry_params": fields.get("geometry_params") or {},
            }
        return {"index": index, "name": self.sample_name(index), "seed": capture_seed, "dataset": self.name,
                "master_seed": self.seed, "params": params, "resolved": resolved}


def rig_model(spec: dict | None, *, key_path: str = "rig") -> RigModel | None:
    """The :class:`~capssim.camera.rig.RigModel` of a drawn ``rig`` entry (``None``: the ideal array);
    errors name ``key_path`` and the quantity."""
    if not spec:
        return None
    try:
        return RigModel.from_spec(spec)
    except InputError as exc:
        raise ConfigError(join(key_path, exc.argument), exc.received, exc.valid, exc.fix) from None


def _canonical_sensor(drawn: dict) -> dict:
    """Keep only the sensor fields that apply to the drawn noise model."""
    noise = drawn.get("noise", DEFAULT_NOISE)
    out: dict = {"noise": noise}
    if noise == "gaussian":
        out["sigma"] = float(drawn["sigma"])
        if "bit_depth" in drawn:
            out["bit_depth"] = int(drawn["bit_depth"])
    elif noise == "poisson-gaussian":
        out["preset"] = drawn.get("preset", DEFAULT_SENSOR_PRESET)
        for key in ("exposure", "bit_depth"):
            if key in drawn:
                out[key] = drawn[key]
    return out


# -- reading and checking -----------------------------------------------------------------------
def load_config(path) -> DatasetConfig:
    """Read and validate a dataset config file (YAML). Raises :class:`ConfigError`."""
    path = Path(path)
    label = str(path)
    if not path.is_file():
        raise ConfigError("", f"no file at {str(path)!r}", "a readable YAML file",
                          "Check the path; see examples/dataset-small.yaml.", config_file=None)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("", f"an unreadable file ({exc})", "a UTF-8 YAML file", config_file=label) from exc
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError("", f"text that is not valid YAML{where} ({problem})", "a YAML mapping",
                          "Fix the YAML syntax (indentation, colons, brackets).", config_file=label) from None
    return parse_config(raw, base_dir=path.resolve().parent, config_file=label, default_name=path.stem)


def parse_config(raw, *, base_dir=None, config_file: str | None = None, default_name: str = "dataset") -> DatasetConfig:
    """Validate an already-loaded config mapping (see :func:`load_config`)."""
    base_dir = Path(base_dir) if base_dir is not None else Path.cwd()
    try:
        return _parse(raw, base_dir, config_file, default_name)
    except ConfigError as exc:
        if exc.config_file is None and config_file is not None:
            raise ConfigError(exc.key_path, exc.received, exc.valid, exc.fix, config_file=config_file) from None
        raise


def _parse(raw, base_dir: Path, config_file, default_name) -> DatasetConfig:
    if raw is None:
        raise ConfigError("", "an empty file", "a YAML mapping with seed, samples and sources",
                          "See examples/dataset-small.yaml.")
    top = TOP_SPEC.check(raw, "")
    defaults = top.get("defaults") or {}
    selection = top.get("selection", "cycle")
    sources = [_parse_source(s, i, base_dir, selection) for i, s in enumerate(top["sources"])]
    if selection == "random" and sum(s.weight for s in sources) <= 0:
        raise ConfigError("sources", "weights that are all 0", "at least one source with weight > 0",
                          "A dataset whose sources all have weight 0 has no samples to draw.")
    if any(s.kind == "scene" for s in sources):
        set_gt_only = [k for k in GT_ONLY_KEYS if k in defaults]
        if set_gt_only:
            log.debug("defaults %s apply to ground-truth sources only; rendered scenes draw their own "
                     "aperture errors (set them in geometry_params)", ", ".join(set_gt_only))
    for src in sources:
        sensor = src.spec.get("sensor", defaults.get("sensor")) or {}
        sensor_path = join(src.key, "sensor") if "sensor" in src.spec else "defaults.sensor"
        noise = sensor.get("noise")
        noises = _possible_values(noise) if noise is not None else ["none"]
        if "gaussian" in noises and "sigma" not in sensor:
            raise ConfigError(join(sensor_path, "sigma"), "nothing (missing key)",
                              "the Gaussian noise std on [0, 1] data, since noise can be 'gaussian'",
                              "Add e.g. sigma: 0.01 or sigma: {log_uniform: [0.002, 0.02]}.")
    return DatasetConfig(name=top.get("name", default_name), seed=top["seed"], samples=top["samples"],
                         selection=selection, defaults=defaults, sources=sources, raw=copy.deepcopy(raw),
                         config_file=config_file, base_dir=base_dir)


def _parse_source(raw, index: int, base_dir: Path, selection: str) -> Source:
    key = f"sources[{index}]"
    has_gt, has_scene = "gt" in raw, "scene" in raw
    if has_gt == has_scene:
        raise ConfigError(key, "both gt and scene" if has_gt else f"keys {sorted(raw)}",
                          "exactly one of 'gt: FOLDER' (ground-truth images) or 'scene: NAME' (a rendered scene)")
    if has_scene:
        for k in GT_ONLY_KEYS:
            if k in raw:
                raise ConfigError(join(key, k), "a value for a rendered scene",
                                  "this key only in ground-truth (gt) sources",
                                  "Rendered scenes draw their aperture errors in capssim.render; "
                                  "set them in geometry_params (baseline_m, tilt_max_deg, roll_max_deg, "
                                  "focal_scale_max).")
    spec = (GT_SOURCE_SPEC if has_gt else SCENE_SOURCE_SPEC).check(raw, key)
    if selection == "cycle" and "weight" in spec:
        raise ConfigError(join(key, "weight"), show(spec["weight"]), "no weight with selection: cycle",
                          "Add 'selection: random' at the top level to draw sources by weight.")
    weight = float(spec.get("weight", 1.0))
    if has_gt:
        written, resolved = _expand_gt(spec["gt"], base_dir, join(key, "gt"))
        label = spec.get("name") or (Path(written[0]).name if len(written) == 1 else spec["gt"])
        return Source(index, "gt", label, weight, spec, written, resolved)
    _check_scene(spec, key)
    return Source(index, "scene", spec.get("name") or spec["scene"], weight, spec)


def _check_scene(spec: dict, source_key: str) -> None:
    """The scene is registered (:mod:`capssim.scenes`) and its scene_params are its own."""
    name, key = spec["scene"], join(source_key, "scene")
    scenes = list_scenes()
    known = sorted(scenes)
    if name not in known:
        close = difflib.get_close_matches(name, known, n=1)
        raise ConfigError(key, f"unknown scene {name!r}", f"one of {', '.join(known)}",
                          (f"Did you mean {close[0]!r}? " if close else "") + "'capssim scenes' lists them.")
    defaults = scenes[name].defaults
    for param in spec.get("scene_params") or {}:
        if param not in defaults:
            raise ConfigError(join(join(source_key, "scene_params"), param), "an unknown parameter",
                              f"a parameter of scene {name!r}: {', '.join(sorted(defaults)) or 'none'}")


def _is_gt(path: Path) -> bool:
    if path.is_file():
        return path.suffix.lower() in (".tif", ".tiff")
    return path.is_dir() and all(any((path / f"{a}{s}").is_file() for s in GT_IMAGE_SUFFIXES)
                                 for a in POLARIZER_ANGLES_DEG)


def _expand_gt(pattern: str, base_dir: Path, key: str) -> tuple[list[str], list[str]]:
    """A GT path or glob -> (paths as written relative to the config, absolute paths)."""
    expanded = os.path.expanduser(pattern)
    absolute = expanded if os.path.isabs(expanded) else str(base_dir / expanded)
    if glob.has_magic(expanded):
        matches = sorted(glob.glob(absolute))
        if not matches:
            raise ConfigError(key, f"{pattern!r}, which matches nothing (looked in {absolute})",
                              "a pattern matching ground-truth folders")
        bad = [m for m in matches if not _is_gt(Path(m))]
        if bad:
            raise ConfigError(key, f"{pattern!r}, which matches {bad[0]!r}",
                              "only folders holding 0/45/90/135.png or 12-channel TIFFs")
    else:
        matches = [absolute]
        p = Path(absolute)
        if not p.exists():
            fix = "Check the path (relative paths are relative to the config file)."
            if "shared" in Path(pattern).parts:
                fix += (" The shared data (../shared/data) is not part of the repository; "
                        "remove this source if you do not have it.")
            raise ConfigError(key, f"{pattern!r}, which does not exist (resolved to {absolute})",
                              "a ground-truth folder (0/45/90/135.png) or a 12-channel TIFF", fix)
        if not _is_gt(p):
            raise ConfigError(key, f"{pattern!r} ({absolute})",
                              "a folder holding 0.png 45.png 90.png 135.png (or .tif/.tiff), or a 12-channel TIFF")
    written = [m if os.path.isabs(expanded) else os.path.relpath(m, base_dir) for m in matches]
    return [Path(w).as_posix() for w in written], [str(Path(m).resolve()) for m in matches]
