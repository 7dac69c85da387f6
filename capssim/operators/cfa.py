"""Colour-filter-array sampling (paper D_spectral): Bayer RGGB and the DoFP quad mosaic.

* :class:`ChannelSample`: ``y[..., i, j] = x[..., map[i, j], i, j]``; the generic CFA.
* :class:`BayerMosaic`: RGB ``(B, 3, H, W)`` -> RGGB raw ``(B, H, W)``.
* :class:`BayerSplit`: raw ``(B, H, W)`` -> Bayer sub-images ``(B, 4, H/2, W/2)`` in site
  order R, G1, G2, B (paper section 3.1, rearrangement). A permutation.
* :class:`DoFPMosaic`: 12-channel ``(12, H, W)`` -> colour-polarization mosaic ``(H, W)``.
"""

from __future__ import annotations

import numpy as np
import torch

from capssim.conventions import DEFAULT_DOFP_LAYOUT, N_CHANNELS, bayer_channel_map, dofp_channel_map
from capssim.errors import InputError
from capssim.operators.base import LinearOperator


class ChannelSample(LinearOperator):
    """Sample one channel per pixel: ``(*lead, C, H, W) -> (*lead, H, W)``; ``channel_map`` is ``(H, W)``."""

    name = "channel_sample"

    def __init__(self, channel_map, input_shape: tuple[int, ...]):
        cmap = np.asarray(channel_map, dtype=np.int64)
        c, h, w = input_shape[-3:]
        if cmap.shape != (h, w) or cmap.min() < 0 or cmap.max() >= c:
            raise InputError("channel_map", f"shape {cmap.shape}", f"shape {(h, w)} with values in [0, {c})")
        super().__init__(input_shape, (*input_shape[:-3], h, w))
        self.index = torch.as_tensor(cmap)[None, None]

    def _forward(self, x):
        c, h, w = self.input_shape[-3:]
        flat = x.reshape(-1, c, h, w)
        idx = self._const("i", self.index, x).expand(flat.shape[0], 1, h, w)
        return torch.gather(flat, 1, idx).reshape(self.output_shape)

    def _adjoint(self, y):
        c, h, w = self.input_shape[-3:]
        flat = y.reshape(-1, 1, h, w)
        idx = self._const("i", self.index, y).expand(flat.shape[0], 1, h, w)
        out = y.new_zeros(flat.shape[0], c, h, w)
        out.scatter_(1, idx, flat)
        return out.reshape(self.input_shape)


class BayerMosaic(ChannelSample):
    """RGGB Bayer sampling, ``(*lead, 3, H, W) -> (*lead, H, W)``; R at raw (0, 0)."""

    name = "bayer_mosaic"

    def __init__(self, input_shape: tuple[int, ...]):
        h, w = input_shape[-2:]
        if input_shape[-3] != 3:
            raise InputError("input_shape", input_shape, "(..., 3, H, W) RGB")
        super().__init__(bayer_channel_map(h, w), input_shape)


class DoFPMosaic(ChannelSample):
    """Colour-polarization DoFP sampling ``(12, H, W) -> (H, W)`` with a 2x2 polarizer ``layout``."""

    name = "dofp_mosaic"

    def __init__(self, height: int, width: int, *, layout=DEFAULT_DOFP_LAYOUT):
        super().__init__(dofp_channel_map(height, width, layout), (N_CHANNELS, height, width))
        self.layout = layout


class BayerSplit(LinearOperator):
    """Raw ``(B, H, W)`` -> Bayer sub-images ``(B, 4, H/2, W/2)``; site q at raw offset ``(q // 2, q % 2)``."""

    name = "bayer_split"

    def __init__(self, input_shape: tuple[int, int, int]):
        b, h, w = input_shape
        if h % 2 or w % 2:
            raise InputError("input_shape", input_shape, "even raw height and width", "Crop one row/column.")
        super().__init__(input_shape, (b, 4, h // 2, w // 2))

    def _forward(self, x):
        b, h, w = self.input_shape
        return x.reshape(b, h // 2, 2, w // 2, 2).permute(0, 2, 4, 1, 3).reshape(self.output_shape).contiguous()

    def _adjoint(self, y):
        b, h, w = self.input_shape
        return y.reshape(b, 2, 2, h // 2, w // 2).permute(0, 3, 1, 4, 2).reshape(self.input_shape).contiguous()
