"""The networks of the learned baselines, their registry and the model file.

A model file (``.pt``, written by ``capssim train``) is a ``torch.save`` dict read back with
``torch.load(weights_only=True)`` (no code is unpickled)::

    {"format": "capssim-model", "version": 1, "network": "cpdnet" | "dofp-nafnet" | "edsr" | "denoiser",
     "params": {constructor keywords}, "state_dict": {...}, "input": "dofp" | "dofp-igri2" | "aperture" | "noisy-gt",
     "training": {config, steps, seed, validation PSNR, ...}}

:func:`load_model` rebuilds the network from ``network`` and ``params``. Shipped weights live in
``weights/`` beside this package (:func:`shipped_weights`).
"""

from __future__ import annotations

import io
from pathlib import Path

import torch
from torch import nn

from capssim.errors import InputError, UnknownNameError
from capssim.files.imageio import atomic_write_bytes

from ..dofp.method_body import reject_unknown_options
from .cpdnet import CPDNet
from .denoiser import NoiseLevelDenoiser
from .edsr import EDSR
from .nafnet import DofpNAFNet

MODEL_FORMAT = "capssim-model"
MODEL_VERSION = 1
#: network name -> class; each class has ``input_kind`` ("dofp", "dofp-igri2", "aperture" or "noisy-gt")
NETWORKS: dict[str, type[nn.Module]] = {"cpdnet": CPDNet, "dofp-nafnet": DofpNAFNet, "edsr": EDSR,
                                        "denoiser": NoiseLevelDenoiser}
#: shipped weights folder (package data of capssim.reconstruct)
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"


def build_network(name: str, params: dict | None = None) -> nn.Module:
    """The network ``name`` built with keyword ``params``; a bad name or keyword is an InputError."""
    if name not in NETWORKS:
        raise UnknownNameError("network", name, sorted(NETWORKS))
    try:
        return NETWORKS[name](**dict(params or {}))
    except TypeError as exc:
        raise InputError("model", dict(params or {}), f"keywords of the {name} network", str(exc)) from None


def save_model(path, network: str, params: dict, model: nn.Module, training: dict | None = None) -> Path:
    """Write a model file atomically (temp file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"format": MODEL_FORMAT, "version": MODEL_VERSION, "network": network, "params": dict(params),
              "input": NETWORKS[network].input_kind, "training": dict(training or {}),
              "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}}
    buffer = io.BytesIO()
    torch.save(record, buffer)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def unreadable_reason(exc: BaseException, *, limit: int = 120) -> str:
    """The first line of ``exc``'s message, at most ``limit`` characters (torch's load errors run to 8
    lines of advice), with the exception's class name when the message is empty."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    text = lines[0] if lines else ""
    if len(text) < 12:  # an empty or bare message (EOFError, a KeyError of a pickle opcode): name the class
        text = f"{type(exc).__name__}{': ' + text if text else ''}"
    elif "weights_only" in text or "Weights only load failed" in text:
        text = "not a torch weights file"
    elif "central directory" in text or "zip archive" in text:
        text = "not a torch archive (truncated or another format)"
    text = text.rstrip(":. ")
    return text if len(text) <= limit else text[:limit - 3].rstrip() + "..."


def is_model_file(path) -> bool:
    """True when ``path`` is a capssim model file (not TorchScript, not ONNX)."""
    try:
        record = torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception:  # TorchScript archives and other files are not model files
        return False
    return isinstance(record, dict) and record.get("format") == MODEL_FORMAT


def load_model(path, *, device: torch.device | str = "cpu", expect: str | None = None,
               option: str = "weights") -> tuple[nn.Module, dict]:
    """``(network in eval mode on device, record without the state dict)`` of a model file.

    ``expect``: the network name the caller needs; another one is an InputError naming ``option``.
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise InputError(option, str(path), "an existing model file written by 'capssim train' (RUN/model.pt)",
                         f"Train one (capssim train CONFIG -o RUN) or use the shipped weights ({WEIGHTS_DIR}).")
    try:
        record = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise InputError(option, str(path), "a model file written by 'capssim train'",
                         f"It cannot be read ({unreadable_reason(exc)}): train it again, or copy it again.") from None
    if not isinstance(record, dict) or record.get("format") != MODEL_FORMAT:
        raise InputError(option, str(path), "a model file written by 'capssim train' (format capssim-model)")
    if record.get("version") != MODEL_VERSION:
        raise InputError(option, f"{p} (version {record.get('version')})", f"model file version {MODEL_VERSION}",
                         "Retrain it with this capssim.")
    if expect is not None and record.get("network") != expect:
        raise InputError(option, f"{p} (a {record.get('network')} model)", f"a {expect} model file")
    try:  # a tampered or truncated record: torch's errors list every key, over many lines
        model = build_network(record["network"], record.get("params"))
        model.load_state_dict(record["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise InputError(option, str(path), "a model file written by 'capssim train' (network, params, state_dict)",
                         f"Its weights do not fit its network ({unreadable_reason(exc)}): train it again.") from None
    model.eval().to(device)
    return model, {k: v for k, v in record.items() if k != "state_dict"}


def weights_option(options: dict, shipped: str, *, also: tuple[str, ...] = ()) -> Path:
    """The model file of a learned method's option ``weights=PATH`` (default: the shipped ``shipped``); any
    other option is an UnknownNameError, which lists ``weights`` and the method's other options ``also`` (already
    taken out of ``options`` by the caller)."""
    opts = dict(options)
    weights = str(opts.pop("weights", "") or "").strip() or None
    reject_unknown_options(opts, ["weights", *also])
    return Path(weights) if weights else shipped_weights(shipped)


def shipped_weights(name: str) -> Path:
    """The path of the shipped model ``weights/NAME.pt`` (an InputError listing them if absent)."""
    path = WEIGHTS_DIR / f"{name}.pt"
    if not path.is_file():
        have = sorted(p.stem for p in WEIGHTS_DIR.glob("*.pt")) or ["(none shipped)"]
        raise UnknownNameError("shipped weights", name, have)
    return path
