"""Training pairs of the learned baselines, held in memory: network inputs and targets from captures.

Two kinds of input (``input:`` in a training config), each a :class:`PairSet` over the samples of a
capssim dataset (:class:`capssim.dataset.torch.CaptureDataset`, whole captures):

* ``dofp``: the DoFP mosaic ``(H, W)`` as CPDNet reads it, ``(sparse, bilinear)`` ``(12, H, W)``
  each (:func:`capssim.reconstruct.networks.cpdnet.dofp_network_input`); target the ground truth
  ``(12, H, W)``. Crops start on multiples of 4 (the mosaic period).
* ``dofp-igri2``: the DoFP mosaic as ``dofp-nafnet`` reads it, ``(sparse, igri2, noise_std)``
  (:func:`capssim.reconstruct.methods.dofp_nafnet.dofp_nafnet_input`: the IGRI2 demosaicking is
  computed once per sample); target the ground truth. Crops start on multiples of 4.
* ``aperture``: each aperture's raw frame demosaicked as ``caps-sisr`` does (Menon 2007,
  :func:`capssim.reconstruct.methods.caps_naive.demosaic_apertures`), ``(3, h, w)``; target the
  ground truth of that aperture's polarizer angle resampled onto the aperture-HR grid
  ``(3, 2h, 2w)`` (bicubic, through the inverse of the aperture's homography ``H_n``), which is
  where ``caps-sisr`` puts the network's output. Pixels whose source lies within
  :data:`BORDER_HR_PX` of the ground truth's border are masked out of the loss.
* ``noisy-gt``: the ground truth ``(12, H, W)`` with white Gaussian noise added at every step, and the noise
  level, as the denoiser of ``caps-plus-cv`` reads them; target the ground truth
  (:class:`NoisyGtPairs`).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from capssim.errors import InputError

from ..methods.caps_naive import bicubic_warp, demosaic_apertures, sampling_grid
from ..methods.dofp_nafnet import dofp_nafnet_input
from ..networks.cpdnet import cpdnet_loss, dofp_network_input
from ..networks.nafnet import nafnet_loss

INPUT_KINDS = ("dofp", "dofp-igri2", "aperture", "noisy-gt")
#: the inputs read from the DoFP mosaic (crops on multiples of 4, its period)
MOSAIC_INPUT_KINDS = ("dofp", "dofp-igri2")
#: aperture targets read the ground truth at least this far (HR px) inside its border
BORDER_HR_PX = 3.0


class PairSet:
    """Inputs, targets and loss masks of one input kind, as tensors ``(S, C, H, W)`` (S samples)."""

    kind = ""

    def __init__(self, inputs: tuple[torch.Tensor, ...], target: torch.Tensor, mask: torch.Tensor, scale: int):
        self.inputs, self.target, self.mask, self.scale = inputs, target, mask, scale

    def __len__(self) -> int:
        return self.target.shape[0]

    @staticmethod
    def predict(model, inputs):
        """The network's outputs for a tuple of inputs."""
        return model(*inputs)

    @staticmethod
    def image(outputs):
        """The 12-channel (or RGB) image among the outputs."""
        return outputs

    def crops(self, index: torch.Tensor, top: torch.Tensor, left: torch.Tensor, size: int):
        """Inputs, target and mask of the crops ``size`` (input pixels) at (``top``, ``left``) of samples ``index``."""
        s = self.scale
        def cut(t, f):
            return torch.stack([t[i, :, a * f:(a + size) * f, b * f:(b + size) * f]
                                for i, a, b in zip(index.tolist(), top.tolist(), left.tolist())])
        return tuple(cut(t, 1) for t in self.inputs), cut(self.target, s), cut(self.mask, s)

    def draw(self, batch: int, size: int, generator: torch.Generator):
        """A random batch of crops (samples, then offsets on the crop lattice, from ``generator``)."""
        h, w = self.inputs[0].shape[-2:]
        step = self.crop_step
        if size > min(h, w):
            raise InputError("data.crop", size * self.scale, f"at most the captures' size {h * self.scale}",
                             "Use a smaller crop or larger dataset samples.")
        index = torch.randint(len(self), (batch,), generator=generator)
        top = step * torch.randint((h - size) // step + 1, (batch,), generator=generator)
        left = step * torch.randint((w - size) // step + 1, (batch,), generator=generator)
        return self.crops(index, top, left, size)

    def full(self, i: int):
        """Inputs, target and mask of the whole sample ``i`` (a batch of one)."""
        return tuple(t[i:i + 1] for t in self.inputs), self.target[i:i + 1], self.mask[i:i + 1]

    def to(self, device: torch.device) -> "PairSet":
        self.inputs = tuple(t.to(device) for t in self.inputs)
        self.target, self.mask = self.target.to(device), self.mask.to(device)
        return self


class DofpPairs(PairSet):
    kind, crop_step = "dofp", 4

    @staticmethod
    def image(outputs):
        return outputs[0]

    def loss(self, outputs, target, mask, loss_params: dict):
        return cpdnet_loss(outputs, target, **loss_params)

    @staticmethod
    def baseline(inputs):
        """What the network refines: the bilinear demosaicking (``dofp-bilinear``)."""
        return inputs[1]


class DofpIgri2Pairs(PairSet):
    kind, crop_step = "dofp-igri2", 4

    def loss(self, outputs, target, mask, loss_params: dict):
        return nafnet_loss(outputs, target, **loss_params)

    @staticmethod
    def baseline(inputs):
        """What the network refines: the IGRI2 demosaicking (``dofp-igri2``)."""
        return inputs[1]


class AperturePairs(PairSet):
    kind, crop_step = "aperture", 1

    def loss(self, outputs, target, mask, loss_params: dict):
        return (torch.abs(outputs - target) * mask).sum() / (mask.sum() * target.shape[1]).clamp_min(1)

    @staticmethod
    def baseline(inputs):
        """What the network refines: bicubic x2 interpolation (``caps-sisr -p model=bicubic``)."""
        return F.interpolate(inputs[0], scale_factor=2, mode="bicubic", align_corners=False)


class NoisyGtPairs(PairSet):
    """Denoising pairs drawn afresh at every step: a crop of the ground truth, brightened by a gain drawn
    log-uniformly in :data:`GAIN_RANGE` (clipped to [0, 1]; the rendered training scenes are dim, the
    benchmark scenes reach 1), randomly flipped and transposed, plus white noise of a std drawn uniformly in
    ``[0, NOISE_SIGMA_MAX]`` per crop. Inputs ``(noisy, sigma)``, target the clean crop. Validation: each
    whole sample with noise of :data:`VALIDATION_SIGMA` from a generator seeded by its index."""

    kind, crop_step = "noisy-gt", 1
    #: the noise levels of training (std on [0, 1]) and of validation
    NOISE_SIGMA_MAX, VALIDATION_SIGMA = 0.06, 0.02
    GAIN_RANGE = (1.0, 3.0)

    def loss(self, outputs, target, mask, loss_params: dict):
        return F.mse_loss(outputs, target)

    @staticmethod
    def baseline(inputs):
        """What the network refines: the noisy input itself."""
        return inputs[0]

    def draw(self, batch: int, size: int, generator: torch.Generator):
        (clean,), _, mask = super().draw(batch, size, generator)
        low, high = np.log(self.GAIN_RANGE[0]), np.log(self.GAIN_RANGE[1])
        gain = torch.exp(low + (high - low) * torch.rand(batch, 1, 1, 1, generator=generator))
        clean = (clean * gain.to(clean.device)).clamp(0.0, 1.0)
        flips = torch.rand(3, generator=generator)
        clean = clean.flip(-1) if flips[0] < 0.5 else clean
        clean = clean.flip(-2) if flips[1] < 0.5 else clean
        clean = clean.transpose(-1, -2) if flips[2] < 0.5 else clean
        sigma = self.NOISE_SIGMA_MAX * torch.rand(batch, generator=generator)
        noise = torch.randn(clean.shape, generator=generator).to(clean.device)
        noisy = clean + sigma.to(clean.device).reshape(-1, 1, 1, 1) * noise
        return (noisy, sigma.to(clean.device)), clean, mask

    def full(self, i: int):
        (clean,), target, mask = super().full(i)
        noise = torch.randn(clean.shape, generator=torch.Generator().manual_seed(i)).to(clean.device)
        sigma = torch.full((1,), self.VALIDATION_SIGMA, device=clean.device)
        return (clean + self.VALIDATION_SIGMA * noise, sigma), target, mask


def noisy_gt_pairs(items: list[dict]) -> NoisyGtPairs:
    """:class:`NoisyGtPairs` of CaptureDataset items (their ground truths)."""
    target = torch.stack([item["gt"].to(torch.float32) for item in items])
    return NoisyGtPairs((target,), target, torch.ones_like(target[:, :1]), 1)


def _require_mosaic(item: dict, kind: str) -> None:
    """Refuse a CaptureDataset item without a DoFP mosaic for a mosaic input ``kind``."""
    if "dofp_raw" not in item:
        raise InputError("input", kind, "captures with a DoFP mosaic (dofp_raw.tiff)",
                         "Generate the dataset with its DoFP captures, or use input: aperture.")


def dofp_pairs(items: list[dict]) -> DofpPairs:
    """:class:`DofpPairs` of CaptureDataset items (whole captures with ``dofp_raw`` and ``gt``)."""
    sparse, bilinear = [], []
    for item in items:
        _require_mosaic(item, "dofp")
        s, b = dofp_network_input(item["dofp_raw"][None], [r.tolist() for r in item["dofp_layout"]])
        sparse.append(s[0])
        bilinear.append(b[0])
    target = torch.stack([item["gt"] for item in items])
    return DofpPairs((torch.stack(sparse), torch.stack(bilinear)), target, torch.ones_like(target[:, :1]), 1)


def dofp_igri2_pairs(items: list[dict]) -> DofpIgri2Pairs:
    """:class:`DofpIgri2Pairs` of CaptureDataset items: ``(sparse, igri2, noise_std)`` of each whole mosaic
    (IGRI2 computed once per sample, here) and the ground truth."""
    inputs = []
    for item in items:
        _require_mosaic(item, "dofp-igri2")
        inputs.append(dofp_nafnet_input(item["dofp_raw"][None], [r.tolist() for r in item["dofp_layout"]],
                                        item["dofp_noise_std"][None]))
    target = torch.stack([item["gt"] for item in items])
    stacked = tuple(torch.cat([x[i] for x in inputs]) for i in range(3))
    return DofpIgri2Pairs(stacked, target, torch.ones_like(target[:, :1]), 1)


def aperture_targets(gt: torch.Tensor, homographies: np.ndarray, hr_shape) -> tuple[torch.Tensor, torch.Tensor]:
    """``(4, 3, H, W)`` targets on the aperture-HR grids and ``(4, 1, H, W)`` masks of a ``(12, H, W)`` GT."""
    inverse = np.linalg.inv(np.asarray(homographies, dtype=np.float64))
    per_angle = gt.reshape(4, 3, *gt.shape[-2:]).to(torch.float32)
    target = bicubic_warp(per_angle, inverse, tuple(hr_shape))
    grid = sampling_grid(inverse, tuple(hr_shape), tuple(gt.shape[-2:]), gt.device)  # normalized, align_corners
    h, w = gt.shape[-2:]
    margin = torch.tensor([2 * BORDER_HR_PX / max(w - 1, 1), 2 * BORDER_HR_PX / max(h - 1, 1)])
    inside = (grid.abs() <= 1 - margin).all(dim=-1)
    return target, inside[:, None].to(torch.float32)


def aperture_pairs(items: list[dict]) -> AperturePairs:
    """:class:`AperturePairs` of CaptureDataset items: 4 pairs per capture."""
    inputs, targets, masks = [], [], []
    for item in items:
        raw = item["caps_raw"].numpy()
        inputs.append(torch.from_numpy(demosaic_apertures(raw, bayer_method="menon2007")))
        t, m = aperture_targets(item["gt"], item["aperture_homographies"].numpy(), item["gt"].shape[-2:])
        targets.append(t)
        masks.append(m)
    return AperturePairs((torch.cat(inputs),), torch.cat(targets), torch.cat(masks), 2)


def build_pairs(kind: str, items: list[dict]) -> PairSet:
    if kind not in INPUT_KINDS:
        raise InputError("input", kind, " or ".join(INPUT_KINDS))
    return {"dofp": dofp_pairs, "dofp-igri2": dofp_igri2_pairs, "aperture": aperture_pairs,
            "noisy-gt": noisy_gt_pairs}[kind](items)


def masked_psnr(image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR (dB, peak 1) over the pixels of ``mask`` (broadcast over channels)."""
    weight = mask.expand_as(target)
    mse = float(((image.clamp(0, 1) - target) ** 2 * weight).sum() / weight.sum().clamp_min(1))
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


__all__ = ["INPUT_KINDS", "MOSAIC_INPUT_KINDS", "NoisyGtPairs", "PairSet", "build_pairs", "masked_psnr"]
