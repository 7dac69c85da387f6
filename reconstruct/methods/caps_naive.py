"""``caps-naive``: the plain camera-array pipeline (paper section 5.2, the naive baseline).

Reference: the naive pipeline of the CAPS paper (Optics Express 32(2) 2364, 2024, section 5.2):
"demosaic each aperture, register, bicubic x2". Bayer demosaicking: Menon, Andriani, Calvagno,
"Demosaicing with directional filtering and a posteriori decision", IEEE TIP 16(1), 2007
(``colour-demosaicing``), or the bilinear / Malvar 2004 demosaickers of the same package.

1. each aperture's RGGB raw frame ``(H, W)`` is demosaicked on its own -> ``(3, H, W)``;
2. the aperture homographies come from the CAPS registration (``reconstruct.registration``)
   or from ``meta.json`` with ``--true-warps`` (the same helper as ``caps``);
3. every HR reference pixel ``x`` (grid ``2H x 2W``) is mapped to raw coordinates of aperture
   ``n`` by ``R @ H_n`` (:func:`capssim.homography.raw_matrix`) and the demosaicked frame is
   sampled there with bicubic interpolation (Keys, a = -0.75; ``torch.grid_sample``), i.e.
   registration and the x2 upsampling are one resampling. Channel ``c = 3 n + k``.

No denoising and no use of the other apertures' samples: it is what a camera-array user
gets without a joint reconstruction. Pixels mapped outside a frame take the border value.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from capssim.conventions import N_APERTURES
from capssim.errors import UnknownNameError
from reconstruct.registry import MethodOutput, RunContext, register_method

#: Bayer demosaickers of colour-demosaicing selectable with ``-O bayer_method=NAME``
BAYER_METHODS = {"menon2007": "demosaicing_CFA_Bayer_Menon2007",
                 "malvar2004": "demosaicing_CFA_Bayer_Malvar2004",
                 "bilinear": "demosaicing_CFA_Bayer_bilinear"}


def demosaic_bayer_frames(raw: np.ndarray, *, method: str = "menon2007") -> np.ndarray:
    """``(N, H, W)`` RGGB raw frames on [0, 1] -> ``(N, 3, H, W)`` float32 RGB (clipped to [0, 1])."""
    import colour_demosaicing

    if method not in BAYER_METHODS:
        raise UnknownNameError("bayer_method", method, list(BAYER_METHODS))
    fn = getattr(colour_demosaicing, BAYER_METHODS[method])
    rgb = np.stack([np.moveaxis(fn(frame.astype(np.float64), "RGGB"), -1, 0) for frame in raw])
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def resample_bicubic(images: torch.Tensor, raw_homographies: np.ndarray, hr_shape: tuple[int, int]) -> torch.Tensor:
    """Sample ``(N, K, H, W)`` frames on the HR reference grid: ``(N, K, 2H', 2W')``.

    ``raw_homographies`` ``(N, 3, 3)`` map HR reference pixel ``(x=col, y=row)`` to frame pixel
    coordinates (pixel centres on integers). Bicubic, border padding, device of ``images``.
    """
    n, _, h, w = images.shape
    hh, ww = hr_shape
    dtype, dev = torch.float64, images.device
    ys, xs = torch.meshgrid(torch.arange(hh, dtype=dtype, device=dev), torch.arange(ww, dtype=dtype, device=dev),
                            indexing="ij")
    pts = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(-1, 3)
    hmat = torch.as_tensor(np.asarray(raw_homographies), dtype=dtype, device=dev)
    mapped = torch.einsum("nij,pj->npi", hmat, pts)
    u = mapped[..., 0] / mapped[..., 2]
    v = mapped[..., 1] / mapped[..., 2]
    grid = torch.stack([2 * u / max(w - 1, 1) - 1, 2 * v / max(h - 1, 1) - 1], -1).reshape(n, hh, ww, 2)
    return F.grid_sample(images, grid.to(images.dtype), mode="bicubic", padding_mode="border", align_corners=True)


@register_method("caps-naive", input_kind="caps",
                 reference="CAPS paper section 5.2 (naive pipeline); Menon et al., IEEE TIP 16(1) 2007",
                 description="Naive camera array: demosaic each aperture (Menon 2007), register, bicubic x2 "
                             "(one resampling)")
def caps_naive(capture, *, context: RunContext) -> MethodOutput:
    from capssim.homography import aperture_from_lr, raw_matrix
    from reconstruct.methods.caps import lr_homographies

    options = dict(context.options)
    bayer_method = str(options.pop("bayer_method", "menon2007")).lower()
    if bayer_method not in BAYER_METHODS:
        raise UnknownNameError("bayer_method", bayer_method, list(BAYER_METHODS))
    options.pop("iterations", None)  # no iterations: accepted so 'reconstruct -m all --iterations N' works
    if options:
        raise UnknownNameError("caps-naive option", sorted(options)[0], ["bayer_method"])
    timer, dev = context.timer, context.device
    with timer.stage("demosaic"):
        rgb = demosaic_bayer_frames(capture.caps_float(), method=bayer_method)
        lr_images, lr_saturated = capture.lr_images()
    with timer.stage("registration"):
        homographies, reg_record = lr_homographies(capture, context, images=lr_images, saturated=lr_saturated)
        aperture_h = aperture_from_lr(homographies)[0::4]
        raw_h = np.stack([raw_matrix() @ h for h in aperture_h])
    with timer.stage("resample"):
        frames = torch.as_tensor(rgb, device=dev)
        hr = resample_bicubic(frames, raw_h, capture.hr_shape).clamp_(0.0, 1.0)
        image = hr.reshape(N_APERTURES * 3, *capture.hr_shape)  # c = 3 n + k
    with timer.stage("to_host"):
        out = image.cpu().numpy().astype(np.float32)
    params = {"bayer_method": bayer_method, "upsampling": "bicubic (Keys a=-0.75), one resampling"}
    return MethodOutput(image=out, params=params, extra={"registration": reg_record})
