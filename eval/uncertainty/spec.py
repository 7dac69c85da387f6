"""The schema of an uncertainty-calibration spec (YAML, ``eval/uncertainty/NAME.yaml``), checked before any case runs.

::

    name: calibration
    role: development
    replicates: 8                      # the bootstrap's N
    seeds: [0]
    noise: [{name: gauss-0.01, noise: gaussian, sigma: 0.01}, ...]   # suite noise entries
    methods: [caps, caps-plus, ...]                                   # suite method entries
    calibration_scenes: [...]          # suite scene entries: the conformal scales are fitted on these
    check_scenes: [...]                # suite scene entries: coverage is measured on these (never fitted)
    options: {equivariant: false, warm_iterations: 4}                 # the bootstrap's options

Both scene lists hold development data only: the frozen test suite's scenes are refused.
"""

from __future__ import annotations

from pathlib import Path

from capssim.files.schema import Boolean, ConfigError, Integer, Mapping, Number, Sequence, String, join
from capssim.reconstruct.uncertainty.bootstrap import MAX_REGISTRATION_JITTER_HR_PX

from ..benchmarks.spec_files import load_spec_file
from ..benchmarks.suite_schema import MAX_SEED, MethodEntrySpec, NoiseSpec, SceneSpec, load_suite

__all__ = ["SPEC_DIR", "load_uncertainty_spec"]

SPEC_DIR = Path(__file__).resolve().parent

UNCERTAINTY_SPEC = Mapping({
    "name": String(),
    "description": String(),
    "role": String(choices=["development"]),
    "replicates": Integer(minimum=2, maximum=64),
    "seeds": Sequence(Integer(minimum=0, maximum=MAX_SEED), min_length=1, what="seeds"),
    "noise": Sequence(NoiseSpec(), min_length=1, what="noise levels"),
    "methods": Sequence(MethodEntrySpec(), min_length=1, what="methods"),
    "calibration_scenes": Sequence(SceneSpec(), min_length=1, what="calibration scenes"),
    "check_scenes": Sequence(SceneSpec(), min_length=1, what="check scenes"),
    "options": Mapping({"equivariant": Boolean(), "warm_iterations": Integer(minimum=1, maximum=100),
                        "registration_jitter_hr_px": Number(minimum=0, maximum=MAX_REGISTRATION_JITTER_HR_PX)},
                       what="bootstrap options (equivariant, warm_iterations, registration_jitter_hr_px)"),
}, required=("replicates", "noise", "methods", "calibration_scenes", "check_scenes"),
   what="an uncertainty calibration (replicates, seeds, noise, methods, calibration_scenes, check_scenes, options)")


def _test_scene_sources() -> set[str]:
    """The ground-truth paths and render scenes of the frozen test suite (never calibrated or checked on)."""
    try:
        test = load_suite("test")
    except Exception:  # noqa: BLE001 - no test suite shipped: nothing to keep apart
        return set()
    return {str(s.get("path") or f"render:{s.get('scene')}:{s.get('scene_params')}") for s in test["scenes"]}


def _check(spec: dict) -> dict:
    spec = UNCERTAINTY_SPEC.check(spec, "")
    spec.setdefault("seeds", [0])
    spec.setdefault("options", {})
    seen: set[str] = set()
    for i, method in enumerate(spec["methods"]):
        if method["name"] in seen:
            raise ConfigError(join("methods", i), f"the method {method['name']!r} again", "each method once (the "
                              "calibration has one entry per method name)", "Remove the repeat.")
        seen.add(method["name"])
    test = _test_scene_sources()
    names: set[str] = set()
    for key in ("calibration_scenes", "check_scenes"):
        for i, scene in enumerate(spec[key]):
            where = join(key, i)
            source = str(scene.get("path") or f"render:{scene.get('scene')}:{scene.get('scene_params')}")
            if source in test:
                raise ConfigError(where, f"{scene['name']} ({source})", "a development scene (not in the frozen "
                                  "test suite eval/suites/test.yaml)", "Calibrate and check on development data only.")
            if scene["name"] in names:
                raise ConfigError(where, f"the scene name {scene['name']!r} again", "distinct scene names over "
                                  "calibration_scenes and check_scenes", "A scene is either fitted on or checked on.")
            names.add(scene["name"])
    return spec


def load_uncertainty_spec(name_or_path: str | Path) -> dict:
    """An uncertainty-calibration spec by name (``eval/uncertainty/NAME.yaml``) or path, validated."""
    return load_spec_file(name_or_path, folder=SPEC_DIR, noun="uncertainty calibration", kind="uncertainty spec",
                          example="eval/uncertainty/calibration.yaml", check=_check,
                          description=UNCERTAINTY_SPEC.description)
