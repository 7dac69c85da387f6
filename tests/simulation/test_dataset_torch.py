"""CaptureDataset: tensors through a DataLoader, and crops aligned exactly across GT, raw and DoFP."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from capssim.camera.array_geometry import ArrayGeometry, lr_homographies
from capssim.camera.psf import gaussian_psf_kernel
from capssim.dataset import load_config
from capssim.dataset.generate import generate_dataset
from capssim.dataset.torch import CaptureDataset, crop_homographies
from capssim.errors import CaptureFormatError, InputError
from capssim.operators.camera import caps_raw_operator, dofp_raw_operator


@pytest.fixture(scope="module")
def dataset_dir(write_gt_folder, tmp_path_factory):
    root = tmp_path_factory.mktemp("torchds")
    write_gt_folder(root / "gt" / "a", size=48, seed=5)
    (root / "config.yaml").write_text(textwrap.dedent("""
        seed: 2
        samples: 5
        defaults:
          sensor: {noise: {choice: [gaussian, poisson-gaussian]}, sigma: 0.01}
          dofp_layout: {choice: [sony, 0-45-135-90]}
          extinction_ratio: {choice: [null, 100]}
        sources:
          - gt: gt/a
            size: 40
            crop_position: random
    """))
    (root / "clean.yaml").write_text(textwrap.dedent("""
        seed: 3
        samples: 2
        defaults:
          pose: {shift_max_px: 2.0, rotation_max_deg: 0.5, scale_max: 0.005}
          dofp_layout: {choice: [sony, 0-45-135-90]}
        sources:
          - gt: gt/a
            size: 48
    """))
    generate_dataset(load_config(root / "config.yaml"), root / "noisy", workers=0)
    generate_dataset(load_config(root / "clean.yaml"), root / "clean", workers=0)
    return root


def test_dataloader_batches(dataset_dir):
    ds = CaptureDataset(dataset_dir / "noisy", crop=16, generator=torch.Generator().manual_seed(0))
    assert len(ds) == 5
    loader = DataLoader(ds, batch_size=2, shuffle=True, num_workers=0, generator=torch.Generator().manual_seed(1))
    batches = list(loader)
    assert [len(b["name"]) for b in batches] == [2, 2, 1]
    b = batches[0]
    assert b["caps_raw"].shape == (2, 4, 8, 8) and b["caps_raw"].dtype == torch.float32
    assert b["caps_saturated"].shape == (2, 4, 8, 8) and b["caps_saturated"].dtype == torch.bool
    assert b["lr_images"].shape == (2, 16, 4, 4)
    assert b["dofp_raw"].shape == (2, 16, 16) and b["gt"].shape == (2, 12, 16, 16)
    assert b["aperture_homographies"].shape == (2, 4, 3, 3) and b["lr_homographies"].shape == (2, 16, 3, 3)
    assert b["aperture_homographies"].dtype == torch.float64
    assert b["dofp_layout"].shape == (2, 2, 2) and b["noise_sigma"].shape == (2,)
    assert torch.all(b["noise_sigma"] > 0) and torch.all(b["crop_offset_hr"] % 4 == 0)
    assert torch.all((b["crop_offset_hr"] >= 0) & (b["crop_offset_hr"] <= 40 - 16))
    assert sorted(int(i) for batch in batches for i in batch["index"]) == list(range(5))
    # values are on the [0, 1] scale, like the GT (noise aside)
    assert abs(float(b["caps_raw"].mean()) - float(b["gt"].mean())) < 0.1
    # lr_images is the Bayer split of caps_raw: m = 4n + q, q at raw offset (q // 2, q % 2)
    item = ds[0]
    for m in range(16):
        n, q = divmod(m, 4)
        assert torch.equal(item["lr_images"][m], item["caps_raw"][n, q // 2::2, q % 2::2])
    # extinction ratio and DoFP layout come through
    values = {float(ds[i]["extinction_ratio"]) for i in range(5)}
    assert values <= {float("inf"), 100.0}
    # the same generator seed gives the same crops; centred crops are fixed
    def offsets(d):
        return [tuple(d[i]["crop_offset_hr"].tolist()) for i in range(len(d))]
    a = CaptureDataset(dataset_dir / "noisy", crop=16, generator=torch.Generator().manual_seed(7))
    c = CaptureDataset(dataset_dir / "noisy", crop=16, generator=torch.Generator().manual_seed(7))
    assert offsets(a) == offsets(c)
    centred = CaptureDataset(dataset_dir / "noisy", crop=16, random_crop=False)
    assert offsets(centred) == [(12, 12)] * 5
    whole = CaptureDataset(dataset_dir / "noisy", indices=[1, 3], load_dofp=False)
    assert len(whole) == 2 and whole[0]["gt"].shape == (12, 40, 40) and "dofp_raw" not in whole[0]
    assert whole.meta(1)["dataset"]["index"] == 3


def test_crops_are_aligned_with_the_camera_model(dataset_dir):
    """The camera model applied to the cropped GT with the cropped homographies reproduces the
    cropped raw and DoFP frames (noise-free samples) away from the crop border."""
    ds = CaptureDataset(dataset_dir / "clean", crop=24, generator=torch.Generator().manual_seed(3))
    kernel = gaussian_psf_kernel(0.5)
    checked = 0
    for i in range(len(ds)):
        for _ in range(3):
            item = ds[i]
            top, left = item["crop_offset_hr"].tolist()
            gt = item["gt"].double()
            ap = item["aperture_homographies"].numpy()
            np.testing.assert_allclose(lr_homographies(ap), item["lr_homographies"].numpy(), atol=1e-12)
            with torch.no_grad():
                raw = caps_raw_operator((24, 24), ap, kernel)(gt).float()
            margin = 3  # raw pixels: pose shift (<= 2 HR px) + rotation + PSF + bilinear support
            inner = (slice(None), slice(margin, -margin), slice(margin, -margin))
            err = (raw - item["caps_raw"])[inner].abs().max().item()
            assert err < 1e-5, (i, top, left, err)
            # the uncropped homographies do not fit the crop (the check can fail)
            if (top, left) != (0, 0):
                meta = ds.meta(i)
                wrong = caps_raw_operator((24, 24), np.asarray(meta["aperture_homographies"]), kernel)(gt).float()
                assert (wrong - item["caps_raw"])[inner].abs().max().item() > 1e-3
            layout = tuple(map(tuple, item["dofp_layout"].tolist()))
            with torch.no_grad():
                dofp = dofp_raw_operator((24, 24), kernel, layout=layout)(gt).float()
            derr = (dofp - item["dofp_raw"])[2:-2, 2:-2].abs().max().item()
            assert derr < 1e-5, (i, top, left, derr)
            checked += 1
    assert checked == 6


def test_crop_homographies_rules_and_errors(dataset_dir):
    h = np.stack([np.eye(3)] * 4)
    h[1, 0, 2] = 0.7
    ap, lr = crop_homographies(ArrayGeometry(h, (32, 32)), 8, 4, (16, 16))
    np.testing.assert_allclose(lr, lr_homographies(ap), atol=1e-12)
    np.testing.assert_allclose(ap[1], h[1])  # a pure translation commutes with the crop shift
    with pytest.raises(InputError, match="multiples of 4"):
        crop_homographies(ArrayGeometry(h, (32, 32)), 2, 0, (16, 16))
    with pytest.raises(InputError, match="multiple of 4"):
        CaptureDataset(dataset_dir / "noisy", crop=18)
    with pytest.raises(InputError, match="at most the capture size"):
        CaptureDataset(dataset_dir / "noisy", crop=64)[0]
    with pytest.raises(InputError, match="not finished"):
        CaptureDataset(dataset_dir / "noisy", indices=[7])
    with pytest.raises(InputError, match="manifest.jsonl"):
        CaptureDataset(dataset_dir / "gt")
    # checksum verification on load catches a corrupt file
    folder = dataset_dir / "noisy" / "samples" / "000004"
    original = (folder / "gt.tiff").read_bytes()
    try:
        data = bytearray(original)
        data[-10] ^= 0xFF
        (folder / "gt.tiff").write_bytes(bytes(data))
        checked = CaptureDataset(dataset_dir / "noisy", verify_checksums=True)
        checked[0]
        with pytest.raises(CaptureFormatError, match="sha256"):
            checked[4]
    finally:
        (folder / "gt.tiff").write_bytes(original)
    # a list of capture folders works too
    folders = sorted((dataset_dir / "noisy" / "samples").iterdir())
    assert CaptureDataset(folders[:2], crop=8)[1]["gt"].shape == (12, 8, 8)
