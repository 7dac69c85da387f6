"""A NAFNet-style U-Net that refines an IGRI2 demosaicking of a colour-polarization DoFP mosaic.

References:

* L. Chen, X. Chu, X. Zhang, J. Sun, "Simple Baselines for Image Restoration", ECCV 2022 (NAFNet):
  the block (layer norm, 1x1 expansion, 3x3 depthwise convolution, SimpleGate, simplified channel
  attention, 1x1 projection, learned residual scales initialised to zero) and the U-Net around it;
* M. Morimatsu, Y. Monno, M. Tanaka, M. Okutomi, IEEE Sensors Journal 21(23) 2021 (IGRI2): the
  classical demosaicking the network starts from (``dofp-igri2``);
* residual learning over a classical demosaicking and a noise-level input map, as in the learned
  DoFP demosaickers of the field (e.g. Nguyen et al., "Two-step colour-polarization demosaicking
  network", ICIP 2022 (TCPDNet); Zhang et al., FFDNet, IEEE TIP 27(9) 2018 for the noise map).

Built here from those descriptions. Input, for ``N`` mosaics ``(N, H, W)`` (H, W multiples of 4):

* ``sparse`` ``(N, 12, H, W)``: each mosaic sample in its channel ``c = 3p + k``, zero elsewhere
  (:func:`capssim.reconstruct.networks.cpdnet.sparse_channels`): the CFA/polarizer pattern;
* ``base`` ``(N, 12, H, W)``: the IGRI2 demosaicking of the mosaic;
* ``noise_std`` ``(N, 1, H, W)``: the sensor's noise std at each sample (on [0, 1]).

The three are stacked (25 channels), folded 2x2 into channels (100 channels at ``H/2``), run
through a 4-level U-Net of NAFNet blocks (widths ``w, 2w, 4w`` and ``8w`` in the middle) and
unfolded back: the output is ``base + residual`` ``(N, 12, H, W)``. The last convolution starts at
zero, so an untrained network returns IGRI2. Sizes are padded (reflect) to multiples of 16.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .cpdnet import stokes_linear

#: the padding multiple of the input (2x2 fold, then three 2x downsamplings)
SIZE_MULTIPLE = 16
INPUT_CHANNELS = 25


class LayerNorm2d(nn.Module):
    """Layer normalization over the channels of ``(N, C, H, W)``, with a per-channel scale and shift."""

    def __init__(self, channels: int, eps: float = 1e-6):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = x.mean(dim=1, keepdim=True)
        var = (x - mean).pow(2).mean(dim=1, keepdim=True)
        x = (x - mean) / torch.sqrt(var + self.eps)
        return x * self.weight[:, None, None] + self.bias[:, None, None]


class NAFBlock(nn.Module):
    """One NAFNet block on ``(N, c, H, W)`` (Chen et al. 2022, fig. 3c): a gated depthwise branch with
    simplified channel attention, then a gated 1x1 feed-forward branch, each added with a learned
    per-channel scale that starts at zero (so a new block is the identity)."""

    def __init__(self, channels: int):
        super().__init__()
        c = channels
        self.norm1, self.norm2 = LayerNorm2d(c), LayerNorm2d(c)
        self.expand = nn.Conv2d(c, 2 * c, 1)
        self.depthwise = nn.Conv2d(2 * c, 2 * c, 3, padding=1, groups=2 * c)
        self.attention = nn.Conv2d(c, c, 1)
        self.project = nn.Conv2d(c, c, 1)
        self.ffn_expand = nn.Conv2d(c, 2 * c, 1)
        self.ffn_project = nn.Conv2d(c, c, 1)
        self.beta = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.gamma = nn.Parameter(torch.zeros(1, c, 1, 1))

    @staticmethod
    def gate(x: torch.Tensor) -> torch.Tensor:
        """SimpleGate: the two halves of the channels multiplied."""
        a, b = x.chunk(2, dim=1)
        return a * b

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.gate(self.depthwise(self.expand(self.norm1(x))))
        y = y * self.attention(y.mean(dim=(2, 3), keepdim=True))
        x = x + self.beta * self.project(y)
        y = self.ffn_project(self.gate(self.ffn_expand(self.norm2(x))))
        return x + self.gamma * y


def blocks(channels: int, count: int) -> nn.Sequential:
    return nn.Sequential(*[NAFBlock(channels) for _ in range(count)])


class DofpNAFNet(nn.Module):
    """``(sparse, base, noise_std)`` -> ``(N, 12, H, W)`` (module docstring).

    ``width``: channels at the top level (``H/2``); ``encoder_blocks`` / ``decoder_blocks``: blocks per level,
    top first (three levels); ``middle_blocks``: blocks at ``H/16``.
    """

    #: what the network reads: the DoFP mosaic with its IGRI2 demosaicking and noise map
    input_kind = "dofp-igri2"

    def __init__(self, *, width: int = 24, encoder_blocks: tuple[int, ...] | list[int] = (1, 1, 2),
                 middle_blocks: int = 2, decoder_blocks: tuple[int, ...] | list[int] = (1, 1, 1)):
        super().__init__()
        if len(encoder_blocks) != 3 or len(decoder_blocks) != 3:
            raise TypeError("encoder_blocks and decoder_blocks take three counts (one per level)")
        widths = [width, 2 * width, 4 * width]
        self.intro = nn.Conv2d(4 * INPUT_CHANNELS, width, 3, padding=1)
        self.encoders = nn.ModuleList(blocks(c, n) for c, n in zip(widths, encoder_blocks))
        self.downs = nn.ModuleList(nn.Conv2d(c, 2 * c, 2, stride=2) for c in widths)
        self.middle = blocks(8 * width, middle_blocks)
        self.ups = nn.ModuleList(nn.Sequential(nn.Conv2d(2 * c, 4 * c, 1), nn.PixelShuffle(2)) for c in widths)
        self.decoders = nn.ModuleList(blocks(c, n) for c, n in zip(widths, decoder_blocks))
        self.ending = nn.Conv2d(width, 4 * 12, 3, padding=1)
        nn.init.zeros_(self.ending.weight)
        nn.init.zeros_(self.ending.bias)

    def forward(self, sparse: torch.Tensor, base: torch.Tensor, noise_std: torch.Tensor) -> torch.Tensor:
        h, w = base.shape[-2:]
        x = torch.cat([sparse, base, noise_std], dim=1)
        ph, pw = -h % SIZE_MULTIPLE, -w % SIZE_MULTIPLE
        if ph or pw:  # reflect needs the pad below the size: replicate covers tiny inputs
            x = F.pad(x, (0, pw, 0, ph), mode="reflect" if ph < h and pw < w else "replicate")
        x = self.intro(F.pixel_unshuffle(x, 2))
        skips = []
        for encoder, down in zip(self.encoders, self.downs):
            x = encoder(x)
            skips.append(x)
            x = down(x)
        x = self.middle(x)
        for decoder, up, skip in zip(reversed(self.decoders), reversed(self.ups), reversed(skips)):
            x = decoder(up(x) + skip)
        residual = F.pixel_shuffle(self.ending(x), 2)[..., :h, :w]
        return base + residual


def nafnet_loss(output: torch.Tensor, target: torch.Tensor, *, stokes_weight: float = 0.5) -> torch.Tensor:
    """``L1(output) + stokes_weight L1(S1, S2 of output)`` (``(N, 12, H, W)`` each): the intensity term and
    the polarization-aware term of CPDNet's loss (:func:`capssim.reconstruct.networks.cpdnet.cpdnet_loss`)."""
    loss = F.l1_loss(output, target)
    if stokes_weight:
        loss = loss + stokes_weight * F.l1_loss(stokes_linear(output), stokes_linear(target))
    return loss
