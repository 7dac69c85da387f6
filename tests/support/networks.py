"""Small network files for tests of the learned priors (the mechanics do not need a trained network)."""

from __future__ import annotations

from pathlib import Path

import torch

from capssim.reconstruct.networks import build_network, save_model


def tiny_denoiser_weights(folder: Path) -> Path:
    """A small untrained 12-channel denoiser (4 features, 3 layers, seed 0) saved as ``folder/model.pt``."""
    torch.manual_seed(0)
    params = {"channels": 12, "features": 4, "depth": 3}
    return save_model(Path(folder) / "model.pt", "denoiser", params, build_network("denoiser", params))
