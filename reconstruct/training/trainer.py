"""``capssim train``: a small deterministic trainer for the learned baselines over capssim datasets.

A run folder ``RUN`` holds:

* ``checkpoint.pt``: model, optimizer and crop-generator states, the step and the history,
  written atomically every ``checkpoint_every`` steps; the same command run again resumes from
  it exactly (the result equals an uninterrupted run's, bit for bit on the same machine);
* ``model.pt``: the trained model (:func:`capssim.reconstruct.networks.save_model`), when done;
* ``history.jsonl``: one line per logged step (loss, learning rate, validation PSNR);
* ``training.png``: the loss and validation-PSNR curves; ``train-config.json``: the parsed config.

Determinism: the network's initial weights come from ``torch.manual_seed(seed)`` and every batch
(samples and crop offsets) from a ``torch.Generator`` seeded with ``seed``; CPU convolutions
are deterministic for a fixed number of threads.
"""

from __future__ import annotations

import io
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from capssim.dataset.config import load_config
from capssim.dataset.generate import dataset_is_finished, generate_dataset
from capssim.dataset.torch import CaptureDataset
from capssim.errors import InputError
from capssim.files.imageio import atomic_write_bytes, atomic_write_json, atomic_write_text
from capssim.runtime.resources import check_memory

from ..networks import build_network, save_model, unreadable_reason
from .config import DICTIONARY_MODEL, TrainConfig, learning_rate
from .dictionary import DICTIONARY_FILE, learn_jcpd_dictionary
from .pairs import MOSAIC_INPUT_KINDS, PairSet, build_pairs, masked_psnr

log = logging.getLogger(__name__)
CHECKPOINT, MODEL, HISTORY, PLOT, CONFIG_COPY = "checkpoint.pt", "model.pt", "history.jsonl", "training.png", \
    "train-config.json"
#: loss lines in the history: one every this many steps (and at every validation)
LOG_EVERY = 10
#: bytes the in-memory training pairs take per GT value, with their inputs and working copies
BYTES_PER_GT_VALUE = 16


@dataclass
class TrainResult:
    run: Path
    model: Path
    steps: int
    resumed_from: int
    validation_psnr: float | None
    wall_s: float
    history: list[dict] = field(default_factory=list)
    baseline_psnr: float | None = None


def ensure_dataset(config: TrainConfig, *, dataset_workers: int = 0, say: Callable[[str], None] = log.info) -> None:
    """Generate the dataset of ``config`` in ``data.root`` if it is not finished there."""
    dataset = load_config(config.dataset_config)
    if dataset.samples <= config.validation:
        raise InputError("data.validation", config.validation,
                         f"fewer than the dataset's {dataset.samples} samples", "Hold out fewer samples.")
    if dataset_is_finished(dataset, config.dataset_root):
        say(f"dataset {config.dataset_root}: {dataset.samples} samples (finished, reused)")
        return
    result = generate_dataset(dataset, config.dataset_root, workers=dataset_workers)
    if not result.complete:
        raise InputError("data.dataset", str(config.dataset_config), "a dataset whose samples all generate",
                         f"Samples {sorted(result.failed)[:10]} failed; rerun to retry them.")
    say(f"dataset {config.dataset_root}: {dataset.samples} samples ({result.generated} generated now)")


def load_pairs(config: TrainConfig, *, dataset_workers: int = 0, say: Callable[[str], None] = log.info):
    """Generate the dataset if it is not finished, then ``(train, validation)`` :class:`PairSet`."""
    ensure_dataset(config, dataset_workers=dataset_workers, say=say)
    items = CaptureDataset(config.dataset_root, crop=None, load_dofp=config.input in MOSAIC_INPUT_KINDS)
    n = len(items)
    first = items[0]
    check_memory("data.dataset", n * first["gt"].numel() * BYTES_PER_GT_VALUE, what="the training pairs in memory",
                 fix="Use a dataset with fewer or smaller samples.")
    split = n - config.validation
    train = build_pairs(config.input, [items[i] for i in range(split)])
    validation = build_pairs(config.input, [items[i] for i in range(split, n)])
    return train, validation


def make_optimizer(config: TrainConfig, model: torch.nn.Module) -> torch.optim.Optimizer:
    o = config.optimizer
    if o["name"] == "sgd":
        return torch.optim.SGD(model.parameters(), lr=o["lr"], momentum=o.get("momentum", 0.9),
                               weight_decay=o["weight_decay"])
    cls = torch.optim.AdamW if o["name"] == "adamw" else torch.optim.Adam
    return cls(model.parameters(), lr=o["lr"], weight_decay=o["weight_decay"])


@torch.no_grad()
def validate(model: torch.nn.Module | None, pairs: PairSet) -> float:
    """Mean PSNR (dB) of the model on the whole validation samples (``None``: of the input baseline)."""
    values = []
    if model is not None:
        model.eval()
    for i in range(len(pairs)):
        inputs, target, mask = pairs.full(i)
        image = pairs.baseline(inputs) if model is None else pairs.image(pairs.predict(model, inputs))
        values.append(masked_psnr(image, target, mask))
    if model is not None:
        model.train()
    return float(np.mean(values))


def _save_checkpoint(run: Path, state: dict) -> None:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(run / CHECKPOINT, buffer.getvalue())
    atomic_write_text(run / HISTORY, "".join(json.dumps(h) + "\n" for h in state["history"]))


def _same_config(config: TrainConfig, run: Path) -> bool:
    """True when ``run`` holds the config copy of ``config`` (a run stopped before its first checkpoint)."""
    try:
        return json.loads((run / CONFIG_COPY).read_text()) == json.loads(json.dumps(config.to_dict()))
    except (OSError, ValueError):
        return False


def check_run_folder(config: TrainConfig, run: Path, *, overwrite: bool = False) -> dict | None:
    """The checkpoint state to resume from (None: a new run, or ``overwrite``), or a one-line
    :class:`InputError` for a run folder that cannot be used: a file, a folder of another config, an unreadable
    checkpoint or one of another config. Changes nothing (the command calls it before any work)."""
    run = Path(run)
    if run.exists() and not run.is_dir():
        raise InputError("-o/--output", str(run), "a folder for the training run")
    checkpoint = run / CHECKPOINT
    if overwrite:
        return None
    if run.is_dir() and any(run.iterdir()) and not checkpoint.is_file() and not _same_config(config, run):
        raise InputError("-o/--output", str(run), "a new folder, or a run folder of this config to resume",
                         "Pass --overwrite to start again there, or choose another -o.")
    if not checkpoint.is_file():
        return None
    try:
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch's message runs to 8 lines of advice: one line, naming the file
        raise InputError("-o/--output", f"{checkpoint} (unreadable: {unreadable_reason(exc)})",
                         "a run folder whose checkpoint capssim train wrote",
                         "Pass --overwrite to start the run again there, or choose another -o.") from None
    if not isinstance(state, dict) or state.get("fingerprint") != config.fingerprint():
        raise InputError("-o/--output", str(run), "the run folder of this same training config",
                         "Its checkpoint comes from another config: pass --overwrite, or choose another -o.")
    return state


def _open_run(config: TrainConfig, run: Path, *, overwrite: bool) -> dict | None:
    """The checkpoint to resume from (None: a new run); refuses a run folder of another config."""
    state = check_run_folder(config, run, overwrite=overwrite)
    if overwrite:
        for name in (CHECKPOINT, MODEL, HISTORY, PLOT, CONFIG_COPY):
            (run / name).unlink(missing_ok=True)
    run.mkdir(parents=True, exist_ok=True)
    return state


def train(config: TrainConfig, run, *, device: torch.device | str = "cpu", overwrite: bool = False,
          dataset_workers: int = 0, stop_after: int | None = None,
          progress: Callable[[int, int, float, float | None], None] | None = None,
          say: Callable[[str], None] = log.info) -> TrainResult:
    """Train ``config`` into the folder ``run`` (resuming its checkpoint); see the module docstring.

    ``stop_after``: stop (after checkpointing) once this many steps are done in all, as a kill would.
    ``progress(step, steps, loss, validation_psnr)`` is called after every step.
    """
    t0 = time.perf_counter()
    run, device = Path(run), torch.device(device)
    state = _open_run(config, run, overwrite=overwrite)
    atomic_write_json(run / CONFIG_COPY, config.to_dict())
    if config.network == DICTIONARY_MODEL:
        ensure_dataset(config, dataset_workers=dataset_workers, say=say)
        record = learn_jcpd_dictionary(config, run, say=say)
        return TrainResult(run, run / DICTIONARY_FILE, config.schedule["steps"], 0, record["validation_psnr_db"],
                           time.perf_counter() - t0, [], record["validation_analytic_psnr_db"])
    train_pairs, val_pairs = (p.to(device) for p in load_pairs(config, dataset_workers=dataset_workers, say=say))
    torch.manual_seed(config.seed)
    model = build_network(config.network, config.network_params).to(device)
    optimizer = make_optimizer(config, model)
    generator = torch.Generator().manual_seed(config.seed)
    history, start = [], 0
    if state is not None:
        try:  # a checkpoint of this config whose contents were damaged: one line, not torch's key lists
            model.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
            generator.set_state(state["generator"])
            history, start = list(state["history"]), int(state["step"])
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise InputError("-o/--output", f"{run / CHECKPOINT} ({unreadable_reason(exc)})",
                             "a checkpoint capssim train wrote", "Pass --overwrite to start the run again.") from None
        say(f"resuming {run} at step {start} of {config.schedule['steps']}")
    baseline = validate(None, val_pairs)
    say(f"validation: {len(val_pairs)} held-out pairs, input baseline ({config.input}) {baseline:.2f} dB")
    if progress is not None and start:
        last = history[-1] if history else {}
        progress(start, config.schedule["steps"], last.get("loss", float("nan")), last.get("val_psnr"))
    val_psnr = _run_steps(config, model, optimizer, generator, train_pairs, val_pairs, history, start, run,
                          stop_after=stop_after, progress=progress)
    steps_done = history[-1]["step"] if history else start
    model_path = run / MODEL
    if steps_done >= config.schedule["steps"]:
        training = {"config": config.to_dict(), "fingerprint": config.fingerprint(), "steps": steps_done,
                    "validation_psnr_db": val_psnr, "validation_baseline_psnr_db": baseline,
                    "torch": str(torch.__version__), "device": str(device), "threads": torch.get_num_threads()}
        save_model(model_path, config.network, config.network_params, model, training)
        write_plot(history, run / PLOT, title=config.name, baseline=baseline)
    return TrainResult(run, model_path, steps_done, start, val_psnr, time.perf_counter() - t0, history, baseline)


def _run_steps(config, model, optimizer, generator, train_pairs, val_pairs, history, start, run, *,
               stop_after, progress) -> float | None:
    steps = config.schedule["steps"]
    end = steps if stop_after is None else min(steps, stop_after)
    val_psnr = next((h["val_psnr"] for h in reversed(history) if "val_psnr" in h), None)
    model.train()
    for step in range(start, end):
        lr = learning_rate(config, step)
        for group in optimizer.param_groups:
            group["lr"] = lr
        inputs, target, mask = train_pairs.draw(config.batch, config.crop, generator)
        loss = train_pairs.loss(train_pairs.predict(model, inputs), target, mask, config.loss)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = None
        if "clip_grad_norm" in config.optimizer:
            grad_norm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), config.optimizer["clip_grad_norm"]))
        optimizer.step()
        done, value = step + 1, float(loss.detach())
        if not np.isfinite(value):
            raise InputError("optimizer.lr", config.optimizer["lr"], "a learning rate that keeps the loss finite",
                             f"The loss became {value} at step {done}; lower the learning rate.")
        record = {"step": done, "loss": value, "lr": lr}
        if grad_norm is not None:  # before clipping
            record["grad_norm"] = grad_norm
        if done % config.validate_every == 0 or done == steps:
            val_psnr = record["val_psnr"] = validate(model, val_pairs)
        if done % LOG_EVERY == 0 or "val_psnr" in record or done == end:
            history.append(record)
        if done % config.checkpoint_every == 0 or done == end:
            _save_checkpoint(run, {"fingerprint": config.fingerprint(), "step": done, "model": model.state_dict(),
                                   "optimizer": optimizer.state_dict(), "generator": generator.get_state(),
                                   "history": history})
        if progress is not None:
            progress(done, steps, value, val_psnr)
    return val_psnr


def write_plot(history: list[dict], path: Path, *, title: str, baseline: float | None = None) -> None:
    """Training loss (log scale) and validation PSNR against the step, written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    steps, losses = [h["step"] for h in history], np.array([h["loss"] for h in history])
    a.semilogy(steps, losses, lw=0.6, alpha=0.5, label="logged steps")
    if len(losses) >= 20:
        a.semilogy(steps[9:-10], np.convolve(losses, np.ones(20) / 20, mode="valid"), lw=1.5, label="mean of 20")
        a.legend(loc="upper right")
    a.set(xlabel="step", ylabel="training loss", title=title)
    val = [h for h in history if "val_psnr" in h]
    b.plot([h["step"] for h in val], [h["val_psnr"] for h in val], "o-", label="network")
    if baseline is not None:
        b.axhline(baseline, color="0.4", ls="--", label="input baseline")
        b.legend(loc="lower right")
    b.set(xlabel="step", ylabel="validation PSNR (dB)", title="held-out samples")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
