"""The learned baselines' networks: shapes, tiling, model files, the methods, and no downloads."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
import torch

from capssim.errors import InputError
from capssim.reconstruct.dofp.bilinear import demosaic_dofp_bilinear
from capssim.reconstruct.networks import NETWORKS, WEIGHTS_DIR, build_network, load_model, save_model
from capssim.reconstruct.networks.cpdnet import dofp_network_input, sparse_channels, stokes_linear
from capssim.reconstruct.networks.tiling import apply_tiled

REPO = Path(__file__).resolve().parents[2]


def test_cpdnet_shapes_and_residual_start():
    torch.manual_seed(0)
    net = build_network("cpdnet", {"features": 8, "colour_blocks": 1, "polarization_blocks": 1})
    mosaic = torch.rand(2, 20, 28)
    sparse, bilinear = dofp_network_input(mosaic, "sony")
    final, intermediate = net(sparse, bilinear)
    assert final.shape == intermediate.shape == (2, 12, 20, 28)
    assert stokes_linear(final).shape == (2, 6, 20, 28)
    # the sparse channels hold every mosaic sample exactly once, in its (angle, colour) channel
    assert torch.equal(sparse.sum(dim=1), mosaic)
    assert int((sparse != 0).sum()) == int((mosaic != 0).sum())
    np.testing.assert_allclose(bilinear[0].numpy(), demosaic_dofp_bilinear(mosaic[0].numpy()), atol=1e-6)


@pytest.mark.parametrize("layout", ["sony", "0-45-135-90"])
def test_sparse_channels_follow_the_layout(layout):
    from capssim.conventions import dofp_channel_map

    mosaic = torch.arange(16 * 16, dtype=torch.float32).reshape(1, 16, 16) + 1
    sparse = sparse_channels(mosaic, layout)[0]
    channel = torch.as_tensor(np.asarray(dofp_channel_map(16, 16, layout)))
    assert torch.equal(sparse.argmax(dim=0), channel)


def test_edsr_shapes_and_bicubic_skip():
    net = build_network("edsr", {"channels": 3, "features": 8, "blocks": 2})
    x = torch.rand(4, 3, 9, 13)
    assert net(x).shape == (4, 3, 18, 26)
    for p in net.parameters():
        torch.nn.init.zeros_(p)
    expected = torch.nn.functional.interpolate(x, scale_factor=2, mode="bicubic", align_corners=False)
    assert torch.allclose(net(x), expected)
    assert build_network("edsr", {"channels": 1})(torch.rand(2, 1, 8, 8)).shape == (2, 1, 16, 16)


def test_tiled_inference_equals_whole_image():
    torch.manual_seed(1)
    net = build_network("cpdnet", {"features": 6, "colour_blocks": 2, "polarization_blocks": 2}).eval()
    sparse, bilinear = dofp_network_input(torch.rand(1, 72, 88), "sony")
    with torch.no_grad():
        whole = net(sparse, bilinear)[0]
    tiled = apply_tiled(lambda s, b: net(s, b)[0], (sparse, bilinear), tile=24, halo=16, step=4)
    assert torch.allclose(whole, tiled, atol=1e-6)
    edsr = build_network("edsr", {"features": 6, "blocks": 2}).eval()
    x = torch.rand(2, 3, 40, 36)
    with torch.no_grad():
        assert torch.allclose(edsr(x), apply_tiled(edsr, (x,), scale=2, tile=16, halo=16, step=1), atol=1e-6)


def test_model_file_round_trip_and_bad_files(tmp_path):
    net = build_network("edsr", {"features": 4, "blocks": 1})
    path = save_model(tmp_path / "m.pt", "edsr", {"features": 4, "blocks": 1}, net, {"steps": 3})
    again, record = load_model(path)
    assert record["input"] == "aperture" and record["training"] == {"steps": 3}
    for k, v in net.state_dict().items():
        assert torch.equal(again.state_dict()[k], v)
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    for bad in (tmp_path / "junk.pt", tmp_path / "missing.pt"):
        with pytest.raises(InputError, match="weights"):
            load_model(bad)


@pytest.mark.parametrize("name", ["cpdnet-small", "edsr-small", "denoiser"])
def test_shipped_weights_are_small_and_load(name):
    path = WEIGHTS_DIR / f"{name}.pt"
    assert path.is_file(), f"shipped weights {path} missing"
    assert path.stat().st_size < 4 * 2**20
    model, record = load_model(path)
    assert record["network"] in NETWORKS and record["training"]["steps"] >= 1000
    config = record["training"]["config"]
    assert Path(config["source"]).name == f"train-{name}.yaml"
    assert (REPO / "examples" / f"train-{name}.yaml").is_file()


def test_no_code_path_downloads():
    """No module of the package opens network connections or calls a download helper."""
    banned = ("urllib.request", "urllib3", "requests", "httpx", "http.client", "torch.hub", "load_state_dict_from_url",
              "urlopen", "download_url_to_file", "create_connection", "socket.socket", "hf_hub_download")
    for folder in ("capssim", "reconstruct", "eval", "scenes"):
        for path in (REPO / folder).rglob("*.py"):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module:
                    names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
                elif isinstance(node, ast.Attribute):
                    names = [node.attr] + ([f"{node.value.id}.{node.attr}"] if isinstance(node.value, ast.Name) else [])
                for name in names:
                    assert not any(name == b or name.startswith(b + ".") for b in banned), f"{path}: {name}"
