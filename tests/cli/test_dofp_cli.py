"""``capssim demosaic`` on raw mosaics: reading, errors, outputs; and the benchmark's metric definitions."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

from capssim.cli import app
from capssim.conventions import dofp_channel_map

runner = CliRunner()


def _raw_png(path, image12, *, layout="sony", bits=8, size=None):
    cmap = dofp_channel_map(*image12.shape[1:], layout)
    mosaic = np.take_along_axis(image12, cmap[None], axis=0)[0]
    if size is not None:
        mosaic = mosaic[: size[0], : size[1]]
    top = 2 ** bits - 1
    data = np.round(np.clip(mosaic, 0, 1) * top).astype(np.uint8 if bits == 8 else np.uint16)
    cv2.imwrite(str(path), data)
    return data


def _invoke(*args):
    return runner.invoke(app, list(args))


@pytest.mark.parametrize("method", ["dofp-bilinear", "dofp-eari"])
@pytest.mark.parametrize("bits", [8, 16])
def test_demosaic_writes_tiff_previews_and_record(tmp_path, scene64, method, bits):
    raw = tmp_path / "raw.png"
    data = _raw_png(raw, scene64, bits=bits)
    out = tmp_path / "out"
    result = _invoke("demosaic", str(raw), "--dofp-layout", "sony", "--method", method, "-o", str(out))
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["aop.png", "demosaic.json", "demosaicked.tiff", "dolp.png",
                                                     "intensity.png", "panel.png"]
    image = tifffile.imread(out / "demosaicked.tiff")
    assert image.shape == (12, 64, 64) and image.dtype == np.float32
    assert np.abs(image - scene64).mean() < 0.03
    four = image.reshape(4, 3, 64, 64).astype(np.float64)  # physically valid by default
    assert four.min() >= 0 and np.abs(four[0] + four[2] - four[1] - four[3]).max() < 1e-5
    # float end to end: without the projection, sampled pixels equal DN / (2^bits - 1) exactly
    raw_out = tmp_path / "raw-out"
    assert _invoke("demosaic", str(raw), "--method", method, "--no-physical-projection", "-o", str(raw_out)).exit_code == 0
    unprojected = tifffile.imread(raw_out / "demosaicked.tiff")
    cmap = dofp_channel_map(64, 64, "sony")
    np.testing.assert_array_equal(np.take_along_axis(unprojected, cmap[None], axis=0)[0],
                                  (data.astype(np.float64) / (2 ** bits - 1)).astype(np.float32))
    record = json.loads((out / "demosaic.json").read_text())
    assert record["method"] == method and record["layout"] == [[90, 45], [135, 0]]
    assert record["input"]["bit_depth"] == bits and record["stages_s"]
    panel = cv2.imread(str(out / "panel.png"))  # titled maps with their keys (tests/test_hardening_outputs.py)
    assert panel.shape[0] > 260 and panel.shape[1] > 3 * 260 and set(record["previews"]) >= {"dolp.png", "panel.png"}


def test_demosaic_white_and_black_level(tmp_path, scene64):
    raw = tmp_path / "raw.tiff"
    cmap = dofp_channel_map(64, 64, "0-45-135-90")
    mosaic = np.take_along_axis(scene64, cmap[None], axis=0)[0]
    dn = np.round(64 + mosaic * (4095 - 64)).astype(np.uint16)  # 12-bit data, black level 64
    tifffile.imwrite(raw, dn)
    out = tmp_path / "out"
    result = _invoke("demosaic", str(raw), "--dofp-layout", "0-45-135-90", "--method", "dofp-bilinear",
                     "--white-level", "4095", "--black-level", "64", "--no-physical-projection", "-o", str(out))
    assert result.exit_code == 0, result.output
    image = tifffile.imread(out / "demosaicked.tiff")
    kept = np.take_along_axis(image, cmap[None], axis=0)[0]
    np.testing.assert_allclose(kept, mosaic, atol=0.5 / 4031 + 1e-6)


def test_odd_size_is_an_error_unless_trimmed(tmp_path, scene64):
    raw = tmp_path / "odd.png"
    _raw_png(raw, scene64, size=(63, 61))
    result = runner.invoke(app, ["demosaic", str(raw), "-o", str(tmp_path / "a")])
    assert result.exit_code != 0
    assert "odd size 63x61" in str(result.exception) and "--trim-odd" in str(result.exception)
    assert not (tmp_path / "a").exists()
    result = _invoke("demosaic", str(raw), "--trim-odd", "--method", "dofp-bilinear", "-o", str(tmp_path / "b"))
    assert result.exit_code == 0, result.output
    assert tifffile.imread(tmp_path / "b" / "demosaicked.tiff").shape == (12, 62, 60)
    assert json.loads((tmp_path / "b" / "demosaic.json").read_text())["input"]["trimmed_to"] == [62, 60]


def test_bad_inputs_give_clear_errors(tmp_path, scene64):
    colour = tmp_path / "colour.png"
    cv2.imwrite(str(colour), np.random.default_rng(0).integers(0, 255, (32, 32, 3), dtype=np.uint8))
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png at all")
    raw = tmp_path / "raw.png"
    _raw_png(raw, scene64)
    cases = [
        (["demosaic", str(colour), "-o", str(tmp_path / "o1")], "single-channel raw mosaic"),
        (["demosaic", str(broken), "-o", str(tmp_path / "o2")], "unreadable image"),
        (["demosaic", str(tmp_path / "missing.png"), "-o", str(tmp_path / "o3")], "existing image file"),
        (["demosaic", str(raw), "--dofp-layout", "sideways", "-o", str(tmp_path / "o4")], "dofp_layout"),
        (["demosaic", str(raw), "--method", "magic", "-o", str(tmp_path / "o5")], "unknown DoFP method"),
        (["demosaic", str(raw), "--white-level", "300", "-o", str(tmp_path / "o6")], "0 <= black < white <= 255"),
    ]
    for args, message in cases:
        result = runner.invoke(app, args)
        assert result.exit_code != 0, args
        assert message in str(result.exception), (args, result.exception)
        assert not (tmp_path / args[-1]).exists()


def test_grey_saved_as_rgb_is_accepted(tmp_path, scene64):
    cmap = dofp_channel_map(64, 64, "sony")
    mosaic = np.round(np.take_along_axis(scene64, cmap[None], axis=0)[0] * 255).astype(np.uint8)
    raw = tmp_path / "grey3.png"
    cv2.imwrite(str(raw), np.repeat(mosaic[..., None], 3, axis=2))
    result = _invoke("demosaic", str(raw), "--method", "dofp-bilinear", "-o", str(tmp_path / "o"))
    assert result.exit_code == 0, result.output


def test_existing_output_needs_overwrite(tmp_path, scene64):
    raw = tmp_path / "raw.png"
    _raw_png(raw, scene64)
    out = tmp_path / "out"
    assert _invoke("demosaic", str(raw), "--method", "dofp-bilinear", "-o", str(out)).exit_code == 0
    result = runner.invoke(app, ["demosaic", str(raw), "-o", str(out)])
    assert result.exit_code != 0 and "--overwrite" in str(result.exception)
    assert _invoke("demosaic", str(raw), "--method", "dofp-bilinear", "-o", str(out), "--overwrite").exit_code == 0


def test_real_raw_mosaics(shared_data, tmp_path):
    """The two real raws of ../shared/data: sensible previews (valid range, real polarization)."""
    for name in ("album", "carlight"):
        out = tmp_path / name
        result = _invoke("demosaic", str(shared_data / "dofp-real" / f"{name}.png"), "--dofp-layout", "sony",
                         "--method", "dofp-bilinear", "-o", str(out))
        assert result.exit_code == 0, result.output
        image = tifffile.imread(out / "demosaicked.tiff")
        assert image.shape == (12, 600, 600) and np.all(np.isfinite(image))
        i = image.reshape(4, 3, 600, 600).astype(np.float64)
        s0 = i.sum(0) / 2
        dolp = np.sqrt((i[0] - i[2]) ** 2 + (i[1] - i[3]) ** 2) / np.maximum(s0, 1e-6)
        # real scenes: mostly weakly polarized, with some strongly polarized pixels
        assert 0.01 < np.median(dolp) < 0.3 and np.percentile(dolp, 99) > 0.15


# -- metric definitions of the benchmark ---------------------------------------------------------------
def test_tokyotech_scores_definitions(scene64):
    from capssim.eval.metrics import PSNR_CAP_DB, tokyotech_scores

    perfect = tokyotech_scores(scene64, scene64, border=15)
    scene64 = scene64.astype(np.float64)
    assert perfect["psnr_s0"] == PSNR_CAP_DB and perfect["aop_rmse_deg"] == 0.0
    shifted = scene64.astype(np.float64) + 0.01
    scores = tokyotech_scores(shifted, scene64, border=0)
    assert scores["psnr_0"] == pytest.approx(40.0, abs=1e-4)  # MSE 1e-4, peak 1
    assert scores["psnr_s0"] == pytest.approx(40.0, abs=1e-4)  # S0 as the mean of the angles
    assert scores["psnr_s1"] == PSNR_CAP_DB  # S1 = I0 - I90 is unchanged by a common offset
    # AoP error wraps around: 179 deg vs 1 deg is a 2 deg error
    from capssim.stokes.polarization import twelve_from_stokes

    def scene(aop_deg):
        a = np.deg2rad(2 * aop_deg)
        s = np.stack([np.full((3, 40, 40), 0.6), np.full((3, 40, 40), 0.3 * np.cos(a)),
                      np.full((3, 40, 40), 0.3 * np.sin(a))])
        return twelve_from_stokes(s)

    assert tokyotech_scores(scene(179.0), scene(1.0))["aop_rmse_deg"] == pytest.approx(2.0, abs=1e-6)
    half = scene(1.0)
    half[:, :20] = scene(5.0)[:, :20]  # half the pixels 4 deg off: MAE 2 deg, RMSE sqrt(8) deg
    mixed = tokyotech_scores(half, scene(1.0), border=0)
    assert mixed["aop_mae_deg"] == pytest.approx(2.0, abs=1e-6)
    assert mixed["aop_rmse_deg"] == pytest.approx(np.sqrt(8.0), abs=1e-6)
    assert tokyotech_scores(scene(179.0), scene(1.0))["psnr_dolp"] == PSNR_CAP_DB
