"""Registration images of the four apertures (paper section 3.1, registration: step 1).

The four RGGB sub-images of aperture n are put back into its raw mosaic ``(H, W)``
(:func:`mosaic_from_sub_images`), and each mosaic becomes one grey registration image:

- ``binomial`` (:func:`binomial_luminance`): the mosaic filtered with the 3x3 binomial kernel
  ``[1 2 1; 2 4 2; 1 2 1] / 16``. On an RGGB mosaic this returns the luminance
  ``(R + 2G + B) / 4`` of locally constant colour at every raw pixel, whatever its Bayer phase:
  no demosaicking, and for grey content the same linear blur in every aperture. At colour
  edges the mosaic's chroma carriers leak into it as a pattern tied to the sensor grid,
  different in each aperture.
- ``ri-binomial`` (:func:`ri_binomial_luminance`): the luminance ``(R + 2G + B) / 4`` of the
  residual-interpolation demosaicking (Kiku et al., IEEE TIP 2016) filtered with the same
  kernel: ``binomial`` minus the leak as the demosaicking estimates it; worse where the
  demosaicking errs (aliased high-frequency texture).

Raw pixels with a saturated sample in their 3x3 neighbourhood are left out
(:func:`usable_pixels`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from capssim.conventions import BAYER_OFFSETS, N_APERTURES

from ..dofp.residual_interpolation import ri_bayer_demosaic_frames


def mosaic_from_sub_images(sub: torch.Tensor) -> torch.Tensor:
    """``(16, h, w)`` Bayer sub-images ``m = 4n + q`` -> ``(4, 2h, 2w)`` RGGB raw mosaics."""
    _, h, w = sub.shape
    raw = sub.new_zeros(N_APERTURES, 2 * h, 2 * w)
    for q, (oy, ox) in enumerate(BAYER_OFFSETS):
        raw[:, oy::2, ox::2] = sub[q::4]
    return raw


def binomial_luminance(raw: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` RGGB mosaics -> ``(B, H, W)`` luminance ``(R + 2G + B) / 4`` (3x3 binomial filter).

    The border is mirrored (row -1 = row 1: the same Bayer parity, so colours stay in place).
    """
    k = torch.tensor([1.0, 2.0, 1.0], dtype=raw.dtype, device=raw.device)
    k = (k[:, None] * k[None, :]) / 16.0
    x = F.pad(raw[:, None], (1, 1, 1, 1), mode="reflect")
    return F.conv2d(x, k[None, None])[:, 0]


def ri_binomial_luminance(raw: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` RGGB mosaics -> ``(B, H, W)``: 3x3 binomial filter of the luminance ``(R + 2G + B) / 4``
    of the residual-interpolation demosaicking
    (:func:`capssim.reconstruct.dofp.residual_interpolation.ri_bayer_demosaic_frames`: ``dofp-eari``'s colour
    stage, any size).
    """
    rgb = ri_bayer_demosaic_frames(raw)
    return binomial_luminance((rgb[:, 0] + 2 * rgb[:, 1] + rgb[:, 2]) / 4)


#: registration images of the raw mosaics (``RegistrationParameters.luminance``)
LUMINANCE_METHODS = {"ri-binomial": ri_binomial_luminance, "binomial": binomial_luminance}


def usable_pixels(saturated_raw: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` 1 where no raw pixel of the 3x3 neighbourhood is saturated, else 0 (dtype of the input)."""
    return (F.max_pool2d(saturated_raw[:, None], 3, stride=1, padding=1)[:, 0] <= 0).to(saturated_raw.dtype)
