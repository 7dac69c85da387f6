"""The schema of a design-map spec (YAML), checked when the map is loaded, before any cell runs.

A map (``eval/maps/NAME.yaml`` or any YAML path) sweeps a grid of camera and scene conditions::

    name: phase-noise
    description: sub-pixel offsets against noise on a Siemens star
    scene: {name: star, source: synthetic, generator: star, size: 128}   # any suite scene entry
    methods: [caps-naive, dofp-igri2, dofp-eari]                           # suite method entries
    axes: {shift_max: [0, 0.25, 0.5, 1.0, 2.0], sigma: [0.0025, 0.005, 0.01, 0.02, 0.04]}
    fixed: {rotation_max: 0}                                               # optional: one value per key
    seeds: [0, 1, 2]

Every key of ``axes`` (a list of values) or ``fixed`` (one value) is one of :data:`AXES`: the options of
``capssim simulate`` without dashes (poses, noise model and sensor fields, PSF blur, extinction ratio), plus
``offset_px`` (the apertures at a regular sub-pixel pattern instead of random poses), ``registration_error_px``
(the true warps perturbed, :mod:`.cells`) and, for rendered scenes, ``depth_m`` (the scene's target depth: a planar
scene's own, a 3-D scene's through its ``scale``, :func:`depth_params`) and ``baseline_m`` (the array's baseline, 0-1 m, any rendered scene).
A mistake is one :class:`~capssim.files.schema.ConfigError` line naming the file, the key path (e.g.
``axes.sigma[2]``), what it got, what is valid and the fix, as for a suite file
(:mod:`capssim.eval.benchmarks.suite_schema`).
"""

from __future__ import annotations

import difflib
import itertools
from pathlib import Path

from capssim.camera.camera_setup import sensor_from_mapping
from capssim.errors import InputError
from capssim.files.schema import (
    AnyMapping,
    ConfigError,
    Integer,
    Mapping,
    Number,
    Sequence,
    Spec,
    String,
    join,
    show,
)
from capssim.render import get_scene

from ..benchmarks.spec_files import available_specs, load_spec_file, spec_path
from ..benchmarks.suite_schema import (
    _SENSOR_FIELDS,
    MAX_SEED,
    MethodEntrySpec,
    SceneSpec,
    check_method_entry_options,
)

MAPS_DIR = Path(__file__).resolve().parent
KIND = "design map"
NOISE_MODELS = tuple(_SENSOR_FIELDS)
#: the sensor fields an axis may sweep (those of the noise models; ``description`` is no condition)
SENSOR_AXES = tuple(dict.fromkeys(f for fields in _SENSOR_FIELDS.values() for f in fields if f != "description"))
#: axes that set the aperture poses of a simulated capture (a render's poses are its array's)
POSE_AXES = ("shift_max", "rotation_max", "scale_max", "offset_px")
#: the most cells x seeds x methods one map may plan (a bigger sweep is several maps)
MAX_RUNS = 20000

#: every axis: its value's check and what it means (units)
AXES: dict[str, tuple[Spec, str]] = {
    "shift_max": (Number(minimum=0, maximum=64), "largest random aperture offset, HR px (simulate --shift-max)"),
    "rotation_max": (Number(minimum=0, maximum=45), "largest random aperture rotation, degrees"),
    "scale_max": (Number(minimum=0, maximum=0.49), "largest random relative scale error"),
    "offset_px": (Number(minimum=0, maximum=64), "apertures 0-3 at (0,0), (d,0), (0,d), (d,d) HR px, no rotation "
                                                 "or scale error (1 = half a raw pixel)"),
    "noise": (String(choices=list(NOISE_MODELS)), "the sensor noise model"),
    **{name: (Number(minimum=0) if name != "preset" else String(), f"the sensor's {name} (simulate's sensor field)")
       for name in SENSOR_AXES},
    "psf_sigma_hr_px": (Number(minimum=0, maximum=16), "Gaussian optical PSF std, HR px"),
    "extinction_ratio": (Number(minimum=1, exclusive_minimum=True), "polarizer extinction ratio T_max/T_min"),
    "registration_error_px": (Number(minimum=0, maximum=16), "HR px by which each of apertures 1-3's true warp is "
                                                            "shifted, in a seeded random direction"),
    "depth_m": (Number(minimum=0.1, maximum=1000), "a rendered scene's target (or 3-D scene's reference) depth, "
                                                "metres (parallax)"),
    "baseline_m": (Number(minimum=0, maximum=1), "a rendered scene's array baseline, metres (parallax; render "
                                                 "--geometry baseline_m, default 0.04)"),
}
#: the axes only a rendered scene takes (they change the render, not the simulation)
RENDER_AXES = ("depth_m", "baseline_m")

MAP_SPEC = Mapping({
    "name": String(),
    "description": String(),
    "role": String(choices=["development"]),
    "convention": String(choices=["capssim"]),
    "scene": SceneSpec(),
    "methods": Sequence(MethodEntrySpec(), min_length=1, what="methods"),
    "axes": AnyMapping(f"axes (name: [values]) with names among {', '.join(AXES)}"),
    "fixed": AnyMapping("fixed conditions (name: value), the names of axes"),
    "seeds": Sequence(Integer(minimum=0, maximum=MAX_SEED), min_length=1, what="seeds"),
}, required=("scene", "methods", "axes"),
   what="a design map (name, description, scene, methods, axes, fixed, seeds)")


def _axis_name(name, path: str) -> str:
    if name not in AXES:
        close = difflib.get_close_matches(str(name), list(AXES), n=1)
        raise ConfigError(join(path, str(name)), "an unknown axis", f"one of {', '.join(AXES)}",
                          f"Did you mean {close[0]!r}?" if close else "capssim bench map --help lists them.")
    return str(name)


def _check_axes(spec: dict) -> tuple[dict, dict]:
    """``(axes, fixed)`` checked value by value: names, values, no repeat, no axis also fixed."""
    axes, fixed = {}, {}
    for name, values in (spec.get("axes") or {}).items():
        _axis_name(name, "axes")
        path = join("axes", name)
        if not isinstance(values, list) or not values:
            raise ConfigError(path, show(values), f"a non-empty list of values ({AXES[name][1]})",
                              f"For example {name}: [{show(values)}].")
        checked = [AXES[name][0].check(v, join(path, i)) for i, v in enumerate(values)]
        for i, value in enumerate(checked):
            if value in checked[:i]:
                raise ConfigError(join(path, i), f"{show(value)} again", "distinct values", "Remove the repeat.")
        axes[name] = checked
    if not axes:
        raise ConfigError("axes", "no axis", f"one or more axes among {', '.join(AXES)}",
                          "For example axes: {sigma: [0.005, 0.01, 0.02]}.")
    for name, value in (spec.get("fixed") or {}).items():
        _axis_name(name, "fixed")
        if name in axes:
            raise ConfigError(join("fixed", name), show(value), "a condition that is not also an axis",
                              f"Remove {name} from fixed or from axes.")
        fixed[name] = AXES[name][0].check(value, join("fixed", name))
    return axes, fixed


def _check_against_scene(axes: dict, fixed: dict, scene: dict) -> None:
    """Axes the scene's source cannot take: poses and extinction of a render, depth of a simulation, and
    ``offset_px`` with ``shift_max``."""
    names = {**{k: "axes" for k in axes}, **{k: "fixed" for k in fixed}}
    render = scene["source"] == "render"
    for name, where in names.items():
        if render and (name in POSE_AXES or name == "extinction_ratio"):
            raise ConfigError(join(where, name), f"{name} with a rendered scene", "the axes of a rendered scene: "
                              "noise, sensor fields, psf_sigma_hr_px, registration_error_px, depth_m, baseline_m",
                              "A render's poses are its array's; sweep them on a synthetic or ground-truth scene.")
        if name in RENDER_AXES and not render:
            raise ConfigError(join(where, name), f"{name} with a {scene['source']} scene",
                              f"{name} only with a rendered scene (source: render)",
                              "Use a render scene (e.g. scene: {source: render, scene: textured}), or drop the axis.")
    if "depth_m" in names and render:
        values = axes.get("depth_m") or [fixed["depth_m"]]
        _check_render_depth(scene, names["depth_m"], values)
    if "offset_px" in names and "shift_max" in names:
        raise ConfigError(join(names["offset_px"], "offset_px"), "offset_px with shift_max",
                          "one of offset_px (a regular pattern) or shift_max (random offsets)", "Drop one of them.")


def depth_params(scene_name: str, depth_m: float) -> dict | None:
    """The scene parameters that put render scene ``scene_name``'s target at ``depth_m``: its own ``depth_m``
    (the planar scenes), or, for a 3-D scene scaled about the array by ``scale`` (materials, window-reflection),
    the scale that moves its reference depth (``capssim scenes``' depth, at the default scale) to ``depth_m``
    (:func:`~capssim.render.scene_base.scale_scene`: the whole scene, so only the parallax changes); None when
    the scene takes neither."""
    info = get_scene(scene_name).info
    defaults = info.defaults or {}
    if "depth_m" in defaults:
        return {"depth_m": float(depth_m)}
    if "scale" in defaults and info.depth_m:
        return {"scale": float(defaults["scale"]) * float(depth_m) / float(info.depth_m)}
    return None


def _check_render_depth(scene: dict, where: str, values: list) -> None:
    """A rendered scene swept in ``depth_m`` must take it (:func:`depth_params`), at every value."""
    try:
        sc = get_scene(scene["scene"])
        params = [depth_params(scene["scene"], v) for v in values]
    except Exception:  # noqa: BLE001 - a renderer that cannot load the scene: the case is skipped at run time
        return
    if params[0] is None:
        raise ConfigError(join(where, "depth_m"), f"depth_m with the render scene {scene['scene']!r}",
                          "a render scene that takes depth_m or scale (the planar ones, materials, "
                          "window-reflection: capssim scenes)",
                          "Use e.g. scene: textured or window-reflection, or drop the axis.")
    for value, p in zip(values, params):
        try:
            sc.check_params({**(sc.info.defaults or {}), **(scene.get("scene_params") or {}), **p})
        except InputError as exc:
            raise ConfigError(join(where, "depth_m"), f"{value:g} ({exc.argument} {exc.received})", exc.valid,
                              f"Use depths the scene {scene['scene']!r} can take.") from None


def cell_noise(values: dict) -> dict:
    """The noise entry of a cell's conditions: ``noise`` if given, else gaussian with a ``sigma``, else none."""
    model = values.get("noise") or ("gaussian" if "sigma" in values else "none")
    fields = {k: values[k] for k in _SENSOR_FIELDS[model] if k in values}
    return {"name": "map", "noise": model, **fields}


def expand_cells(spec: dict) -> list[dict]:
    """The cells of a map in plan order (the product of the axes, the first axis slowest): each a dict of
    every axis value (``axes``) and the fixed conditions (``fixed``)."""
    names = list(spec["axes"])
    return [{"axes": dict(zip(names, combo)), "fixed": dict(spec.get("fixed") or {})}
            for combo in itertools.product(*(spec["axes"][n] for n in names))]


def _check_cells(spec: dict) -> None:
    """Each cell's sensor (its noise model takes its fields), and the map's size."""
    for cell in expand_cells(spec):
        values = {**cell["fixed"], **cell["axes"]}
        noise = cell_noise(values)
        stray = [k for k in values if k in SENSOR_AXES and k not in noise]
        if stray:
            where = "axes" if stray[0] in spec["axes"] else "fixed"
            raise ConfigError(join(where, stray[0]), f"{stray[0]} with noise {noise['noise']!r}",
                              f"the fields of noise {noise['noise']!r}: {', '.join(_SENSOR_FIELDS[noise['noise']])}",
                              "Set noise to the model that takes it (e.g. fixed: {noise: poisson-gaussian}).")
        try:
            sensor_from_mapping({k: v for k, v in noise.items() if k != "name"}, where="axes")
        except InputError as exc:
            raise ConfigError("axes", f"{show(values)} ({exc.argument}: {exc.received})", exc.valid, exc.fix) from None
    runs = len(expand_cells(spec)) * len(spec["seeds"]) * len(spec["methods"])
    if runs > MAX_RUNS:
        raise ConfigError("axes", f"{runs} runs (cells x seeds x methods)", f"at most {MAX_RUNS}",
                          "Split the sweep into several maps, or use fewer values, seeds or methods.")


def check_map(spec: dict) -> dict:
    """Validate a parsed map (module docstring) and return it with its defaults (``seeds`` [0], ``fixed`` {},
    ``convention`` capssim, ``role`` development); raises :class:`ConfigError` (:func:`load_map` adds the file)."""
    spec = MAP_SPEC.check(spec, "")
    spec["axes"], spec["fixed"] = _check_axes(spec)
    _check_against_scene(spec["axes"], spec["fixed"], spec["scene"])
    spec.setdefault("seeds", [0])
    spec.setdefault("convention", "capssim")
    spec.setdefault("role", "development")
    if len(set(spec["seeds"])) != len(spec["seeds"]):
        raise ConfigError("seeds", show(spec["seeds"]), "distinct seeds", "Remove the repeated seed.")
    labels = [m["label"] for m in spec["methods"]]
    for i, label in enumerate(labels):
        if label in labels[:i]:
            raise ConfigError(join(join("methods", i), "label"), f"{label!r} again", "distinct method labels",
                              "Give each variant its own label: {name: caps, label: caps-10it, options: {...}}.")
    for i, method in enumerate(spec["methods"]):
        check_method_entry_options(method, join(join("methods", i), "options"))
    _check_cells(spec)
    return spec


def available_maps() -> list[str]:
    """The map specs shipped in ``eval/maps``."""
    return available_specs(MAPS_DIR)


def map_path(name_or_path: str | Path) -> Path:
    """The file of a map name (``eval/maps/NAME.yaml``) or YAML path; :class:`UnknownNameError` otherwise."""
    return spec_path(name_or_path, folder=MAPS_DIR, noun="map")


def load_map(name_or_path: str | Path) -> dict:
    """Read and validate a map spec (module docstring): every mistake is one :class:`ConfigError` line.

    Returns the spec with its defaults, every method a mapping, ``name`` (default: the file's stem), and
    ``path`` and ``sha256`` of the file.
    """
    return load_spec_file(name_or_path, folder=MAPS_DIR, noun="map", kind=KIND, example="eval/maps/phase-noise.yaml",
                          check=check_map, description=MAP_SPEC.description)
