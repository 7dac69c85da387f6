"""Colour-polarized image rearrangement (paper section 3.1).

The four RGGB raw frames of the camera array (one per polarizer angle) are split into
16 low-resolution images observing 12 channels: image ``m = 4*n + q`` is Bayer site
``q`` in (R, G1, G2, B) of aperture ``n`` (polarizer ``45*n`` deg) and observes channel
``c(m) = 3*n + colour(q)``. The two G images of one aperture stay separate: their
sampling positions differ by the Bayer offset, and that offset is information.

Sub-image pixel ``(u, v)`` is raw pixel ``(2u + oy, 2v + ox)`` with ``(oy, ox)`` the site's
offset in the 2x2 cell: R (0, 0), G1 (0, 1), G2 (1, 0), B (1, 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from capssim.conventions import N_CHANNELS, lr_image_channels, split_bayer
from capssim.errors import InputError


@dataclass
class Observations:
    """Low-resolution observations and how they map to the channels to reconstruct.

    ``images`` ``(N, h, w)`` float32 on [0, 1]; ``weights`` ``(N, h, w)`` data weights
    (0 for saturated pixels, 1 elsewhere); ``channel_of`` ``(N,)`` int64, the channel each
    image observes; ``n_channels`` the number of channels of the HR image.
    """

    images: torch.Tensor
    weights: torch.Tensor
    channel_of: torch.Tensor
    n_channels: int

    @property
    def count(self) -> int:
        return int(self.images.shape[0])

    def to(self, device) -> "Observations":
        return Observations(self.images.to(device), self.weights.to(device), self.channel_of.to(device), self.n_channels)

    def images_per_channel(self) -> torch.Tensor:
        """``(n_channels,)`` number of images observing each channel."""
        return torch.bincount(self.channel_of, minlength=self.n_channels)


def rearrange_raw(raw, saturated=None, *, device="cpu", cfa: str = "RGGB") -> Observations:
    """Rearrange four float Bayer frames ``(4, H, W)`` into the 16 observations (section 3.1).

    ``cfa`` (RGGB, BGGR, GRBG or GBRG) sets the channel each site observes; the sites keep their
    positions (their homographies), so any pattern is modelled exactly.

    ``saturated`` is an optional boolean ``(4, H, W)`` mask; saturated pixels get weight 0.
    """
    arr = np.asarray(raw)
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError("raw", f"dtype {arr.dtype}", "float frames on [0, 1] (use Sensor.to_float)")
    if not np.all(np.isfinite(arr)):
        raise InputError("raw", f"{int(np.sum(~np.isfinite(arr)))} NaN/inf values", "finite values")
    images = split_bayer(arr)
    if saturated is None:
        weights = np.ones_like(images, dtype=np.float32)
    else:
        sat = np.asarray(saturated)
        if sat.shape != arr.shape:
            raise InputError("saturated", f"shape {sat.shape}", f"the raw shape {arr.shape}")
        weights = (~split_bayer(sat.astype(bool), argument="saturated")).astype(np.float32)
    return Observations(
        images=torch.as_tensor(images, dtype=torch.float32, device=device),
        weights=torch.as_tensor(weights, dtype=torch.float32, device=device),
        channel_of=torch.as_tensor(lr_image_channels(cfa), dtype=torch.int64, device=device),
        n_channels=N_CHANNELS,
    )


def observations_from_capture(capture, *, device="cpu") -> Observations:
    """The 16 observations of a :class:`~capssim.captures.capture.Capture` (raw converted to [0, 1])."""
    return rearrange_raw(capture.caps_float(), capture.caps_saturated(), device=device, cfa=capture.cfa)


__all__ = ["Observations", "observations_from_capture", "rearrange_raw"]
