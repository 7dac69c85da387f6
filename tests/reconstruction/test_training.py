"""``capssim train``: config checks, loss decreases, exact resume (in process and after SIGKILL), model files."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from capssim.errors import InputError, UnknownNameError
from capssim.reconstruct.methods.dofp_jcpd import demosaic_dofp_jcpd
from capssim.reconstruct.networks import load_model
from capssim.reconstruct.training.config import learning_rate, load_train_config, parse_train_config
from capssim.reconstruct.training.trainer import CHECKPOINT, MODEL, PLOT, train

CLI = [sys.executable, "-m", "capssim.cli.__main__"]

DATASET = """
name: tiny
seed: 4
samples: 5
defaults:
  sensor: {noise: gaussian, sigma: 0.005}
  dofp_layout: {choice: [sony, 0-45-135-90]}
  pose: {shift_max_px: {uniform: [0.3, 1.0]}}
sources:
  - gt: gt/a
    size: 32
    crop_position: random
    augment: {rot90: {int_uniform: [0, 3]}}
"""


@pytest.fixture
def tmp_gt(tmp_path, write_png_gt, smooth_random_scene) -> Path:
    """``tmp_path``, holding ``gt/a`` (a 48 px PNG ground truth) and the ``dataset.yaml`` that reads it."""
    write_png_gt(tmp_path / "gt" / "a", smooth_random_scene(48, seed=2))
    (tmp_path / "dataset.yaml").write_text(textwrap.dedent(DATASET))
    return tmp_path


def tiny_config(tmp_path: Path, network: str = "cpdnet", steps: int = 12, **extra) -> Path:
    """A training config in ``tmp_path`` (the :func:`tmp_gt` folder) for a tiny network."""
    model = {"cpdnet": "{network: cpdnet, features: 6, colour_blocks: 1, polarization_blocks: 1}",
             "edsr": "{network: edsr, channels: 3, features: 6, blocks: 1}",
             "denoiser": "{network: denoiser, channels: 12, features: 6, depth: 3}"}[network]
    crop = {"cpdnet": 16, "edsr": 8, "denoiser": 16}[network]
    kind = {"cpdnet": "dofp", "edsr": "aperture", "denoiser": "noisy-gt"}[network]
    text = f"""
    name: tiny-{network}
    seed: 1
    model: {model}
    input: {kind}
    data: {{dataset: dataset.yaml, root: {tmp_path / "data"}, validation: 1, crop: {crop}, batch: 4}}
    optimizer: {{name: adam, lr: {extra.get("lr", 0.003)}}}
    schedule: {{steps: {steps}, warmup: 0, decay: constant}}
    validate_every: 6
    checkpoint_every: 3
    """
    path = tmp_path / f"train-{network}.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def weights_equal(a: Path, b: Path) -> bool:
    sa = torch.load(a, weights_only=True)["state_dict"]
    sb = torch.load(b, weights_only=True)["state_dict"]
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


@pytest.mark.parametrize("network", ["cpdnet", "edsr", "denoiser"])
def test_loss_decreases_and_model_file_loads(tmp_path, network, tmp_gt):
    config = load_train_config(tiny_config(tmp_gt, network, steps=40))
    losses = []
    result = train(config, tmp_path / "run", progress=lambda s, n, loss, v: losses.append(loss))
    assert len(losses) == 40 and result.steps == 40
    assert sum(losses[-8:]) / 8 < 0.8 * sum(losses[:8]) / 8
    assert (tmp_path / "run" / PLOT).stat().st_size > 1000
    model, record = load_model(result.model, expect=network)
    assert record["network"] == network and record["training"]["steps"] == 40
    assert record["training"]["validation_psnr_db"] == pytest.approx(result.validation_psnr)
    with pytest.raises(InputError, match="weights"):
        load_model(result.model, expect="cpdnet" if network == "edsr" else "edsr")


def test_denoiser_retrains_to_the_same_weights(tmp_path, tmp_gt):
    """The noisy pairs are drawn from the run's seeded generator: two runs of one config give equal weights,
    and another seed gives other weights."""
    config = load_train_config(tiny_config(tmp_gt, "denoiser", steps=6))
    first, second = train(config, tmp_path / "first"), train(config, tmp_path / "second")
    assert weights_equal(first.model, second.model)
    other = load_train_config(tiny_config(tmp_gt, "denoiser", steps=6))
    other.seed = 2
    assert not weights_equal(first.model, train(other, tmp_path / "other").model)


def test_resume_is_exact_in_process(tmp_path, tmp_gt):
    config = load_train_config(tiny_config(tmp_gt, steps=9))
    straight = train(config, tmp_path / "straight")
    part = train(config, tmp_path / "resumed", stop_after=5)  # checkpoints at 3 and at the stop
    assert part.steps == 5 and not (tmp_path / "resumed" / MODEL).exists()
    resumed = train(config, tmp_path / "resumed")
    assert resumed.resumed_from == 5 and resumed.steps == 9
    assert weights_equal(straight.model, resumed.model)
    logged = {h["step"]: h["loss"] for h in resumed.history}
    assert all(logged[h["step"]] == h["loss"] for h in straight.history)


def test_finished_dataset_is_shared_while_another_run_holds_its_lock(tmp_path, tmp_gt):
    from capssim.dataset.manifest import DatasetLock

    config = load_train_config(tiny_config(tmp_gt, steps=2))
    train(config, tmp_path / "first")  # generates the dataset
    with DatasetLock(config.dataset_root):  # e.g. a second training that is checking it
        second = train(config, tmp_path / "second")
    assert second.steps == 2
    (tmp_path / "stopped").mkdir()  # a run stopped before its first checkpoint reruns in its folder
    (tmp_path / "stopped" / "train-config.json").write_text((tmp_path / "first" / "train-config.json").read_text())
    assert train(config, tmp_path / "stopped").steps == 2


@pytest.mark.processes
def test_sigkill_then_rerun_equals_uninterrupted(tmp_path, tmp_gt):
    config_path = tiny_config(tmp_gt, steps=150)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the command below: CPU results depend on the thread count
    try:
        train(load_train_config(config_path), tmp_path / "straight")
    finally:
        torch.set_num_threads(threads)
    env = {**os.environ, "CAPSSIM_THREADS": "1"}
    cmd = [*CLI, "train", str(config_path), "-o", str(tmp_path / "killed")]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not (tmp_path / "killed" / CHECKPOINT).exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (tmp_path / "killed" / MODEL).exists(), "the run finished before it could be killed"
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "resumed at step" in done.stdout
    assert weights_equal(tmp_path / "straight" / MODEL, tmp_path / "killed" / MODEL)


def test_config_errors_name_the_key(tmp_path, tmp_gt):
    good = tiny_config(tmp_gt)
    base = {"model": {"network": "cpdnet"}, "input": "dofp", "data": {"dataset": "dataset.yaml"}}
    parse_train_config(base, base_dir=tmp_path)
    cases = [({"model": {"network": "unet"}}, UnknownNameError, "unet"),
             ({"input": "aperture"}, InputError, "input"),
             ({"data": {"dataset": "missing.yaml"}}, InputError, "data.dataset"),
             ({"data": {"dataset": "dataset.yaml", "crop": 30}}, InputError, "multiple of 4"),
             ({"optimizer": {"name": "adam", "lr": -1}}, InputError, "optimizer.lr"),
             ({"schedule": {"steps": 0}}, InputError, "schedule.steps"),
             ({"learning_rate": 1}, UnknownNameError, "learning_rate"),
             ({"model": {"network": "cpdnet", "features": "wide"}}, InputError, "model.features")]
    for change, error, text in cases:
        with pytest.raises(error, match=text):
            parse_train_config({**base, **change}, base_dir=tmp_path)
    with pytest.raises(InputError, match="network"):
        from capssim.reconstruct.networks import build_network
        build_network("cpdnet", {"depth": 3})
    cfg = load_train_config(good)
    assert learning_rate(cfg, 0) == pytest.approx(0.003)


def test_run_folder_of_another_config_is_refused(tmp_path, tmp_gt):
    config = load_train_config(tiny_config(tmp_gt, steps=3))
    train(config, tmp_path / "run")
    other = load_train_config(tiny_config(tmp_gt, steps=3, lr=0.001))
    with pytest.raises(InputError, match="another config"):
        train(other, tmp_path / "run")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="overwrite"):
        train(config, tmp_path / "busy")


def test_cli_bad_config_is_one_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("model: {network: cpdnet}\ninput: dofp\ndata: {dataset: nowhere.yaml}\n")
    done = subprocess.run([*CLI, "train", str(bad), "-o", str(tmp_path / "run")], capture_output=True, text=True)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "data.dataset" in done.stderr


def test_jcpd_dictionary_learning_gives_a_usable_dictionary(tmp_path, tmp_gt):
    tiny_config(tmp_gt)
    path = tmp_path / "dict.yaml"
    path.write_text(textwrap.dedent(f"""
    seed: 2
    model: {{network: jcpd-dictionary, patch: 8, atoms: 24, sparsity: 4, patches: 150}}
    input: gt-patches
    data: {{dataset: dataset.yaml, root: {tmp_path / "data"}, validation: 1}}
    schedule: {{steps: 3}}
    """))
    result = train(load_train_config(path), tmp_path / "run")
    with np.load(result.model) as data:
        d, record = data["D"], json.loads(str(data["record"]))
    assert d.shape == (768, 9 + 24) and np.isfinite(d).all()
    errors = record["representation_error"]
    assert errors[-1] < errors[0]
    assert record["validation_psnr_db"] > 20
    grey = np.full((32, 32), 0.3, dtype=np.float32)  # a constant mosaic stays exact with the learned atoms
    np.testing.assert_allclose(demosaic_dofp_jcpd(grey, dictionary=str(result.model)), 0.3, atol=1e-5)
    with pytest.raises(InputError, match="model"):
        parse_train_config({"model": {"network": "jcpd-dictionary", "atoms": 50, "patches": 10},
                            "input": "gt-patches", "data": {"dataset": "dataset.yaml"}}, base_dir=tmp_path)
