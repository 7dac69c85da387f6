"""A PyTorch ``Dataset`` over generated captures, with crops aligned across GT, raw and DoFP grids.

Usage::

    from torch.utils.data import DataLoader
    from capssim.dataset.torch import CaptureDataset

    train = CaptureDataset("runs/my-dataset", crop=64)          # random aligned 64x64 HR crops
    for batch in DataLoader(train, batch_size=8, shuffle=True, num_workers=2):
        raw, gt = batch["caps_raw"], batch["gt"]                # (8, 4, 32, 32), (8, 12, 64, 64)

Item (a dict; every array is a tensor, so the default ``collate_fn`` batches it):

==========================  =====================  ==============================================
key                         shape, dtype           meaning
==========================  =====================  ==============================================
``caps_raw``                (4, h, w) float32      raw RGGB frames on [0, 1] full scale (``Sensor.to_float``)
``caps_saturated``          (4, h, w) bool         clipped pixels (give them weight 0)
``lr_images``               (16, h/2, w/2) float32 the 16 Bayer sub-images, ``m = 4n + q``
``dofp_raw``                (2h, 2w) float32       DoFP mosaic on [0, 1] (if the capture has one)
``dofp_saturated``          (2h, 2w) bool
``dofp_noise_std``          (2h, 2w) float32       the sensor's noise std at each DoFP sample (:func:`~capssim.camera.sensor.noise_std_map`)
``gt``                      (12, 2h, 2w) float32   ground truth, ``c = 3p + k``
``aperture_homographies``   (4, 3, 3) float64      HR reference -> aperture-HR, in crop coordinates
``lr_homographies``         (16, 3, 3) float64     HR reference -> sub-image pixel, in crop coordinates
``crop_offset_hr``          (2,) int64             (row, col) of the crop's top-left HR pixel
``dofp_layout``             (2, 2) int64           polarizer angles (deg) of the DoFP 2x2 cell
``noise_sigma``             () float32             noise std on [0, 1] at irradiance 0.5 (0: none)
``extinction_ratio``        () float32             inf for ideal polarizers
``index``, ``seed``         () int64               sample index in the dataset, capture seed
``name``                    str                    sample folder name
==========================  =====================  ==============================================

Aligned crops: a crop of ``c x c`` HR pixels (``c`` a multiple of 4) at HR offset (top, left),
both multiples of 4, is exactly the raw window ``[top/2, top/2 + c/2)`` (the RGGB phase is kept:
the offset is even), the sub-image window ``[top/4, top/4 + c/4)``, and the DoFP window
``[top, top + c)`` (the DoFP quad-Bayer period of 4 is kept). The homographies move with it:
``H'_n = T(-left, -top) H_n T(left, top)`` for the aperture homographies and
``H'_m = T(-left/4, -top/4) H_m T(left, top)`` for the sub-image ones (T a translation on
(x=col, y=row)); so ``H'_m = S_q H'_n`` still holds and the camera model applied to the cropped
GT with the cropped homographies reproduces the cropped raw frames. Caveat: apertures 1-3
near the crop border see scene content from just outside the GT crop (up to the pose shift,
a few HR pixels), as any crop of a real capture does.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from capssim.camera.array_geometry import ArrayGeometry
from capssim.camera.sensor import noise_sigma_estimate, noise_std_map
from capssim.captures.capture import read_capture
from capssim.conventions import split_bayer
from capssim.dataset.manifest import MANIFEST, SAMPLES_DIR, read_manifest
from capssim.errors import CaptureFormatError, InputError
from capssim.files.imageio import file_sha256

CROP_MULTIPLE = 4


def crop_homographies(geometry: ArrayGeometry, top: int, left: int, hr_shape) -> tuple[np.ndarray, np.ndarray]:
    """Homographies of a capture cropped to ``hr_shape`` at HR offset (``top``, ``left``), multiples of 4.

    Returns ``(4, 3, 3)`` HR reference -> aperture-HR and ``(16, 3, 3)`` HR reference -> sub-image
    pixels, both in the crop's coordinates (:meth:`capssim.camera.array_geometry.ArrayGeometry.cropped`).
    """
    crop = geometry.cropped(top, left, hr_shape)  # refuses offsets that are not multiples of 4
    return crop.aperture_homographies.copy(), crop.lr_homographies


def dataset_sample_folders(root, *, indices: Iterable[int] | None = None) -> list[Path]:
    """Sample folders of a dataset, in index order, from its manifest (finished samples only)."""
    root = Path(root)
    if not (root / MANIFEST).is_file():
        raise InputError("root", f"{str(root)!r} without {MANIFEST}",
                         "a dataset folder made by 'capssim dataset', or a list of capture folders")
    records = read_manifest(root / MANIFEST).records
    wanted = sorted(records) if indices is None else list(indices)
    missing = [i for i in wanted if i not in records]
    if missing:
        raise InputError("indices", f"samples {missing[:10]} that are not finished in {root}",
                         "indices of finished samples", "Finish the dataset: rerun 'capssim dataset CONFIG -o OUT'.")
    return [root / SAMPLES_DIR / records[i]["name"] for i in wanted]


class CaptureDataset(Dataset):
    """Captures as tensors for training (see the module docstring for the item layout).

    Parameters
    ----------
    root : str, pathlib.Path or sequence of them
        A dataset folder (samples read from its manifest) or a sequence of capture folders.
    crop : int, optional
        HR crop size (a multiple of 4), or None for whole captures (which must then share a size to be batched).
    random_crop : bool
        Random crop offsets (multiples of 4, drawn with ``generator`` or torch's global generator, which a
        DataLoader seeds per worker); False: the centred crop (offset rounded down to a multiple of 4).
    load_gt, load_dofp : bool
        Load ``gt.tiff`` / ``dofp_raw.tiff``.
    verify_checksums : bool
        Check each file's sha256 against the manifest when loading it.
    indices : iterable of int, optional
        Only these dataset samples (e.g. a train/validation split).
    generator : torch.Generator, optional
        The generator of the random crops (None: torch's global one).
    """

    def __init__(self, root: str | Path | Sequence[str | Path], *, crop: int | None = None, random_crop: bool = True,
                 load_gt: bool = True, load_dofp: bool = True, verify_checksums: bool = False,
                 indices: Iterable[int] | None = None, generator: torch.Generator | None = None):
        if isinstance(root, (str, Path)):
            self.folders = dataset_sample_folders(root, indices=indices)
            self._records = {r["name"]: r for r in read_manifest(Path(root) / MANIFEST).records.values()}
        else:
            if indices is not None:
                raise InputError("indices", "indices with a list of folders", "indices only with a dataset folder")
            self.folders = [Path(p) for p in root]
            self._records = {}
        if not self.folders:
            raise InputError("root", str(root), "a dataset with at least one finished sample")
        if crop is not None and (int(crop) != crop or crop < CROP_MULTIPLE or crop % CROP_MULTIPLE):
            raise InputError("crop", crop, f"a positive multiple of {CROP_MULTIPLE} (HR pixels)",
                             f"Try crop={max(CROP_MULTIPLE, int(crop) - int(crop) % CROP_MULTIPLE)}.")
        if verify_checksums and not self._records:
            raise InputError("verify_checksums", True, "a dataset folder (its manifest holds the checksums)")
        self.crop = None if crop is None else int(crop)
        self.random_crop = random_crop
        self.load_gt = load_gt
        self.load_dofp = load_dofp
        self.verify_checksums = verify_checksums
        self.generator = generator

    def __len__(self) -> int:
        return len(self.folders)

    def meta(self, i: int) -> dict:
        """The full ``meta.json`` of sample ``i`` (includes ``dataset.params`` for dataset samples)."""
        return json.loads((self.folders[i] / "meta.json").read_text())

    def _check(self, folder: Path) -> None:
        record = self._records.get(folder.name)
        if record is None:
            raise CaptureFormatError(f"{folder}: not listed in the manifest; cannot verify its checksums.")
        for name, expected in record["files"].items():
            if file_sha256(folder / name) != expected["sha256"]:
                raise CaptureFormatError(f"{folder / name}: sha256 differs from the manifest (corrupt sample). "
                                         "Run 'capssim dataset --verify OUT'.")

    def _offset(self, hr_shape: tuple[int, int], folder: Path) -> tuple[int, int]:
        hh, ww = hr_shape
        c = self.crop
        if c > min(hh, ww):
            raise InputError("crop", c, f"at most the capture size {hh}x{ww} of {folder}")
        n_rows, n_cols = (hh - c) // CROP_MULTIPLE + 1, (ww - c) // CROP_MULTIPLE + 1
        if self.random_crop:
            r = torch.randint(n_rows, (1,), generator=self.generator).item()
            s = torch.randint(n_cols, (1,), generator=self.generator).item()
        else:
            r, s = (n_rows - 1) // 2, (n_cols - 1) // 2
        return CROP_MULTIPLE * int(r), CROP_MULTIPLE * int(s)

    def __getitem__(self, i: int) -> dict:
        folder = self.folders[i]
        if self.verify_checksums:
            self._check(folder)
        cap = read_capture(folder, load_gt=self.load_gt, require_gt=self.load_gt)
        meta = cap.meta
        if cap.hr_shape[0] % CROP_MULTIPLE or cap.hr_shape[1] % CROP_MULTIPLE:
            raise CaptureFormatError(f"{folder}: HR size {cap.hr_shape} is not a multiple of {CROP_MULTIPLE}.")
        hh, ww = cap.hr_shape
        top, left = (0, 0) if self.crop is None else self._offset(cap.hr_shape, folder)
        ch, cw = (hh, ww) if self.crop is None else (self.crop, self.crop)
        sensor = cap.sensor
        raw = cap.caps_raw[:, top // 2:(top + ch) // 2, left // 2:(left + cw) // 2]
        caps = sensor.to_float(raw)
        h, w = caps.shape[1:]
        lr = split_bayer(caps)
        ap_h, lr_h = crop_homographies(cap.geometry, top, left, (ch, cw))
        er = cap.extinction_ratio
        item = {
            "caps_raw": torch.from_numpy(np.ascontiguousarray(caps)),
            "caps_saturated": torch.from_numpy(np.ascontiguousarray(sensor.saturation_mask(raw))),
            "lr_images": torch.from_numpy(np.ascontiguousarray(lr)),
            "aperture_homographies": torch.from_numpy(ap_h),
            "lr_homographies": torch.from_numpy(lr_h),
            "crop_offset_hr": torch.tensor([top, left], dtype=torch.int64),
            "dofp_layout": torch.tensor(cap.dofp_layout, dtype=torch.int64),
            "noise_sigma": torch.tensor(noise_sigma_estimate(sensor), dtype=torch.float32),
            "extinction_ratio": torch.tensor(math.inf if er is None else float(er), dtype=torch.float32),
            "index": torch.tensor(int((meta.get("dataset") or {}).get("index", i)), dtype=torch.int64),
            "seed": torch.tensor(int(meta.get("seed") or 0), dtype=torch.int64),
            "name": folder.name,
        }
        if self.load_dofp and cap.dofp_raw is not None:
            d = cap.dofp_raw[top:top + ch, left:left + cw]
            item["dofp_raw"] = torch.from_numpy(np.ascontiguousarray(sensor.to_float(d)))
            item["dofp_noise_std"] = torch.from_numpy(noise_std_map(sensor, item["dofp_raw"].numpy()))
            item["dofp_saturated"] = torch.from_numpy(np.ascontiguousarray(sensor.saturation_mask(d)))
        if self.load_gt:
            item["gt"] = torch.from_numpy(np.ascontiguousarray(cap.gt[:, top:top + ch, left:left + cw]))
        return item
