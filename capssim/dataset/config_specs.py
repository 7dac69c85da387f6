"""The schema of a dataset config (YAML): what each key may hold (docs: guides/datasets.md).

:mod:`capssim.dataset.config` reads a config against :data:`TOP_SPEC` and the source specs. The
camera set-up keys (:data:`SETUP_KEYS_IN_DATASETS`) are spelled as
:class:`capssim.camera.camera_setup.CameraSetup` spells them; ``pose`` (the random aperture errors of
ground-truth sources) is the dataset's own.
"""

from __future__ import annotations

from capssim.camera.camera_setup import SETUP_KEYS
from capssim.camera.sensor import NOISE_MODELS, SENSOR_PRESETS
from capssim.conventions import dofp_layout, dofp_layout_name
from capssim.dataset.distributions import Distribution
from capssim.files.schema import (
    AnyMapping,
    Anything,
    Boolean,
    Custom,
    Integer,
    Mapping,
    Nullable,
    Number,
    Sequence,
    String,
)

MIN_SIZE = 16
SIZE_MULTIPLE = 4
DEFAULT_SCENE_SIZE = 64
#: the camera set-up keys a dataset config takes (:data:`capssim.camera.camera_setup.SETUP_KEYS`)
SETUP_KEYS_IN_DATASETS = tuple(k for k in SETUP_KEYS if k not in ("psf", "seed_rule"))
#: keys a source may take over from ``defaults``
SHARED_KEYS = (*SETUP_KEYS_IN_DATASETS, "pose")
#: shared keys that only ground-truth sources use (render draws its own aperture errors from geometry_params)
GT_ONLY_KEYS = ("pose",)
#: the photometric augmentations of a ground-truth source (:func:`capssim.dataset.augment.scale_colours`); a
#: sample records them only when its source sets them, so configs without them keep their fingerprints
COLOUR_AUGMENTS = ("gain_red", "gain_blue", "exposure")
#: set-up keys a rendered-scene sample takes only when the config sets them (else the set-up's default)
RENDER_OPTICS_KEYS = ("psf_sigma_hr_px", "extinction_ratio")


def _dofp(value):
    """A DoFP layout name or 2x2 cell -> its canonical name (``sony``, ``0-45-135-90``, ...)."""
    return dofp_layout_name(dofp_layout(value))


def _size_spec(nullable: bool):
    inner = Integer(minimum=MIN_SIZE, multiple_of=SIZE_MULTIPLE)
    return Distribution(Nullable(inner) if nullable else inner)


SENSOR_SPEC = Mapping({
    "noise": Distribution(String(choices=list(NOISE_MODELS))),
    "sigma": Distribution(Number(minimum=0, maximum=1)),
    "preset": Distribution(String(choices=list(SENSOR_PRESETS))),
    "exposure": Distribution(Number(minimum=0, exclusive_minimum=True)),
    "bit_depth": Distribution(Integer(minimum=8, maximum=16)),
}, what="a sensor description (noise, sigma, preset, exposure, bit_depth)")

POSE_SPEC = Mapping({
    "shift_max_px": Distribution(Number(minimum=0)),
    "rotation_max_deg": Distribution(Number(minimum=0, maximum=45)),
    "scale_max": Distribution(Number(minimum=0, maximum=0.5)),
}, what="aperture pose error ranges (shift_max_px, rotation_max_deg, scale_max)")

_ER = Distribution(Number(minimum=1, exclusive_minimum=True))
#: an imperfect array (capssim.camera.rig.RigModel): a preset's draw, then per-quantity overrides (lists as in the CLI)
RIG_SPEC = Mapping({
    "preset": Distribution(String(choices=["ideal", "realistic"])),
    "seed": Distribution(Integer(minimum=0)),
    "angle_offsets_deg": Sequence(Distribution(Number(minimum=-20, maximum=20)), lengths=(4,), what="degrees"),
    "extinction_ratio": Sequence(_ER, lengths=(1, 3, 12), what="extinction ratios (all, R G B, or 4 x R G B)",
                                 bare=_ER),
    "gain": Sequence(Distribution(Number(minimum=1e-3, maximum=1e3)), lengths=(4,), what="gains (1 = nominal)"),
    "vignetting_corner": Distribution(Number(minimum=0, maximum=0.9)),
    "psf_sigmas_hr_px": Sequence(Distribution(Number(minimum=0)), lengths=(4,), what="Gaussian PSF stds (HR px)"),
}, what="an imperfect array (preset, seed, angle_offsets_deg, extinction_ratio, gain, vignetting_corner, "
        "psf_sigmas_hr_px)")

SHARED_SPECS = {
    "sensor": SENSOR_SPEC,
    "dofp_layout": Distribution(Custom(_dofp, "a DoFP layout")),
    "pose": POSE_SPEC,
    "psf_sigma_hr_px": Distribution(Number(minimum=0)),
    "extinction_ratio": Distribution(Nullable(Number(minimum=1, exclusive_minimum=True))),
    "rig": RIG_SPEC,
}

GT_SOURCE_SPEC = Mapping({
    "gt": String(),
    "name": String(),
    "weight": Number(minimum=0),
    "size": _size_spec(nullable=True),
    "crop_position": Distribution(String(choices=["center", "random"])),
    "augment": Mapping({"rot90": Distribution(Integer(minimum=0, maximum=3)), "flip": Distribution(Boolean()),
                        **{name: Distribution(Number(minimum=0.1, maximum=10)) for name in COLOUR_AUGMENTS}},
                       what="augmentations (rot90: quarter turns 0..3, flip: true/false; gain_red, gain_blue, "
                            "exposure: multipliers 0.1..10, the exposure capped so that no value exceeds 1)"),
    **SHARED_SPECS,
}, required=("gt",), what="a ground-truth source")

SCENE_SOURCE_SPEC = Mapping({
    "scene": String(),
    "name": String(),
    "weight": Number(minimum=0),
    "size": _size_spec(nullable=False),
    "spp": Distribution(Nullable(Integer(minimum=1))),
    "variant": String(),
    "target_noise": Distribution(Nullable(Number(minimum=0, exclusive_minimum=True, maximum=1))),
    "scene_params": Mapping(extra=Distribution(Anything()), what="scene parameters (name: value or distribution)"),
    "geometry_params": Mapping(extra=Distribution(Anything()), what="geometry parameters (name: value or distribution)"),
    **{k: v for k, v in SHARED_SPECS.items() if k not in GT_ONLY_KEYS},
}, required=("scene",), what="a rendered-scene source")

TOP_SPEC = Mapping({
    "name": String(),
    "seed": Integer(minimum=0),
    "samples": Integer(minimum=1),
    "selection": String(choices=["cycle", "random"]),
    "defaults": Mapping(SHARED_SPECS, what="default parameters (sensor, dofp_layout, pose, psf_sigma_hr_px, extinction_ratio, rig)"),
    "sources": Sequence(AnyMapping("a source (gt: FOLDER or scene: NAME)"), min_length=1, what="sources"),
}, required=("seed", "samples", "sources"), what="a dataset config")
