"""The training configuration of ``capssim train`` (a YAML file), parsed and checked in full before any work.

::

    name: cpdnet-small
    seed: 0
    model: {network: cpdnet, features: 24}       # NETWORKS or jcpd-dictionary; other keys: its options
    input: dofp                                  # dofp (DoFP mosaic) | aperture (demosaicked LR images)
                                                 # | noisy-gt (denoiser: ground truth + white noise)
                                                 # | gt-patches (jcpd-dictionary)
    data:
      dataset: dataset-train-textures.yaml       # a capssim dataset config, relative to this file
      root: runs/datasets/train                  # where it is generated or read (relative to the working dir)
      validation: 8                              # the last N samples are held out for validation
      crop: 64                                   # crop side in input pixels (dofp: a multiple of 4)
      batch: 8
    loss: {intermediate_weight: 0.5, stokes_weight: 0.5}   # cpdnet's multitask weights; aperture: masked L1; noisy-gt: MSE
    optimizer: {name: adam, lr: 0.001, weight_decay: 0}   # clip_grad_norm: N bounds the gradient's norm
    schedule: {steps: 2000, warmup: 50, decay: cosine, final_lr_fraction: 0.05}
    validate_every: 250
    checkpoint_every: 50

Every key has a default except ``model.network``, ``input`` and ``data.dataset``. The file is checked
on load against :data:`TOP_SPEC` and the model's :data:`MODEL_SPECS` (``capssim.files.schema``: unknown keys
with a "Did you mean" hint, types, ranges), then the memory of the model's weights; ``capssim train``
adds the batch's activations when it trains on the CPU (:func:`check_model_memory`). A mistake is a
one-line :class:`~capssim.files.schema.ConfigError` naming the file and the key.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

from capssim.errors import InputError, UnknownNameError
from capssim.files.schema import (
    AnyMapping,
    Boolean,
    ConfigError,
    Custom,
    Integer,
    Mapping,
    Nullable,
    Number,
    Sequence,
    String,
    load_yaml_file,
    validate,
)
from capssim.runtime.resources import MEMORY_LIMIT_ENV, check_memory

from ..networks import NETWORKS
from .pairs import INPUT_KINDS, MOSAIC_INPUT_KINDS

OPTIMIZERS = ("adam", "adamw", "sgd")
DECAYS = ("cosine", "constant", "step")
LOSS_KEYS = {"dofp": ("intermediate_weight", "stokes_weight"), "dofp-igri2": ("stokes_weight",), "aperture": (),
             "noisy-gt": (), "gt-patches": ()}
#: the dictionary of dofp-jcpd, learned from ground-truth patches (schedule.steps: MOD iterations)
DICTIONARY_MODEL, DICTIONARY_INPUT = "jcpd-dictionary", "gt-patches"
DICTIONARY_DEFAULTS = {"patch": 8, "atoms": 256, "sparsity": 8, "patches": 8000}
#: every trainable model and the input it reads
MODEL_INPUTS = {**{name: cls.input_kind for name, cls in NETWORKS.items()}, DICTIONARY_MODEL: DICTIONARY_INPUT}
TOP_KEYS = ("name", "seed", "model", "input", "data", "loss", "optimizer", "schedule", "validate_every",
            "checkpoint_every")
KIND = "training config"
EXAMPLE = "examples/train-cpdnet-small.yaml"


def _name(value) -> str:
    if isinstance(value, bool) or not isinstance(value, (str, int, float)) or not str(value):
        raise InputError("name", value, "a non-empty name")
    return str(value)


_WEIGHT = Number(minimum=0, maximum=100)
#: the schema of a training config (checked on load, before any work); ``model`` has its own per network
TOP_SPEC = Mapping({
    "name": Custom(_name, "a non-empty name"),
    "seed": Integer(minimum=0, maximum=2**63 - 1),
    "model": AnyMapping("a model description (network: NAME and its options)"),
    "input": String(choices=[*INPUT_KINDS, DICTIONARY_INPUT]),
    "data": Mapping({"dataset": String(), "root": Nullable(String()), "validation": Integer(minimum=1, maximum=10**9),
                     "crop": Integer(minimum=8, maximum=1024), "batch": Integer(minimum=1, maximum=4096)},
                    required=("dataset",), what="the training data (dataset, root, validation, crop, batch)"),
    "loss": Mapping({"intermediate_weight": _WEIGHT, "stokes_weight": _WEIGHT},
                    what="loss weights (intermediate_weight, stokes_weight)"),
    "optimizer": Mapping({"name": String(choices=list(OPTIMIZERS)),
                          "lr": Number(minimum=0, exclusive_minimum=True, maximum=10),
                          "weight_decay": Number(minimum=0, maximum=10), "momentum": Number(minimum=0, maximum=10),
                          "clip_grad_norm": Number(minimum=0, exclusive_minimum=True, maximum=1e6)},
                         what="an optimizer (name, lr, weight_decay, momentum, clip_grad_norm)"),
    "schedule": Mapping({"steps": Integer(minimum=1, maximum=10**8), "warmup": Integer(minimum=0, maximum=10**8),
                         "decay": String(choices=list(DECAYS)), "final_lr_fraction": Number(minimum=0, maximum=1),
                         "milestones": Sequence(Integer(minimum=1, maximum=10**8), what="step numbers"),
                         "gamma": Number(minimum=0, exclusive_minimum=True, maximum=1)},
                        what="a schedule (steps, warmup, decay, final_lr_fraction, milestones, gamma)"),
    "validate_every": Integer(minimum=1, maximum=10**8),
    "checkpoint_every": Integer(minimum=1, maximum=10**8),
}, required=("model", "input", "data"), what="a training config (model, input, data, ...)")

_NETWORK = String(choices=list(MODEL_INPUTS))
#: dofp-nafnet's blocks per U-Net level, top level first
_LEVEL_BLOCKS = Sequence(Integer(minimum=0, maximum=64), what="block counts (top level first)", lengths=(3,))
#: per model: the keys of ``model`` (sizes have no upper bound here: the memory estimate refuses what cannot fit)
MODEL_SPECS = {
    "cpdnet": Mapping({"network": _NETWORK, "features": Integer(minimum=1), "colour_blocks": Integer(minimum=0),
                       "polarization_blocks": Integer(minimum=0)},
                      what="a cpdnet model (network, features, colour_blocks, polarization_blocks)"),
    "dofp-nafnet": Mapping({"network": _NETWORK, "width": Integer(minimum=1), "encoder_blocks": _LEVEL_BLOCKS,
                            "middle_blocks": Integer(minimum=0, maximum=64), "decoder_blocks": _LEVEL_BLOCKS},
                           what="a dofp-nafnet model (network, width, encoder_blocks, middle_blocks, decoder_blocks)"),
    "edsr": Mapping({"network": _NETWORK, "channels": Integer(minimum=1, maximum=64), "features": Integer(minimum=1),
                     "blocks": Integer(minimum=0), "residual_scale": Number(minimum=0, maximum=10),
                     "bicubic_skip": Boolean()},
                    what="an edsr model (network, channels, features, blocks, residual_scale, bicubic_skip)"),
    "denoiser": Mapping({"network": _NETWORK, "channels": Integer(minimum=1, maximum=64), "features": Integer(minimum=1),
                         "depth": Integer(minimum=2, maximum=64)},
                        what="a denoiser model (network, channels, features, depth)"),
    DICTIONARY_MODEL: Mapping({"network": _NETWORK, "patch": Integer(minimum=4, maximum=16, multiple_of=2),
                               "atoms": Integer(minimum=1, maximum=4096), "sparsity": Integer(minimum=1, maximum=64),
                               "patches": Integer(minimum=1, maximum=10**6)},
                              what="a jcpd-dictionary model (network, patch, atoms, sparsity, patches)"),
}
#: the channels of each input's images (a network's ``channels`` must match: the pairs have no other count)
INPUT_CHANNELS = {"aperture": 3, "noisy-gt": 12}
INPUT_CHANNEL_NAMES = {"aperture": "one aperture's demosaicked RGB", "noisy-gt": "RGB x 4 polarizer angles"}
#: the constructor defaults of each network, for the memory estimate (the config keeps only what it sets), read
#: from the constructors themselves
NETWORK_DEFAULTS = {name: {key: parameter.default for key, parameter in inspect.signature(cls).parameters.items()
                           if parameter.default is not inspect.Parameter.empty}
                    for name, cls in NETWORKS.items()}


class UnknownConfigName(ConfigError, UnknownNameError):
    """An unknown key or name in a training config: a :class:`ConfigError` (file, key, Did you mean) that is
    also an :class:`UnknownNameError`."""

    def __init__(self, exc: ConfigError):
        self.key_path, self.config_file, self.kind = exc.key_path, exc.config_file, exc.kind
        self.argument, self.received, self.valid, self.fix = exc.argument, exc.received, exc.valid, exc.fix
        self.name, self.known = exc.key_path, []
        Exception.__init__(self, str(exc))


@dataclass
class TrainConfig:
    name: str
    seed: int
    network: str
    network_params: dict
    input: str
    dataset_config: Path
    dataset_root: Path
    validation: int = 8
    crop: int = 64
    batch: int = 8
    loss: dict = field(default_factory=dict)
    optimizer: dict = field(default_factory=lambda: {"name": "adam", "lr": 1e-3, "weight_decay": 0.0})
    schedule: dict = field(default_factory=lambda: {"steps": 2000, "warmup": 50, "decay": "cosine",
                                                    "final_lr_fraction": 0.05})
    validate_every: int = 250
    checkpoint_every: int = 50
    source: str = ""

    def to_dict(self) -> dict:
        d = asdict(self)
        d["dataset_config"], d["dataset_root"] = str(self.dataset_config), str(self.dataset_root)
        return d

    def fingerprint(self) -> str:
        """A hash of everything that changes the result (not the file's path or the checkpoint cadence)."""
        d = self.to_dict()
        for key in ("source", "checkpoint_every", "dataset_root"):
            d.pop(key)
        d["dataset_config"] = hashlib.sha256(self.dataset_config.read_bytes()).hexdigest()
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def load_train_config(path) -> TrainConfig:
    """Parse and check the training config at ``path`` (a ConfigError names the file and the first bad key)."""
    path = Path(path)
    raw = load_yaml_file(path, kind=KIND, example=EXAMPLE)
    return parse_train_config(raw, base_dir=path.parent, source=str(path))


def _fail(key: str, received, valid: str, fix: str | None = None):
    raise ConfigError(key, received, valid, fix)


def _model(raw: dict) -> tuple[str, dict, str]:
    """``(network, its options, input kind)`` of the checked ``model`` and ``input``."""
    model = dict(raw["model"])
    network = _NETWORK.check(model.get("network"), "model.network")
    model = MODEL_SPECS[network].check(model, "model")
    model.pop("network")
    kind = raw["input"]
    if MODEL_INPUTS[network] != kind:
        _fail("input", repr(kind), f"{MODEL_INPUTS[network]} for the {network} model")
    channels = INPUT_CHANNELS.get(kind)
    if "channels" in model and channels is not None and model["channels"] != channels:
        _fail("model.channels", model["channels"], f"{channels} (the {kind} input's images have {channels} channels: "
              f"{INPUT_CHANNEL_NAMES[kind]})", f"Remove model.channels, or write channels: {channels}.")
    if network == DICTIONARY_MODEL:
        model = {**DICTIONARY_DEFAULTS, **model}
        if model["patches"] < model["atoms"]:
            _fail("model.patches", model["patches"], f"at least as many patches as atoms ({model['atoms']})")
    return network, model, kind


def _data(raw: dict, base_dir: Path, kind: str) -> dict:
    data = raw["data"]
    dataset = (base_dir / data["dataset"]).resolve()
    if not dataset.is_file():
        _fail("data.dataset", repr(data["dataset"]), f"an existing dataset config (looked at {dataset})",
              "Give the path relative to the training config.")
    crop = data.get("crop", 64)
    if kind in MOSAIC_INPUT_KINDS and crop % 4:
        _fail("data.crop", crop, "a multiple of 4 for DoFP input (the mosaic period)", f"Try crop: {crop - crop % 4}.")
    return {"dataset_config": dataset, "dataset_root": Path(data.get("root") or f"runs/datasets/{dataset.stem}"),
            "validation": data.get("validation", 8), "crop": crop, "batch": data.get("batch", 8)}


def _optimization(raw: dict, kind: str) -> dict:
    loss = raw.get("loss") or {}
    for key in loss:
        if key not in LOSS_KEYS[kind]:
            valid = ", ".join(LOSS_KEYS[kind]) or "no loss keys"
            raise UnknownConfigName(ConfigError(f"loss.{key}", "an unknown key", f"{valid} for input {kind}"))
    opt = {"name": "adam", "lr": 1e-3, "weight_decay": 0.0, **(raw.get("optimizer") or {})}
    sched = {"steps": 2000, "decay": "cosine", "final_lr_fraction": 0.05, "milestones": [], "gamma": 0.5,
             **(raw.get("schedule") or {})}
    sched.setdefault("warmup", min(50, sched["steps"]))
    if sched["warmup"] > sched["steps"]:
        _fail("schedule.warmup", sched["warmup"], f"at most schedule.steps ({sched['steps']})")
    late = [m for m in sched["milestones"] if m > sched["steps"]]
    if late:
        _fail("schedule.milestones", late[0], f"step numbers in [1, {sched['steps']}] (schedule.steps)")
    return {"loss": loss, "optimizer": opt, "schedule": sched}


def model_memory_bytes(network: str, params: dict, *, batch: int, crop: int, activations: bool = True) -> float:
    """Training working set of ``network`` in bytes: float32 weights x 4 (weights, gradients, two Adam moments)
    plus, with ``activations``, the maps a batch of ``crop`` crops keeps for the backward pass (4 per block)."""
    p = {**NETWORK_DEFAULTS.get(network, {}), **params}
    if network == DICTIONARY_MODEL:
        return 8.0 * 4 * p["patches"] * (12 * p["patch"] ** 2 + p["atoms"])
    f = p.get("features", 0)
    if network == "cpdnet":
        weights = 9 * f * (9 + 3 + 8 + 4) + 18 * f * f * (p["colour_blocks"] + p["polarization_blocks"])
        maps = batch * crop ** 2 * f * (4 * (4 * p["colour_blocks"] + 3) + 3 * (4 * p["polarization_blocks"] + 3))
    elif network == "dofp-nafnet":  # a block of width c: about 7 c^2 weights and 12 c maps per pixel of its level
        w, enc, dec = p["width"], list(p["encoder_blocks"]), list(p["decoder_blocks"])
        counts = [e + d for e, d in zip(enc, dec)] + [p["middle_blocks"]]
        weights = 9 * 100 * w + 9 * w * 48 + sum(7 * (w * 2 ** level) ** 2 * n for level, n in enumerate(counts))
        maps = batch * sum(12 * w * 2 ** level * (crop / 2 ** (level + 1)) ** 2 * max(n, 1)
                           for level, n in enumerate(counts)) + batch * crop ** 2 * 100
    elif network == "denoiser":
        weights = 9 * f * (2 * p["channels"] + 1) + 9 * f * f * (p["depth"] - 2)
        maps = batch * crop ** 2 * (2 * f * (p["depth"] - 1) + 3 * p["channels"])
    else:
        weights = 18 * f * p["channels"] + 9 * f * f * (2 * p["blocks"] + 1 + 4)
        maps = batch * crop ** 2 * f * (4 * p["blocks"] + 3 + 4 * 4 + 4)
    return 4.0 * (4 * weights + (maps if activations else 0))


def check_model_memory(config: TrainConfig, *, activations: bool = True) -> None:
    """Refuse (:class:`~capssim.errors.ResourceError`, naming the file and ``model``) a model whose training
    working set (:func:`model_memory_bytes`) passes the memory limit, before building it. The network is built
    on the host; ``activations=False`` (training on a GPU) leaves the batch's maps out of the host estimate."""
    estimate = model_memory_bytes(config.network, config.network_params, batch=config.batch, crop=config.crop,
                                  activations=activations)
    sizes = ", ".join(f"{k}: {v}" for k, v in config.network_params.items())
    check_memory(f"{KIND} {config.source}, key 'model'" if config.source else f"{KIND}, key 'model'", estimate,
                 what=f"training {config.network} ({sizes}{', ' if sizes else ''}batch {config.batch}, crop "
                      f"{config.crop}{'' if activations else ', weights only'})",
                 fix=f"Lower the model's sizes, data.batch or data.crop, or raise {MEMORY_LIMIT_ENV}.")


def parse_train_config(raw, *, base_dir: Path = Path("."), source: str = "") -> TrainConfig:
    """Check ``raw`` (a parsed YAML file) against :data:`TOP_SPEC` and the model's spec, then the memory of the
    model's weights (:func:`check_model_memory`); a ConfigError names ``source`` and the key."""
    where = source or None
    try:
        raw = validate(TOP_SPEC, raw, config_file=where, kind=KIND)
        network, params, kind = _model(raw)
        parsed = {**_data(raw, Path(base_dir), kind), **_optimization(raw, kind)}
    except ConfigError as exc:
        error = ConfigError(exc.key_path, exc.received, exc.valid, exc.fix, config_file=where, kind=KIND)
        if exc.received == "an unknown key" or str(exc.valid).startswith("one of "):
            raise UnknownConfigName(error) from None
        raise error from None
    config = TrainConfig(name=str(raw.get("name") or network), seed=raw.get("seed", 0), network=network,
                         network_params=params, input=kind, **parsed, source=source,
                         validate_every=raw.get("validate_every", 250), checkpoint_every=raw.get("checkpoint_every", 50))
    check_model_memory(config, activations=False)  # the weights, whatever the device; the CLI adds the rest
    return config


def learning_rate(config: TrainConfig, step: int) -> float:
    """The learning rate at ``step`` (0-based): linear warm-up, then the decay of ``schedule``."""
    s, base = config.schedule, config.optimizer["lr"]
    if step < s["warmup"]:
        return base * (step + 1) / s["warmup"]
    if s["decay"] == "constant":
        return base
    if s["decay"] == "step":
        return base * s["gamma"] ** sum(step >= m for m in s["milestones"])
    t = (step - s["warmup"]) / max(1, s["steps"] - s["warmup"])
    floor = s["final_lr_fraction"]
    return base * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t)))
