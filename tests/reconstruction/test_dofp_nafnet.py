"""``dofp-nafnet``: the network (identity start, sizes), the method with a model file and with the shipped
weights, hard inputs, the noise map, training (loss, retraining to the same weights) and CUDA."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor, noise_std_map
from capssim.errors import InputError
from capssim.files.schema import ConfigError
from capssim.reconstruct.methods.dofp_nafnet import demosaic_dofp_nafnet, dofp_nafnet_input, mosaic_noise_std
from capssim.reconstruct.networks import WEIGHTS_DIR, build_network, load_model, save_model
from capssim.reconstruct.networks.nafnet import DofpNAFNet
from capssim.reconstruct.registry import reconstruct
from capssim.reconstruct.training.config import load_train_config, parse_train_config
from capssim.reconstruct.training.trainer import train
from capssim.simulate import simulate_capture

REPO = Path(__file__).resolve().parents[2]
TINY = {"width": 4, "encoder_blocks": [1, 0, 1], "middle_blocks": 1, "decoder_blocks": [0, 1, 0]}


def _perturbed(params: dict, seed: int = 0) -> DofpNAFNet:
    """A tiny network whose last convolution is not zero (so it does change IGRI2)."""
    torch.manual_seed(seed)
    net = build_network("dofp-nafnet", params)
    torch.nn.init.normal_(net.ending.weight, std=0.01)
    return net


@pytest.mark.parametrize("shape", [(12, 12), (12, 20), (36, 44), (64, 64)])
def test_untrained_network_returns_its_igri2_start_at_any_size(shape):
    torch.manual_seed(0)
    net = build_network("dofp-nafnet", TINY).eval()
    mosaic = torch.rand(1, *shape)
    sparse, base, sigma = dofp_nafnet_input(mosaic, "sony", torch.full((1, *shape), 0.01))
    assert sparse.shape == base.shape == (1, 12, *shape) and sigma.shape == (1, 1, *shape)
    with torch.no_grad():
        out = net(sparse, base, sigma)
    torch.testing.assert_close(out, base)  # the last convolution starts at zero
    with torch.no_grad():
        moved = _perturbed(TINY).eval()(sparse, base, sigma)
    assert moved.shape == base.shape and not torch.equal(moved, base)


def test_network_sizes_are_checked():
    with pytest.raises(InputError, match="model"):
        build_network("dofp-nafnet", {"width": 4, "encoder_blocks": [1, 1]})


def test_noise_map_follows_the_sensor_model():
    x = np.linspace(0, 1, 11, dtype=np.float32)
    assert np.all(noise_std_map(make_sensor("none"), x) == 0)
    gauss = noise_std_map(make_sensor("gaussian", sigma=0.01), x)
    assert np.allclose(gauss, gauss[0]) and 0.01 <= gauss[0] < 0.0101
    shot = noise_std_map(make_sensor("poisson-gaussian", preset="imx250myr"), x)
    assert np.all(np.diff(shot) > 0) and shot.dtype == np.float32


def test_noise_estimate_of_a_mosaic_without_a_noise_model():
    """The std ``capssim demosaic`` gives the network for a raw frame: Immerkaer's estimate over the 16 sub-mosaics
    (exact on planes, which its Laplacian cancels)."""
    ramp = np.linspace(0.2, 0.7, 128, dtype=np.float32)
    gt = np.stack([ramp[None, :] * (0.6 + 0.03 * c) + 0.1 * ramp[:, None] for c in range(12)])
    clean = simulate_capture(gt, make_sensor("none"), seed=0, psf={"type": "none"}).dofp_raw
    noisy = clean + np.random.default_rng(0).normal(0, 0.01, clean.shape)
    assert mosaic_noise_std(torch.as_tensor(clean)) < 0.002
    assert mosaic_noise_std(torch.as_tensor(noisy)) == pytest.approx(0.01, rel=0.25)


@pytest.fixture
def capture(smooth_random_scene):
    gt = smooth_random_scene(48, seed=5)
    return simulate_capture(gt, make_sensor("poisson-gaussian", preset="imx250myr"), seed=1, dofp_layout="0-45-135-90")


def test_method_with_a_model_file_and_its_refusals(tmp_path, capture):
    path = save_model(tmp_path / "naf.pt", "dofp-nafnet", TINY, _perturbed(TINY), {"steps": 1})
    out, record = reconstruct(capture, "dofp-nafnet", weights=str(path))
    assert out.image.shape == (12, 48, 48) and np.isfinite(out.image).all()
    assert record["params"]["network"] == "dofp-nafnet" and record["params"]["noise_model"] == "poisson-gaussian"
    assert "dev" in record["tuned_on"]
    cpd = save_model(tmp_path / "cpd.pt", "cpdnet", {"features": 4}, build_network("cpdnet", {"features": 4}))
    with pytest.raises(InputError, match="dofp-nafnet"):
        reconstruct(capture, "dofp-nafnet", weights=str(cpd))
    with pytest.raises(InputError, match="weights"):
        reconstruct(capture, "dofp-nafnet", weights=str(tmp_path / "missing.pt"))


def test_shipped_weights_are_small_come_from_the_shipped_config_and_beat_igri2(natural_scene):
    path = WEIGHTS_DIR / "dofp-nafnet.pt"
    assert path.stat().st_size <= 20 * 2**20
    _, record = load_model(path, expect="dofp-nafnet")
    config = load_train_config(REPO / "examples" / "train-dofp-nafnet.yaml")
    assert record["training"]["fingerprint"] == config.fingerprint()
    assert record["training"]["steps"] == config.schedule["steps"]
    gt = natural_scene().astype(np.float32)
    capture = simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=3, psf={"type": "none"})
    out, _ = reconstruct(capture, "dofp-nafnet")
    igri2, _ = reconstruct(capture, "dofp-igri2")

    def mse(image):
        return float(np.mean((np.clip(image, 0, 1) - gt)[:, 8:-8, 8:-8] ** 2))

    assert mse(out.image) < 0.97 * mse(igri2.image)  # 0.905 when shipped: +0.43 dB on a scene it never saw


@pytest.mark.parametrize("fill", [0.0, 1e-6, 1.0, "noise"])
def test_hard_inputs_stay_finite_and_in_range(fill):
    """Black, near-black, saturated and pure-noise mosaics at the smallest and at odd sizes, noise std 0 and 0.2."""
    for shape, sigma in (((12, 12), 0.0), ((26, 38), 0.2)):
        mosaic = (np.random.default_rng(0).random(shape) if fill == "noise" else np.full(shape, fill)).astype(np.float32)
        out = demosaic_dofp_nafnet(mosaic, noise_std=sigma)
        assert out.shape == (12, *shape) and np.isfinite(out).all()
        assert out.min() >= 0 and out.max() <= 1
        if fill != "noise":
            assert np.abs(out - fill).max() < 0.1


def test_the_network_reads_no_noise_std_beyond_its_training_range():
    """Past TRAINED_NOISE_STD_MAX the network would extrapolate: it reads the largest std it was trained on."""
    from capssim.reconstruct.methods.dofp_nafnet import TRAINED_NOISE_STD_MAX

    mosaic = np.random.default_rng(1).random((24, 28)).astype(np.float32)
    at_max = demosaic_dofp_nafnet(mosaic, noise_std=TRAINED_NOISE_STD_MAX)
    np.testing.assert_array_equal(demosaic_dofp_nafnet(mosaic, noise_std=0.2), at_max)
    assert not np.array_equal(demosaic_dofp_nafnet(mosaic, noise_std=TRAINED_NOISE_STD_MAX / 2), at_max)


DATASET = """
name: tiny
seed: 4
samples: 3
defaults:
  sensor: {noise: {choice: [gaussian, poisson-gaussian]}, sigma: 0.01}
  dofp_layout: {choice: [sony, 0-45-135-90]}
sources:
  - gt: gt/a
    size: 32
    crop_position: random
"""


def _config(root: Path, steps: int, *, clip: float | None = None) -> Path:
    (root / "dataset.yaml").write_text(textwrap.dedent(DATASET))
    text = f"""
    name: tiny-nafnet
    seed: 3
    model: {{network: dofp-nafnet, width: 4, encoder_blocks: [1, 0, 1], middle_blocks: 1, decoder_blocks: [0, 1, 0]}}
    input: dofp-igri2
    data: {{dataset: dataset.yaml, root: {root / "data"}, validation: 1, crop: 16, batch: 4}}
    optimizer: {{name: adamw, lr: 0.003{"" if clip is None else f", clip_grad_norm: {clip}"}}}
    schedule: {{steps: {steps}, warmup: 0, decay: constant}}
    validate_every: {steps}
    """
    path = root / ("train.yaml" if clip is None else f"train-clip-{clip}.yaml")
    path.write_text(textwrap.dedent(text))
    return path


def test_training_lowers_the_loss_and_retrains_to_the_same_weights(tmp_path, write_png_gt, smooth_random_scene):
    write_png_gt(tmp_path / "gt" / "a", smooth_random_scene(48, seed=2))
    config = load_train_config(_config(tmp_path, 20))
    losses = []
    first = train(config, tmp_path / "first", progress=lambda s, n, loss, v: losses.append(loss))
    assert sum(losses[-5:]) < sum(losses[:5])
    second = train(config, tmp_path / "second")
    a = torch.load(first.model, weights_only=True)["state_dict"]
    b = torch.load(second.model, weights_only=True)["state_dict"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert first.baseline_psnr is not None and np.isfinite(first.validation_psnr)


def test_gradient_clipping_bounds_each_step_and_is_off_by_default(tmp_path, write_png_gt, smooth_random_scene):
    """``optimizer.clip_grad_norm``: a bound above every gradient changes nothing (bit for bit), a tight one
    changes the weights; the gradient norm before clipping is logged."""
    write_png_gt(tmp_path / "gt" / "a", smooth_random_scene(48, seed=2))

    def weights(clip):
        run = train(load_train_config(_config(tmp_path, 10, clip=clip)), tmp_path / f"run-{clip}")
        return torch.load(run.model, weights_only=True)["state_dict"], run.history

    plain, plain_history = weights(None)
    loose, loose_history = weights(1e6)
    tight, tight_history = weights(1e-5)
    assert all(torch.equal(plain[k], loose[k]) for k in plain)
    assert not all(torch.equal(plain[k], tight[k]) for k in plain)
    assert "grad_norm" not in plain_history[-1]
    assert loose_history[-1]["grad_norm"] > 1e-5 and tight_history[-1]["grad_norm"] > 1e-5


def test_config_refuses_a_bad_block_list_and_a_loss_key(tmp_path):
    (tmp_path / "d.yaml").write_text(textwrap.dedent(DATASET))
    raw = {"model": {"network": "dofp-nafnet", "encoder_blocks": [1, 1]}, "input": "dofp-igri2",
           "data": {"dataset": "d.yaml"}}
    with pytest.raises(ConfigError, match="encoder_blocks"):
        parse_train_config(raw, base_dir=tmp_path)
    raw["model"]["encoder_blocks"] = [1, 1, 1]
    raw["loss"] = {"intermediate_weight": 1.0}
    with pytest.raises(ConfigError, match="intermediate_weight"):
        parse_train_config(raw, base_dir=tmp_path)
    raw.pop("loss")
    raw["optimizer"] = {"clip_grad_norm": 0}
    with pytest.raises(ConfigError, match="clip_grad_norm"):
        parse_train_config(raw, base_dir=tmp_path)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_runs_the_same_code(capture):
    cpu, _ = reconstruct(capture, "dofp-nafnet", device="cpu")
    gpu, _ = reconstruct(capture, "dofp-nafnet", device="cuda")
    np.testing.assert_allclose(gpu.image, cpu.image, atol=2e-3)
