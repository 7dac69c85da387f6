"""What the CAPS methods record against the ground truth while they run, when a capture carries one.

Diagnostics only (``init_psnr_db``, ``psnr_db``, ``-p track_psnr=true``): never used by the algorithm;
the scores are :func:`capssim.eval.metrics.score`'s.
"""

from __future__ import annotations

import torch

__all__ = ["channel_mean_psnr", "mean_psnr", "psnr_observer"]


def channel_mean_psnr(image: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean over the channels of the PSNR (dB, data range 1, ``image`` clipped to [0, 1]).

    Parameters
    ----------
    image, gt : torch.Tensor
        ``(C, H, W)`` on the same device.

    Returns
    -------
    float
        The mean of the C per-channel PSNRs, in dB.
    """
    mse = (image.clamp(0, 1) - gt).square().mean(dim=(-2, -1)).clamp(min=1e-20)
    return float((-10 * torch.log10(mse)).mean())


def psnr_observer(capture, device, channels: slice = slice(None)):
    """A solver observer recording :func:`channel_mean_psnr` per iteration (``None`` without ground truth).

    Parameters
    ----------
    capture : Capture
        The capture; ``capture.gt`` ``(12, H, W)`` or ``None``.
    device : torch.device
        Where the solver's iterates live.
    channels : slice
        The output channels the solver's image holds (a problem's ``channels``).

    Returns
    -------
    callable or None
        ``observer(iteration, image) -> {"psnr_db": float}``.
    """
    if capture.gt is None:
        return None
    gt = torch.as_tensor(capture.gt, dtype=torch.float32, device=device)[channels]
    return lambda i, x: {"psnr_db": channel_mean_psnr(x, gt)}


def mean_psnr(capture, image: torch.Tensor) -> float | None:
    """:func:`channel_mean_psnr` of ``image`` ``(12, H, W)`` against the capture's ground truth (None without one)."""
    if capture.gt is None:
        return None
    return channel_mean_psnr(image, torch.as_tensor(capture.gt, dtype=torch.float32, device=image.device))
