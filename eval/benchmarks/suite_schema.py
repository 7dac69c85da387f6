"""The schema of a suite file (YAML), checked when the suite is loaded, before any case runs.

:func:`load_suite` reads a suite (a name in ``eval/suites`` or a YAML path) with
:func:`capssim.files.schema.load_yaml_file` and checks it against :data:`SUITE_SPEC`: unknown keys (with a
"Did you mean" hint), types, ranges, duplicates (seeds, noise names, method labels, scene names),
registered method names, renderer scene names, the sensor of every noise level and the rig of every
scene, and the ground-truth paths. The keys a scene takes depend on its ``source``
(:data:`SOURCE_KEYS`). A mistake is a :class:`~capssim.files.schema.ConfigError`: one line naming the file,
the key path (e.g. ``scenes[2].crop``) and the fix (exit 2 on the command line).

:func:`check_scene_memory` is the resource guard of a suite's scene sizes
(:func:`capssim.runtime.resources.check_scene_size`, as ``bench reconstruct --size``), run before any work.

The keys, their values and their defaults are listed in docs/guides/benchmarks.md and docs/guides/limits.md.
"""

from __future__ import annotations

import difflib
from dataclasses import fields
from pathlib import Path

from capssim.camera.camera_setup import sensor_from_mapping
from capssim.camera.rig import RigModel
from capssim.camera.sensor import GaussianSensor, NoNoiseSensor, PoissonGaussianSensor
from capssim.dataset.calibration_captures import MIN_POLARIZER_ANGLES
from capssim.errors import CapssimError, InputError
from capssim.files.schema import (
    AnyMapping,
    Boolean,
    ConfigError,
    Integer,
    Mapping,
    Nullable,
    Number,
    Sequence,
    Spec,
    String,
    join,
    show,
)
from capssim.reconstruct.option_probe import check_method_options
from capssim.reconstruct.registration.parameters import REGISTRATION_MODES
from capssim.reconstruct.registry import available_methods, default_registration
from capssim.runtime.resources import check_scene_size
from capssim.simulate import MIN_HR_SIZE

from ..metrics import CONVENTIONS
from ..synthetic import GENERATORS
from . import captures
from .provenance import REPO_ROOT, shared_data_dir
from .rigs import METHOD_CALIBRATIONS
from .spec_files import available_specs, load_spec_file, spec_path

SUITES_DIR = Path(__file__).resolve().parents[1] / "suites"
SCENE_SOURCES = ("render", "shared-gt", "gt", "synthetic")
#: ``role:`` of a suite: ``development`` (defaults may be chosen on it; the default of a suite file that names
#: none) or ``test`` (frozen: run to report, never to choose a default, a count or a candidate)
SUITE_ROLES = ("development", "test")
#: largest seed (numpy's SeedSequence takes any integer >= 0; 63 bits keep it an int64 everywhere, as --seed)
MAX_SEED = 2**63 - 1
#: default HR size of a synthetic and of a rendered scene
DEFAULT_SIZE = {"synthetic": 128, "render": 256}
KIND = "suite"

_SIZE = Integer(minimum=MIN_HR_SIZE, multiple_of=4)

#: an imperfect array (capssim.camera.rig.RigModel.from_spec) and its calibration sweep (capssim.eval.benchmarks.rigs)
RIG_SPEC = Mapping({
    "preset": String(choices=["ideal", "realistic"]),
    "seed": Integer(minimum=0, maximum=MAX_SEED),
    "geometry_seed": Integer(minimum=0, maximum=MAX_SEED),
    "angle_offsets_deg": Sequence(Number(minimum=-20, maximum=20), lengths=(4,), what="degrees"),
    "extinction_ratio": Sequence(Number(minimum=1, exclusive_minimum=True), lengths=(1, 3, 12),
                                 what="extinction ratios (all, R G B, or 4 x R G B)",
                                 bare=Number(minimum=1, exclusive_minimum=True)),
    "gain": Sequence(Number(minimum=1e-3, maximum=1e3), lengths=(4,), what="gains (1 = nominal)"),
    "vignetting_corner": Number(minimum=0, maximum=0.9),
    "psf_sigmas_hr_px": Sequence(Number(minimum=0), lengths=(4,), what="Gaussian PSF stds (HR px)"),
    "polarizer_angles": Integer(minimum=MIN_POLARIZER_ANGLES, maximum=180),
}, what="an imperfect array (preset, seed, geometry_seed, angle_offsets_deg, extinction_ratio, gain, "
        "vignetting_corner, psf_sigmas_hr_px, polarizer_angles)")

#: keys of every scene, whatever its source
COMMON_SCENE_KEYS = {
    "name": String(),
    "source": String(choices=list(SCENE_SOURCES)),
    "description": String(),
    "fallback": String(),
    "psf_sigma_hr_px": Number(minimum=0),
    "rig": RIG_SPEC,
}
_GT_KEYS = {"path": String(kind="path"), "crop": _SIZE}
#: the keys of a scene by its ``source`` (besides :data:`COMMON_SCENE_KEYS`)
SOURCE_KEYS = {
    "render": {"scene": String(), "size": _SIZE, "spp": Nullable(Integer(minimum=1, maximum=1 << 16)),
               "variant": String(), "scene_params": AnyMapping("scene parameters (name: value)"),
               "geometry_params": AnyMapping("array geometry (e.g. baseline_m: 0.04)"), "prefix": String()},
    "synthetic": {"generator": String(choices=list(GENERATORS)), "size": _SIZE, "cycles": Integer(minimum=1),
                  "scene_seed": Integer(minimum=0, maximum=MAX_SEED)},
    "shared-gt": _GT_KEYS,
    "gt": _GT_KEYS,
}
REQUIRED_SCENE_KEYS = {"render": ("scene",), "synthetic": (), "shared-gt": ("path",), "gt": ("path",)}
SCENE_SPECS = {src: Mapping({**COMMON_SCENE_KEYS, **SOURCE_KEYS[src]}, required=("name", "source",
                                                                             *REQUIRED_SCENE_KEYS[src]),
                            what=f"a {src} scene") for src in SCENE_SOURCES}

METHOD_SPEC = Mapping({
    "name": String(choices=lambda: list(available_methods())),
    "label": String(),
    "options": AnyMapping("the method's keyword options (name: value)"),
    "true_warps": Boolean(),
    "registration": String(choices=lambda: list(REGISTRATION_MODES)),
    "calibration": String(choices=list(METHOD_CALIBRATIONS)),
    "uncertainty": Integer(minimum=2, maximum=64),
}, required=("name",), what="a method (a name, or {name, label, options, true_warps, registration, calibration, "
                            "uncertainty})")

#: the sensor fields each noise model takes (besides ``name`` and ``noise``)
_SENSOR_FIELDS = {model: [f.name for f in fields(kind) if f.name != "model"] for model, kind in
                  (("none", NoNoiseSensor), ("gaussian", GaussianSensor), ("poisson-gaussian", PoissonGaussianSensor))}


def _unknown_key(path: str, key: str, known: list[str], elsewhere: str | None = None) -> ConfigError:
    close = difflib.get_close_matches(str(key), known, n=1)
    fix = f"Did you mean {close[0]!r}?" if close else None
    if elsewhere:
        fix = f"{elsewhere}" + (f" Did you mean {close[0]!r}?" if close else "")
    return ConfigError(join(path, str(key)), "an unknown key", f"one of {', '.join(known)}", fix)


class NoiseSpec(Spec):
    """A noise level: ``{name, noise: none|gaussian|poisson-gaussian, ...the sensor fields of that model}``
    (``model``: the old spelling of ``noise``), checked by :func:`capssim.camera.camera_setup.sensor_from_mapping`."""

    description = "a noise level {name, noise: none|gaussian|poisson-gaussian, sigma, preset, ...}"

    def check(self, value, path):
        if not isinstance(value, dict):
            raise ConfigError(path, show(value), self.description, "For example {name: gauss-0.01, noise: gaussian, "
                                                                   "sigma: 0.01}.")
        entry = dict(value)
        if "noise" not in entry and "model" in entry:  # the old spelling, read as ``noise``
            entry = {"noise": entry.pop("model"), **entry}
        for key in ("name", "noise"):
            if key not in entry:
                raise ConfigError(join(path, key), "nothing (missing key)", self.description,
                                  "For example {name: gauss-0.01, noise: gaussian, sigma: 0.01}.")
        name = String().check(entry["name"], join(path, "name"))
        model = String(choices=list(_SENSOR_FIELDS)).check(entry["noise"], join(path, "noise"))
        known = ["name", "noise", *_SENSOR_FIELDS[model]] + (["model"] if "model" in value else [])
        for key in entry:
            if key not in known:
                raise _unknown_key(path, key, known, f"Noise {model!r} takes {', '.join(_SENSOR_FIELDS[model])}.")
        try:
            sensor_from_mapping({k: v for k, v in entry.items() if k != "name"}, where=path)
        except InputError as exc:
            raise ConfigError(exc.argument, exc.received, exc.valid, exc.fix) from None
        return {"name": name, **{k: v for k, v in entry.items() if k != "name"}}


class MethodEntrySpec(Spec):
    """A method entry: a registered name, or a mapping (:data:`METHOD_SPEC`), normalised to the mapping
    with its defaults (``label`` the name, ``options`` {}, ``true_warps`` false, ``registration`` the method's own:
    local-correlation, or fast for ``array-kr``)."""

    description = METHOD_SPEC.description

    def check(self, value, path):
        if isinstance(value, str):
            value = {"name": value}
        entry = METHOD_SPEC.check(value, path)
        entry.setdefault("label", entry["name"])
        entry.setdefault("options", {})
        entry.setdefault("true_warps", False)
        entry.setdefault("registration", default_registration(entry["name"]))
        if any(not isinstance(k, str) for k in entry["options"]):
            raise ConfigError(join(path, "options"), show(entry["options"]), "option names that are strings")
        return entry


class SceneSpec(Spec):
    """A scene: the common keys and those of its ``source`` (:data:`SOURCE_KEYS`), its renderer scene
    name, ground-truth path and rig checked."""

    description = "a scene {name, source: render|shared-gt|gt|synthetic, ...}"

    def check(self, value, path):
        if not isinstance(value, dict):
            raise ConfigError(path, show(value), self.description)
        if "source" not in value:
            raise ConfigError(join(path, "source"), "nothing (missing key)", f"one of {', '.join(SCENE_SOURCES)}")
        source = COMMON_SCENE_KEYS["source"].check(value["source"], join(path, "source"))
        known = [*COMMON_SCENE_KEYS, *SOURCE_KEYS[source]]
        for key in value:
            if key not in known:
                others = [s for s in SCENE_SOURCES if key in SOURCE_KEYS[s]]
                hint = f"'{key}' is a key of {', '.join(others)} scenes, not of {source} ones." if others else None
                raise _unknown_key(path, key, known, hint)
        scene = SCENE_SPECS[source].check(value, path)  # checked; the value is kept as written (its cache key)
        scene = dict(value)
        if scene.get("rig") is not None:
            try:
                RigModel.from_spec(scene["rig"])
            except InputError as exc:
                raise ConfigError(join(join(path, "rig"), exc.argument), exc.received, exc.valid, exc.fix) from None
        if source == "render":
            _check_render_scene(scene, path)
        elif source in ("gt", "shared-gt"):
            _check_gt_path(scene, path)
        return scene


def _check_render_scene(scene: dict, path: str) -> None:
    """The renderer's scene name (``*``: every scene) when the renderer lists its scenes; ``prefix`` only with ``*``."""
    if scene.get("prefix") is not None and scene["scene"] != "*":
        raise ConfigError(join(path, "prefix"), show(scene["prefix"]), "no prefix (it names the scenes of scene: '*')",
                          "Remove 'prefix', or write scene: '*'.")
    if scene["scene"] == "*":
        return
    try:
        known = sorted(captures.rendered_scene_names())
    except captures.Unavailable:  # a renderer that cannot list its scenes: the case is skipped at run time
        return
    if known and scene["scene"] not in known:
        close = difflib.get_close_matches(scene["scene"], known, n=1)
        raise ConfigError(join(path, "scene"), show(scene["scene"]), f"one of the renderer's scenes {', '.join(known)} "
                          "or '*'", f"Did you mean {close[0]!r}?" if close else "List them with: capssim scenes.")


def _check_gt_path(scene: dict, path: str) -> None:
    """``gt``: the path (relative to the repository) exists. ``shared-gt``: it exists under the data root when
    the data root does (without it the scene is skipped at run time, as on CI without the shared data)."""
    if scene["source"] == "shared-gt":
        root = shared_data_dir()
        if root.is_dir() and not (root / scene["path"]).exists():
            raise ConfigError(join(path, "path"), show(scene["path"]), f"a ground truth under the data root {root}",
                              "Check the path (CAPSSIM_SHARED_DATA sets the data root).")
        return
    where = Path(scene["path"]).expanduser()
    where = where if where.is_absolute() else REPO_ROOT / where
    if not where.exists():
        raise ConfigError(join(path, "path"), show(scene["path"]), "a ground-truth folder or 12-channel TIFF "
                          f"(relative paths are read from {REPO_ROOT})", f"Nothing is at {where}; check the path.")


SUITE_SPEC = Mapping({
    "name": String(),
    "role": String(choices=list(SUITE_ROLES)),
    "description": String(),
    "convention": String(choices=list(CONVENTIONS)),
    "seeds": Sequence(Integer(minimum=0, maximum=MAX_SEED), min_length=1, what="seeds"),
    "noise": Sequence(NoiseSpec(), min_length=1, what="noise levels"),
    "methods": Sequence(MethodEntrySpec(), min_length=1, what="methods"),
    "scenes": Sequence(SceneSpec(), min_length=1, what="scenes"),
    "paired": String(),
    "uncertainty": Integer(minimum=2, maximum=64),
}, required=("methods", "scenes"),
   what="a suite (name, role, description, convention, seeds, noise, methods, scenes, paired, uncertainty)")


def _unique(values: list, path: str, key: str | None, what: str, fix: str) -> None:
    """Refuse the second of two equal ``values`` (the items of the list at ``path``; ``key``: their field)."""
    seen: dict = {}
    for i, value in enumerate(values):
        if value in seen:
            where = join(join(path, i), key) if key else join(path, i)
            raise ConfigError(where, f"{show(value)} again (as {join(path, seen[value])})", f"distinct {what}", fix)
        seen[value] = i


def check_suite(spec: dict) -> dict:
    """Validate a parsed suite (:data:`SUITE_SPEC`, duplicates, fallbacks) and return it normalised with its
    defaults; raises :class:`ConfigError` (without the file: :func:`load_suite` adds it)."""
    spec = SUITE_SPEC.check(spec, "")
    spec.setdefault("convention", "capssim")
    spec.setdefault("role", "development")
    spec.setdefault("seeds", [0])
    spec.setdefault("noise", [{"name": "clean", "noise": "none"}])
    _unique(spec["seeds"], "seeds", None, "seeds", "Remove the repeated seed (each seed is one noise draw).")
    _unique([n["name"] for n in spec["noise"]], "noise", "name", "noise level names",
            "Give each noise level its own name.")
    _unique([m["label"] for m in spec["methods"]], "methods", "label", "method labels",
            "Give each variant of a method its own label: {name: caps, label: caps-10it, options: {...}}.")
    for i, method in enumerate(spec["methods"]):
        _check_method_entry_options(method, join(join("methods", i), "options"))
        if spec.get("uncertainty") is not None:  # the suite's replicate count, unless the method names its own
            method.setdefault("uncertainty", spec["uncertainty"])
    labels = [m["label"] for m in spec["methods"]]
    if spec.get("paired") is not None and spec["paired"] not in labels:
        close = difflib.get_close_matches(str(spec["paired"]), labels, n=1)
        raise ConfigError("paired", show(spec["paired"]), f"a method label of this suite ({', '.join(labels)})",
                          f"Did you mean {close[0]!r}?" if close else "Name the method the report compares with "
                          "every other one, or remove 'paired'.")
    names = [s["name"] for s in spec["scenes"]]
    _unique(names, "scenes", "name", "scene names", "Give each scene its own name.")
    for i, scene in enumerate(spec["scenes"]):
        target = scene.get("fallback")
        if target is not None and (target not in names or target == scene["name"]):
            others = [n for n in names if n != scene["name"]]
            raise ConfigError(join(join("scenes", i), "fallback"), show(target),
                              f"another scene of this suite ({', '.join(others) or 'none'})")
    return spec


def _check_method_entry_options(method: dict, path: str) -> None:
    """A method entry's ``options`` parsed and checked by the method itself before the first case
    (:func:`capssim.reconstruct.option_probe.check_method_options`), so that a typo fails at load, not in every case."""
    options = dict(method.get("options") or {})
    if not options:
        return
    try:
        check_method_options(method["name"], options)
    except InputError as exc:
        if not str(exc.argument).startswith("option "):  # e.g. a weights file made by a training run later
            return
        raise ConfigError(path, f"{show(options)} ({exc.argument}: got {exc.received})", f"{exc.valid} "
                          f"(the options of method {method['name']!r})", exc.fix) from None
    except CapssimError as exc:
        raise ConfigError(path, show(options), f"options that method {method['name']!r} takes ({exc})") from None


#: the public name of the check (a design map's methods are checked alike, :mod:`capssim.eval.maps.spec`)
check_method_entry_options = _check_method_entry_options


def available_suites() -> list[str]:
    return available_specs(SUITES_DIR)


def suite_path(name_or_path: str | Path) -> Path:
    """The file of a suite name (``eval/suites/NAME.yaml``) or YAML path; :class:`UnknownNameError` otherwise."""
    return spec_path(name_or_path, folder=SUITES_DIR, noun="suite")


def load_suite(name_or_path: str | Path) -> dict:
    """Read and validate a suite (module docstring): every mistake is one :class:`ConfigError` line.

    Parameters
    ----------
    name_or_path : str or pathlib.Path
        A name in ``eval/suites`` or a path to a YAML file.

    Returns
    -------
    dict
        The suite with its defaults (``name``: the file's stem, ``convention`` capssim, ``seeds`` [0],
        ``noise`` clean), every method a mapping, and ``path`` and ``sha256`` of the file.
    """
    return load_spec_file(name_or_path, folder=SUITES_DIR, noun="suite", kind=KIND, example="eval/suites/quick.yaml",
                          check=check_suite, description=SUITE_SPEC.description)


def _scene_size(scene: dict) -> int | None:
    """The HR size a scene's capture has, when the suite says it (``size``, or ``crop`` of a ground truth)."""
    if scene["source"] in DEFAULT_SIZE:
        return int(scene.get("size", DEFAULT_SIZE[scene["source"]]))
    return None if scene.get("crop") is None else int(scene["crop"])


def check_scene_memory(spec: dict, scenes: list[dict]) -> None:
    """The resource guard of a run's ``scenes`` (and their fallbacks): refuse, before any work, a scene whose
    HR size needs more memory than the limit (:func:`capssim.runtime.resources.check_scene_size`, as ``bench
    reconstruct --size``). Ground truths without ``crop`` are sized when read."""
    entries = spec["scenes"]
    by_name = {s["name"]: i for i, s in enumerate(entries)}
    star = next((i for i, s in enumerate(entries) if s["source"] == "render" and s.get("scene") == "*"), None)
    wanted = {s["name"] for s in scenes} | {s["fallback"] for s in scenes if s.get("fallback")}
    seen = set()
    for name in wanted:
        index = by_name.get(name, star)
        if index is None or index in seen:
            continue
        seen.add(index)
        size = _scene_size(entries[index])
        if size is not None:
            key = "crop" if entries[index]["source"] in ("gt", "shared-gt") else "size"
            check_scene_size(f"suite {spec.get('path', spec['name'])}, key {join(join('scenes', index), key)!r}", size,
                             fix=f"Use a smaller {key}, or raise CAPSSIM_MEMORY_LIMIT_GB.")
