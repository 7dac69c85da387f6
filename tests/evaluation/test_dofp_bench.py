"""Done-when numbers of the DoFP baselines on the real ground-truth scenes (skip without ../shared)."""

from __future__ import annotations

import numpy as np
import pytest

from capssim.conventions import dofp_channel_map
from capssim.files.imageio import read_gt_scene


def _scene_and_mosaic(shared_data, name):
    gt, _ = read_gt_scene(shared_data / "gt" / name)
    cmap = dofp_channel_map(*gt.shape[1:], "sony")
    return gt, np.take_along_axis(gt, cmap[None], axis=0)[0]


def test_bilinear_matches_published_scores_on_kettle(shared_data):
    """Published-style two-step bilinear on qiu-kettle: S0 39.8 dB, DoLP 33.6 dB, AoP RMSE 12.0 deg."""
    from capssim.eval.metrics import tokyotech_scores
    from capssim.reconstruct.dofp.bilinear import demosaic_dofp_bilinear

    gt, mosaic = _scene_and_mosaic(shared_data, "qiu-kettle")
    scores = tokyotech_scores(demosaic_dofp_bilinear(mosaic, layout="sony"), gt)
    assert scores["psnr_s0"] == pytest.approx(39.8, abs=0.3)
    assert scores["psnr_dolp"] == pytest.approx(33.6, abs=0.3)
    assert scores["aop_rmse_deg"] == pytest.approx(12.0, abs=0.3)


@pytest.mark.slow
def test_simulated_capture_mosaic_is_the_direct_sampling(shared_data, tmp_path):
    """``capssim simulate --noise none --psf-sigma-hr-px 0`` gives exactly the directly sampled mosaic."""
    from capssim.eval.benchmarks.dofp import make_capture

    gt, mosaic = _scene_and_mosaic(shared_data, "qiu-cellphonecases")
    capture = make_capture(shared_data / "gt" / "qiu-cellphonecases")
    np.testing.assert_array_equal(capture.dofp_float(), mosaic)


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["qiu-kettle", "qiu-cellphonecases"])
def test_eari_beats_bilinear(shared_data, scene):
    from capssim.eval.metrics import tokyotech_scores
    from capssim.reconstruct.dofp.bilinear import demosaic_dofp_bilinear
    from capssim.reconstruct.methods.dofp_eari import demosaic_dofp_eari

    gt, mosaic = _scene_and_mosaic(shared_data, scene)
    bil = tokyotech_scores(demosaic_dofp_bilinear(mosaic, layout="sony"), gt)
    eari = tokyotech_scores(demosaic_dofp_eari(mosaic, layout="sony"), gt)
    assert eari["psnr_s0"] > bil["psnr_s0"] + 1.5
    assert eari["psnr_dolp"] > bil["psnr_dolp"] + 1.0
    assert eari["aop_rmse_deg"] < bil["aop_rmse_deg"]
