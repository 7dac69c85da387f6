"""CPDNet: a two-stage (colour, then polarization) demosaicking network for colour-polarization DoFP mosaics.

Reference: S. Wen, Y. Zheng, F. Lu, Q. Zhao, "Convolutional demosaicing network for joint chromatic
and polarimetric imagery", Optics Letters 44(22) 5646, 2019 (CPDNet), as the CAPS paper (Optics
Express 32(2) 2364, 2024, sections 1 and 5.2) describes it: a multitask cascade of a colour module
and a polarization module, trained with a loss on the intermediate colour result as well as the
final one. Built here from that description; the width and depth are options.

Input, for a mosaic batch ``(N, H, W)`` with the 2x2 polarizer cell ``layout``
(:func:`dofp_network_input`):

* ``sparse`` ``(N, 12, H, W)``: each mosaic sample placed in its channel ``c = 3p + k``
  (angle p of 0/45/90/135 deg, colour k of R/G/B), zero elsewhere;
* ``bilinear`` ``(N, 12, H, W)``: the two-step bilinear demosaicking (``dofp-bilinear``).

Stages (both predict residuals, all convolutions 3x3 with ``features`` channels):

1. colour module, shared by the four angles: for angle p it reads the angle's 3 sparse and 3
   bilinear channels and the bilinear intensity (mean over angles, 3 channels), and returns the
   angle's RGB; stacked, the intermediate ``(N, 12, H, W)``;
2. polarization module, shared by the three colours: for colour k it reads the 4 intermediate and
   4 bilinear angle channels of that colour and returns the 4 angle channels of the output.

:func:`cpdnet_loss` is the multitask loss: ``L1(final) + w_mid L1(intermediate) + w_stokes
L1(S1, S2 of final)``, the last term the polarization-aware constraint (Stokes S1 = I0 - I90,
S2 = I45 - I135 per colour).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from capssim.conventions import BAYER_RGGB

from ..dofp.bilinear import demosaic_dofp_bilinear
from ..dofp.mosaic import angle_offsets
from .edsr import ResidualBlock


def conv_stack(in_channels: int, out_channels: int, features: int, blocks: int) -> nn.Sequential:
    """3x3 convolution, ``blocks`` residual blocks (scale 1), ReLU, 3x3 convolution to ``out_channels``."""
    return nn.Sequential(nn.Conv2d(in_channels, features, 3, padding=1),
                         *[ResidualBlock(features, 1.0) for _ in range(blocks)],
                         nn.ReLU(), nn.Conv2d(features, out_channels, 3, padding=1))


class CPDNet(nn.Module):
    """``(sparse, bilinear)`` ``(N, 12, H, W)`` each -> ``(final, intermediate)`` ``(N, 12, H, W)`` each."""

    #: what the network reads: the DoFP mosaic (:func:`dofp_network_input`)
    input_kind = "dofp"

    def __init__(self, *, features: int = 24, colour_blocks: int = 2, polarization_blocks: int = 2):
        super().__init__()
        self.colour = conv_stack(9, 3, features, colour_blocks)
        self.polarization = conv_stack(8, 4, features, polarization_blocks)

    def forward(self, sparse: torch.Tensor, bilinear: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n, _, h, w = sparse.shape
        by_angle_sparse = sparse.reshape(n, 4, 3, h, w)
        by_angle_bilinear = bilinear.reshape(n, 4, 3, h, w)
        intensity = by_angle_bilinear.mean(dim=1, keepdim=True).expand(n, 4, 3, h, w)
        x = torch.cat([by_angle_sparse, by_angle_bilinear, intensity], dim=2).reshape(n * 4, 9, h, w)
        intermediate = by_angle_bilinear + self.colour(x).reshape(n, 4, 3, h, w)  # (N, angle, colour, H, W)
        by_colour = intermediate.transpose(1, 2)  # (N, colour, angle, H, W)
        y = torch.cat([by_colour, by_angle_bilinear.transpose(1, 2)], dim=2).reshape(n * 3, 8, h, w)
        final = by_colour + self.polarization(y).reshape(n, 3, 4, h, w)
        return final.transpose(1, 2).reshape(n, 12, h, w), intermediate.reshape(n, 12, h, w)


def sparse_channels(mosaic: torch.Tensor, layout="sony") -> torch.Tensor:
    """``(N, H, W)`` mosaics -> ``(N, 12, H, W)``: each sample in its channel ``3p + k``, zeros elsewhere."""
    n, h, w = mosaic.shape
    out = mosaic.new_zeros((n, 4, 3, h, w))
    rows = torch.arange(h, device=mosaic.device)
    cols = torch.arange(w, device=mosaic.device)
    for p, (dr, dc) in enumerate(angle_offsets(layout)):
        for r0 in (0, 1):
            for c0 in (0, 1):  # the angle's sub-mosaic is an RGGB Bayer image
                k = BAYER_RGGB[r0][c0]
                rs = rows[(rows % 2 == dr) & ((rows // 2) % 2 == r0)]
                cs = cols[(cols % 2 == dc) & ((cols // 2) % 2 == c0)]
                out[:, p, k, rs[:, None], cs[None, :]] = mosaic[:, rs[:, None], cs[None, :]]
    return out.reshape(n, 12, h, w)


def dofp_network_input(mosaic: torch.Tensor, layout="sony") -> tuple[torch.Tensor, torch.Tensor]:
    """``(N, H, W)`` mosaics on [0, 1] -> ``(sparse, bilinear)``, each ``(N, 12, H, W)`` float32."""
    mosaic = mosaic.to(torch.float32)
    bilinear = torch.stack([demosaic_dofp_bilinear(m, layout=layout) for m in mosaic])
    return sparse_channels(mosaic, layout), bilinear


def stokes_linear(image: torch.Tensor) -> torch.Tensor:
    """``(N, 12, H, W)`` -> ``(N, 6, H, W)``: S1 = I0 - I90 and S2 = I45 - I135 per colour."""
    n, _, h, w = image.shape
    x = image.reshape(n, 4, 3, h, w)
    return torch.cat([x[:, 0] - x[:, 2], x[:, 1] - x[:, 3]], dim=1)


def cpdnet_loss(outputs: tuple[torch.Tensor, torch.Tensor], target: torch.Tensor, *, intermediate_weight: float = 0.5,
                stokes_weight: float = 0.5) -> torch.Tensor:
    """The multitask loss (module docstring); ``target`` ``(N, 12, H, W)``."""
    final, intermediate = outputs
    loss = F.l1_loss(final, target)
    if intermediate_weight:
        loss = loss + intermediate_weight * F.l1_loss(intermediate, target)
    if stokes_weight:
        loss = loss + stokes_weight * F.l1_loss(stokes_linear(final), stokes_linear(target))
    return loss
