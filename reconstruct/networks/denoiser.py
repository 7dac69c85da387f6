"""A small noise-level-conditioned Gaussian denoiser of 12-channel images, the learned half of the
``nlstr-denoiser`` prior (``caps-plus-cv``). Not the paper's.

References: K. Zhang, W. Zuo, Y. Chen, D. Meng, L. Zhang, "Beyond a Gaussian denoiser: residual learning
of deep CNN for image denoising", IEEE TIP 26(7) 2017 (DnCNN: a plain stack of 3x3 convolutions that
predicts the noise); K. Zhang, W. Zuo, L. Zhang, "FFDNet: toward a fast and flexible solution for CNN
based image denoising", IEEE TIP 27(9) 2018 (the noise level as an input map, so that one network
serves every level a plug-and-play solver asks for).

Layout, for ``noisy`` ``(N, C, H, W)`` on [0, 1] and ``sigma`` ``(N,)`` (white-noise std on that scale):

* input: the image and a constant map ``NOISE_MAP_SCALE * sigma``, ``C + 1`` channels;
* body: ``depth - 1`` 3x3 convolutions of ``features`` channels with ReLU (no batch normalization), a last
  3x3 convolution to ``C`` channels: the noise estimate;
* output: ``noisy`` minus the noise estimate (residual learning), ``(N, C, H, W)``.

The receptive field is ``2 depth + 1`` pixels wide; any ``H, W >= 1`` works (zero padding).
"""

from __future__ import annotations

import torch
from torch import nn

#: the noise map fed to the network is ``sigma`` times this (levels of 0.001-0.1 become 0.01-1)
NOISE_MAP_SCALE = 10.0


class NoiseLevelDenoiser(nn.Module):
    """``denoised = noisy - body([noisy, NOISE_MAP_SCALE * sigma])`` (module docstring).

    Parameters
    ----------
    channels : int
        Image channels ``C`` (12 for the CAPS image, ``c = 3 p + k``).
    features : int
        Channels of the hidden convolutions.
    depth : int
        Convolutions in all (at least 2).
    """

    input_kind = "noisy-gt"

    def __init__(self, channels: int = 12, features: int = 48, depth: int = 7):
        super().__init__()
        if depth < 2:
            raise ValueError(f"depth must be at least 2, got {depth}")
        self.channels = channels
        layers: list[nn.Module] = [nn.Conv2d(channels + 1, features, 3, padding=1), nn.ReLU(inplace=True)]
        for _ in range(depth - 2):
            layers += [nn.Conv2d(features, features, 3, padding=1), nn.ReLU(inplace=True)]
        layers.append(nn.Conv2d(features, channels, 3, padding=1))
        self.body = nn.Sequential(*layers)

    def forward(self, noisy: torch.Tensor, sigma: torch.Tensor | float) -> torch.Tensor:
        n, _, h, w = noisy.shape
        level = torch.as_tensor(sigma, dtype=noisy.dtype, device=noisy.device).reshape(-1, 1, 1, 1)
        noise_map = (NOISE_MAP_SCALE * level).expand(n, 1, h, w)
        return noisy - self.body(torch.cat([noisy, noise_map], dim=1))
