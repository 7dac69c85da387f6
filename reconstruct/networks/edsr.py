"""A x2 single-image super-resolution network in the EDSR style, for ``caps-sisr``.

Reference: B. Lim, S. Son, H. Kim, S. Nah, K. M. Lee, "Enhanced deep residual networks for single
image super-resolution", CVPR Workshops 2017 (EDSR). The CAPS paper (Optics Express 32(2) 2364,
2024, section 5.2) applies such networks to each demosaicked aperture image.

Layout, for an input ``(N, C, H, W)`` on [0, 1] and output ``(N, C, 2H, 2W)``:

* head: 3x3 convolution ``C -> F``;
* body: ``blocks`` residual blocks ``x + s * conv(relu(conv(x)))`` (no batch normalization, residual
  scaling ``s``, EDSR's two changes to SRResNet), a 3x3 convolution and the long skip;
* upsampler: 3x3 convolution ``F -> 4F`` and a pixel shuffle (sub-pixel convolution) by 2;
* tail: 3x3 convolution ``F -> C``.

One addition to EDSR (``bicubic_skip``, default on): the network predicts the residual over the
bicubic x2 interpolation of its input, which the small models trained on 2 CPU cores need to
converge in minutes. The output pixel grid is that of ``F.interpolate(..., align_corners=False)``
(output pixel ``j`` at input coordinate ``j / 2 - 1/4``), the aperture-HR grid of ``caps-sisr``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ResidualBlock(nn.Module):
    """``x + scale * conv(relu(conv(x)))`` with 3x3 convolutions of ``features`` channels."""

    def __init__(self, features: int, scale: float):
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1)
        self.scale = scale

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.scale * self.conv2(F.relu(self.conv1(x)))


class EDSR(nn.Module):
    """x2 EDSR: ``(N, channels, H, W) -> (N, channels, 2H, 2W)`` (see the module docstring)."""

    #: what the network reads: demosaicked aperture images (``capssim.reconstruct.training.pairs``)
    input_kind = "aperture"

    def __init__(self, *, channels: int = 3, features: int = 32, blocks: int = 4, residual_scale: float = 0.1,
                 bicubic_skip: bool = True):
        super().__init__()
        self.channels = channels
        self.head = nn.Conv2d(channels, features, 3, padding=1)
        self.body = nn.Sequential(*[ResidualBlock(features, residual_scale) for _ in range(blocks)],
                                  nn.Conv2d(features, features, 3, padding=1))
        self.upsample = nn.Sequential(nn.Conv2d(features, 4 * features, 3, padding=1), nn.PixelShuffle(2))
        self.tail = nn.Conv2d(features, channels, 3, padding=1)
        self.bicubic_skip = bicubic_skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        head = self.head(x)
        y = self.tail(self.upsample(head + self.body(head)))
        if self.bicubic_skip:
            y = y + F.interpolate(x, scale_factor=2, mode="bicubic", align_corners=False)
        return y
