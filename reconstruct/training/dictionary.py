"""Learning the joint colour-polarization dictionary of ``dofp-jcpd`` (``capssim train``, ``network: jcpd-dictionary``).

JCPD (Wen, Zheng, Lu, IEEE TIP 30 2021) codes each ``P x P x 12`` patch of the mosaic over a
dictionary learned from full 12-channel images. Here it is learned from the ground truths of a
capssim dataset by the method of optimal directions
(:func:`capssim.reconstruct.priors.sparse_coding.learn_dictionary`, Engan, Aase, Husoy 1999):

1. patches: every ``P x P`` window (stride 4) of the training samples' ground truths ``(12, H, W)``,
   vectorized as ``dofp-jcpd`` does (channel, row, column); their projection on the 9 spatially
   constant joint atoms (the local mean colour-polarization state) is removed, nearly flat
   patches (residual norm below 1e-3) are dropped, and ``patches`` of them are drawn with the seed;
2. ``schedule.steps`` MOD iterations of OMP coding (``sparsity`` atoms) and the least-squares
   dictionary update, ``atoms`` atoms, from patches drawn with the seed;
3. the dictionary ``D`` ``(12 P^2, 9 + atoms)``: the 9 constant atoms, then the learned atoms made
   orthogonal to them (so constant images stay exact in ``dofp-jcpd``).

Validation: ``dofp-jcpd`` PSNR on the held-out samples' DoFP mosaics, with the learned and with the
analytic dictionary. Output ``RUN/dictionary.npz`` (arrays ``D`` and ``record``, a JSON string),
written atomically; there is no checkpoint (the learning takes minutes), a rerun starts again.
"""

from __future__ import annotations

import io
import json
import time

import numpy as np
import torch
import torch.nn.functional as F

from capssim.dataset.torch import CaptureDataset
from capssim.errors import InputError
from capssim.files.imageio import atomic_write_bytes, atomic_write_json

from ..methods.dofp_jcpd import demosaic_dofp_jcpd
from ..priors.sparse_coding import constant_atoms, joint_dictionary, learn_dictionary
from .config import DICTIONARY_DEFAULTS

DICTIONARY_FILE = "dictionary.npz"


def training_patches(gts: list[torch.Tensor], patch: int, count: int, generator: torch.Generator,
                     constant: torch.Tensor) -> torch.Tensor:
    """``(count, 12 patch^2)`` float64 ground-truth patches with their constant part removed."""
    rows = [F.unfold(gt[None].double(), patch, stride=4)[0].T for gt in gts]
    x = torch.cat(rows)
    x = x - (x @ constant) @ constant.T
    x = x[x.norm(dim=1) > 1e-3]
    if x.shape[0] < count:
        raise InputError("model.patches", count, f"at most the {x.shape[0]} textured patches of the training samples",
                         "Use fewer patches or a larger dataset.")
    return x[torch.randperm(x.shape[0], generator=generator)[:count]]


def jcpd_psnr(items: list[dict], dictionary) -> float:
    """Mean PSNR (dB) of ``dofp-jcpd`` on the DoFP mosaics of ``items`` with ``dictionary``."""
    values = []
    for item in items:
        layout = [r.tolist() for r in item["dofp_layout"]]
        image = demosaic_dofp_jcpd(item["dofp_raw"].numpy(), layout=layout, dictionary=dictionary)
        mse = float(np.mean((np.clip(image, 0, 1) - item["gt"].numpy()) ** 2))
        values.append(10 * np.log10(1.0 / max(mse, 1e-12)))
    return float(np.mean(values))


def learn_jcpd_dictionary(config, run, *, say=print) -> dict:
    """Learn the dictionary of ``config`` (a TrainConfig with network jcpd-dictionary) into ``run``."""
    t0 = time.perf_counter()
    params = {**DICTIONARY_DEFAULTS, **config.network_params}
    patch, atoms = int(params["patch"]), int(params["atoms"])
    items = CaptureDataset(config.dataset_root, crop=None, load_dofp=True)
    split = len(items) - config.validation
    generator = torch.Generator().manual_seed(config.seed)
    constant = joint_dictionary(patch)[:, constant_atoms(joint_dictionary(patch))]
    x = training_patches([items[i]["gt"] for i in range(split)], patch, int(params["patches"]), generator, constant)
    say(f"dictionary: {x.shape[0]} patches of {patch}x{patch}x12, {atoms} atoms, {config.schedule['steps']} MOD steps")
    learned, errors = learn_dictionary(x, atoms=atoms, sparsity=int(params["sparsity"]),
                                       iterations=config.schedule["steps"], generator=generator)
    learned = learned - constant @ (constant.T @ learned)
    d = torch.cat([constant, learned / learned.norm(dim=0).clamp_min(1e-30)], dim=1).numpy().astype(np.float32)
    validation = [items[i] for i in range(split, len(items))]
    record = {"config": config.to_dict(), "fingerprint": config.fingerprint(), "params": params,
              "representation_error": errors, "validation_psnr_db": jcpd_psnr(validation, d),
              "validation_analytic_psnr_db": jcpd_psnr(validation, "analytic"),
              "torch": str(torch.__version__), "threads": torch.get_num_threads(), "wall_s": time.perf_counter() - t0}
    buffer = io.BytesIO()
    np.savez(buffer, D=d, record=np.array(json.dumps(record)))
    atomic_write_bytes(run / DICTIONARY_FILE, buffer.getvalue())
    atomic_write_json(run / "history.json", {"representation_error": errors})
    return record
