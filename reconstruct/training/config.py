"""The training configuration of ``capssim train`` (a YAML file), parsed and checked in full before any work.

::

    name: cpdnet-small
    seed: 0
    model: {network: cpdnet, features: 24}       # NETWORKS or jcpd-dictionary; other keys: its options
    input: dofp                                  # dofp (DoFP mosaic) | aperture (demosaicked LR images)
                                                 # | gt-patches (jcpd-dictionary)
    data:
      dataset: dataset-train-textures.yaml       # a capssim dataset config, relative to this file
      root: runs/datasets/train                  # where it is generated or read (relative to the working dir)
      validation: 8                              # the last N samples are held out for validation
      crop: 64                                   # crop side in input pixels (dofp: a multiple of 4)
      batch: 8
    loss: {intermediate_weight: 0.5, stokes_weight: 0.5}   # cpdnet's multitask weights; aperture: masked L1
    optimizer: {name: adam, lr: 0.001, weight_decay: 0}
    schedule: {steps: 2000, warmup: 50, decay: cosine, final_lr_fraction: 0.05}
    validate_every: 250
    checkpoint_every: 50

Every key has a default except ``model.network``, ``input`` and ``data.dataset``.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import yaml

from capssim.errors import InputError, UnknownNameError

from ..networks import NETWORKS
from .pairs import INPUT_KINDS

OPTIMIZERS = ("adam", "adamw", "sgd")
DECAYS = ("cosine", "constant", "step")
LOSS_KEYS = {"dofp": ("intermediate_weight", "stokes_weight"), "aperture": (), "gt-patches": ()}
#: the dictionary of dofp-jcpd, learned from ground-truth patches (schedule.steps: MOD iterations)
DICTIONARY_MODEL, DICTIONARY_INPUT = "jcpd-dictionary", "gt-patches"
DICTIONARY_DEFAULTS = {"patch": 8, "atoms": 256, "sparsity": 8, "patches": 8000}
#: every trainable model and the input it reads
MODEL_INPUTS = {**{name: cls.input_kind for name, cls in NETWORKS.items()}, DICTIONARY_MODEL: DICTIONARY_INPUT}
TOP_KEYS = ("name", "seed", "model", "input", "data", "loss", "optimizer", "schedule", "validate_every",
            "checkpoint_every")


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


def _mapping(raw, key: str) -> dict:
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise InputError(key, raw, "a mapping (key: value)")
    return dict(raw)


def _integer(raw, key: str, low: int, high: int = 10**9) -> int:
    if isinstance(raw, bool) or not isinstance(raw, int) or not low <= raw <= high:
        raise InputError(key, raw, f"an integer in [{low}, {high}]")
    return raw


def _number(raw, key: str, low: float, high: float = math.inf, *, low_open: bool = False) -> float:
    ok = isinstance(raw, (int, float)) and not isinstance(raw, bool) and math.isfinite(raw)
    if not ok or raw < low or (low_open and raw == low) or raw > high:
        raise InputError(key, raw, f"a finite number in {'(' if low_open else '['}{low:g}, {high:g}]")
    return float(raw)


def _reject_unknown(d: dict, known, where: str) -> None:
    for key in d:
        if key not in known:
            raise UnknownNameError(f"key of {where}", str(key), list(known))


def load_train_config(path) -> TrainConfig:
    """Parse and check the training config at ``path`` (an InputError names the first bad key)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("CONFIG", str(path), "a training config YAML file",
                         "See examples/train-cpdnet-small.yaml.")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise InputError("CONFIG", str(path), "valid YAML", str(exc).splitlines()[0]) from None
    return parse_train_config(raw, base_dir=path.parent, source=str(path))


def _parse_model(raw: dict) -> tuple[str, dict, str]:
    model = _mapping(raw.get("model"), "model")
    network = model.pop("network", None)
    if network not in MODEL_INPUTS:
        raise UnknownNameError("model.network", str(network), list(MODEL_INPUTS))
    kind = raw.get("input")
    if kind not in (*INPUT_KINDS, DICTIONARY_INPUT):
        raise InputError("input", kind, " or ".join((*INPUT_KINDS, DICTIONARY_INPUT)))
    if MODEL_INPUTS[network] != kind:
        raise InputError("input", kind, f"{MODEL_INPUTS[network]} for the {network} model")
    if network == DICTIONARY_MODEL:
        _reject_unknown(model, DICTIONARY_DEFAULTS, "model (jcpd-dictionary)")
        model = {**DICTIONARY_DEFAULTS, **model}
        for key, (low, high) in {"patch": (4, 16), "atoms": (1, 4096), "sparsity": (1, 64),
                                 "patches": (1, 10**6)}.items():
            _integer(model[key], f"model.{key}", low, high)
        if model["patch"] % 2 or model["patches"] < model["atoms"]:
            raise InputError("model", model, "an even patch and at least as many patches as atoms")
    for key, value in model.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"model.{key}", value, "a number or true/false")
    return network, model, kind


def _parse_data(raw: dict, base_dir: Path, kind: str) -> dict:
    data = _mapping(raw.get("data"), "data")
    _reject_unknown(data, ("dataset", "root", "validation", "crop", "batch"), "data")
    if not data.get("dataset"):
        raise InputError("data.dataset", None, "a capssim dataset config (YAML), relative to the training config")
    dataset = (base_dir / str(data["dataset"])).resolve()
    if not dataset.is_file():
        raise InputError("data.dataset", str(data["dataset"]), f"an existing dataset config (looked at {dataset})")
    crop = _integer(data.get("crop", 64), "data.crop", 8, 1024)
    if kind == "dofp" and crop % 4:
        raise InputError("data.crop", crop, "a multiple of 4 for DoFP input (the mosaic period)",
                         f"Try crop: {crop - crop % 4}.")
    return {"dataset_config": dataset, "dataset_root": Path(str(data.get("root") or f"runs/datasets/{dataset.stem}")),
            "validation": _integer(data.get("validation", 8), "data.validation", 1),
            "crop": crop, "batch": _integer(data.get("batch", 8), "data.batch", 1, 4096)}


def _parse_optimization(raw: dict, kind: str) -> dict:
    loss = _mapping(raw.get("loss"), "loss")
    _reject_unknown(loss, LOSS_KEYS[kind], f"loss (input {kind})")
    loss = {k: _number(v, f"loss.{k}", 0.0, 100.0) for k, v in loss.items()}
    opt = {"name": "adam", "lr": 1e-3, "weight_decay": 0.0, **_mapping(raw.get("optimizer"), "optimizer")}
    _reject_unknown(opt, ("name", "lr", "weight_decay", "momentum"), "optimizer")
    if opt["name"] not in OPTIMIZERS:
        raise UnknownNameError("optimizer.name", str(opt["name"]), list(OPTIMIZERS))
    for key in ("lr", "weight_decay", "momentum"):
        if key in opt:
            opt[key] = _number(opt[key], f"optimizer.{key}", 0.0, 10.0, low_open=key == "lr")
    sched = {"steps": 2000, "decay": "cosine", "final_lr_fraction": 0.05, "milestones": [],
             **_mapping(raw.get("schedule"), "schedule")}
    _reject_unknown(sched, ("steps", "warmup", "decay", "final_lr_fraction", "milestones", "gamma"), "schedule")
    sched["steps"] = _integer(sched["steps"], "schedule.steps", 1, 10**8)
    sched["warmup"] = _integer(sched.get("warmup", min(50, sched["steps"])), "schedule.warmup", 0, sched["steps"])
    if sched["decay"] not in DECAYS:
        raise UnknownNameError("schedule.decay", str(sched["decay"]), list(DECAYS))
    sched["final_lr_fraction"] = _number(sched["final_lr_fraction"], "schedule.final_lr_fraction", 0.0, 1.0)
    sched["gamma"] = _number(sched.get("gamma", 0.5), "schedule.gamma", 0.0, 1.0, low_open=True)
    if not isinstance(sched["milestones"], list):
        raise InputError("schedule.milestones", sched["milestones"], "a list of step numbers")
    sched["milestones"] = [_integer(m, "schedule.milestones", 1, sched["steps"]) for m in sched["milestones"]]
    return {"loss": loss, "optimizer": opt, "schedule": sched}


def parse_train_config(raw, *, base_dir: Path = Path("."), source: str = "") -> TrainConfig:
    if not isinstance(raw, dict):
        raise InputError("CONFIG", type(raw).__name__, "a YAML mapping with model, input and data")
    _reject_unknown(raw, TOP_KEYS, "the training config")
    network, params, kind = _parse_model(raw)
    name = str(raw.get("name") or network)
    seed = _integer(raw.get("seed", 0), "seed", 0, 2**63 - 1)
    every = {key: _integer(raw.get(key, default), key, 1, 10**8)
             for key, default in (("validate_every", 250), ("checkpoint_every", 50))}
    return TrainConfig(name=name, seed=seed, network=network, network_params=params, input=kind,
                       **_parse_data(raw, Path(base_dir), kind), **_parse_optimization(raw, kind), **every,
                       source=source)


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
