"""DoFP demosaicking baselines: layout handling, exactness, stability, the registry path."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import correlate as nd_correlate

from capssim.conventions import POLARIZER_ANGLES_DEG, dofp_channel_map
from capssim.errors import InputError
from capssim.reconstruct.dofp.bilinear import demosaic_dofp_bilinear
from capssim.reconstruct.dofp.mosaic import (
    angle_offsets,
    check_mosaic,
    merge_submosaics,
    polarization_masks,
    split_submosaics,
)
from capssim.reconstruct.filters import box_sum, correlate
from capssim.reconstruct.methods.dofp_eari import demosaic_dofp_eari
from capssim.reconstruct.methods.dofp_igri2 import QuincunxRotation, demosaic_dofp_igri2

LAYOUTS = ("sony", "0-45-135-90")
METHODS = {"dofp-bilinear": demosaic_dofp_bilinear, "dofp-eari": demosaic_dofp_eari,
           "dofp-igri2": demosaic_dofp_igri2}
#: border bands (pixels) outside which each method is exact on linear ramps (measured, see tests)
RAMP_BORDER = {"dofp-bilinear": 4, "dofp-eari": 40, "dofp-igri2": 40}


def mosaic_of(image12: np.ndarray, layout: str) -> np.ndarray:
    """Independent DoFP sampling: pixel (r, c) takes channel dofp_channel_map[r, c]."""
    cmap = dofp_channel_map(*image12.shape[1:], layout)
    return np.take_along_axis(image12, cmap[None], axis=0)[0]


def linear_ramps(h: int, w: int, *, seed: int = 0) -> np.ndarray:
    """12 independent linear ramps a + b*row + c*col, all inside (0.1, 0.9)."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    out = []
    for _ in range(12):
        b, c = rng.uniform(-0.3, 0.3, 2) / max(h, w)
        out.append(0.5 + b * (rows - h / 2) + c * (cols - w / 2))
    return np.stack(out)


# -- layout helpers ------------------------------------------------------------------------------
def test_angle_offsets_follow_the_layout_cell():
    assert angle_offsets("sony") == ((1, 1), (0, 1), (0, 0), (1, 0))  # 0, 45, 90, 135 in [[90,45],[135,0]]
    assert angle_offsets("0-45-135-90") == ((0, 0), (0, 1), (1, 1), (1, 0))
    assert angle_offsets([[45, 0], [90, 135]]) == ((0, 1), (0, 0), (1, 0), (1, 1))


@pytest.mark.parametrize("layout", LAYOUTS)
def test_split_and_masks_agree_with_the_channel_map(layout):
    h, w = 12, 20
    cmap = dofp_channel_map(h, w, layout)
    angle_index = torch.as_tensor(cmap // 3)
    masks = polarization_masks(h, w, layout)
    assert torch.equal(masks.sum(0), torch.ones(h, w))
    for p in range(4):
        assert torch.equal(masks[p] > 0, angle_index == p)
    x = torch.arange(h * w, dtype=torch.float64).reshape(h, w)
    subs = split_submosaics(x, layout)
    assert subs.shape == (4, h // 2, w // 2)
    assert torch.equal(merge_submosaics(subs, layout), x)
    # every sub-mosaic is RGGB with R at (0, 0)
    colour = torch.as_tensor(cmap % 3)
    for p, (dr, dc) in enumerate(angle_offsets(layout)):
        sub_colour = colour[dr::2, dc::2]
        assert torch.equal(sub_colour[0::2, 0::2], torch.zeros_like(sub_colour[0::2, 0::2]))
        assert torch.equal(sub_colour[1::2, 1::2], torch.full_like(sub_colour[1::2, 1::2], 2))
        assert POLARIZER_ANGLES_DEG[int(angle_index[dr, dc])] == POLARIZER_ANGLES_DEG[p]


def test_filter_primitives_match_scipy():
    rng = np.random.default_rng(1)
    x = rng.random((2, 17, 23))
    k = rng.normal(size=(5, 3))
    k[2, 1] = 0.0
    for mode, nd_mode in (("reflect", "mirror"), ("replicate", "nearest"), ("zeros", "constant")):
        ours = correlate(torch.from_numpy(x), k, padding=mode).numpy()
        ref = np.stack([nd_correlate(s, k, mode=nd_mode, cval=0.0) for s in x])
        np.testing.assert_allclose(ours, ref, atol=1e-12)
    for ry, rx in ((5, 5), (3, 3), (0, 2), (4, 0), (2, 6)):
        ours = box_sum(torch.from_numpy(x), ry, rx).numpy()
        ref = np.stack([nd_correlate(s, np.ones((2 * ry + 1, 2 * rx + 1)), mode="constant") for s in x])
        np.testing.assert_allclose(ours, ref, atol=1e-12)


# -- exactness -------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("method", METHODS)
def test_samples_are_kept(method, layout, scene64):
    mosaic = mosaic_of(scene64, layout)
    out = METHODS[method](mosaic, layout=layout)
    assert out.shape == (12, 64, 64) and out.dtype == np.float32
    cmap = dofp_channel_map(64, 64, layout)
    np.testing.assert_array_equal(np.take_along_axis(out, cmap[None], axis=0)[0], mosaic)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("method", METHODS)
def test_constant_channels_are_exact_everywhere(method, layout):
    values = np.linspace(0.05, 0.95, 12)
    image = np.broadcast_to(values[:, None, None], (12, 36, 44)).copy()
    out = METHODS[method](mosaic_of(image, layout).astype(np.float64), layout=layout)
    np.testing.assert_allclose(out, image, atol=1e-6)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("method", METHODS)
def test_linear_ramps_are_exact_away_from_borders(method, layout):
    """Bilinear and EARI reproduce linear ramps (exactly, up to float32 rounding) in the interior.

    Bilinear: each step is linear interpolation between two or four lattice neighbours. EARI: a
    linear image has zero step-2 Laplacian, so every MLRI slope is 0 and the tentative estimate is
    a symmetric average of window means, which equals the ramp; the residuals vanish. The
    border band is where windows are truncated or mirrored: 4 px for bilinear; for EARI the
    11x11 MLRI windows of the colour stage at half resolution (14 sub-mosaic px = 28 px) plus
    those of the polarization stage (12 px) make 40 px (measured: errors ~3e-3 up to 38 px, at
    rounding level from 40 px on).
    """
    h, w = 112, 120
    image = linear_ramps(h, w)
    out = METHODS[method](mosaic_of(image, layout).astype(np.float32), layout=layout)
    b = RAMP_BORDER[method]
    np.testing.assert_allclose(out[:, b:h - b, b:w - b], image[:, b:h - b, b:w - b], atol=2e-5)
    # ... and not exact just inside the band: the band is tight, not a loose bound
    near = np.abs(out - image)[:, b - 2:h - b + 2, b - 2:w - b + 2]
    assert near.max() > 1e-4


def test_quincunx_rotation_is_a_bijection_onto_diagonal_neighbours():
    h, w = 14, 18
    x = torch.arange(h * w, dtype=torch.float64).reshape(h, w) + 1
    for parity in (0, 1):
        rot = QuincunxRotation(h, w, parity)
        r = rot.rotate(x)
        assert r.shape[1] % 2 == 0 and int((r != 0).sum()) == h * w // 2
        back = rot.unrotate_into(torch.zeros_like(x), r)
        on = ((torch.arange(h)[:, None] + torch.arange(w)[None]) % 2) == parity
        assert torch.equal(back[on], x[on]) and torch.equal(back[~on], torch.zeros_like(back[~on]))
        # rotated horizontal neighbours are image diagonal neighbours (down-right)
        u, v = int(rot.u[5]), int(rot.v[5])
        y0, x0 = int(rot.ys[5]), int(rot.xs[5])
        assert r[u + 1, v] == x[y0 + 1, x0 + 1] and r[u, v - 1] == x[y0 + 1, x0 - 1]
        # sites with u + v odd are the cell offsets (1, 1) / (1, 0): RGGB green sites
        odd = (rot.u + rot.v) % 2 == 1
        assert torch.all(rot.ys[odd] % 2 == 1) and torch.all(rot.ys[~odd] % 2 == 0)


def test_igri2_needs_orthogonal_diagonals(scene64):
    with pytest.raises(InputError, match="orthogonal angles on each diagonal"):
        demosaic_dofp_igri2(mosaic_of(scene64, "0-90-45-135"), layout="0-90-45-135")


def test_wrong_layout_is_not_exact():
    image = linear_ramps(32, 32)
    out = demosaic_dofp_bilinear(mosaic_of(image, "sony"), layout="0-45-135-90")
    assert np.abs(out - image)[:, 4:-4, 4:-4].max() > 1e-2


def test_bilinear_matches_an_independent_two_step_implementation(scene64):
    """scipy re-implementation of the polanalyser-style pipeline; equal in the interior."""
    layout = "sony"
    mosaic = mosaic_of(scene64, layout).astype(np.float64)
    k_rect = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]]) / 4
    k_cross = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]]) / 4
    cell = {90: (0, 0), 45: (0, 1), 135: (1, 0), 0: (1, 1)}
    expected = np.zeros((12, 64, 64))
    for p, angle in enumerate(POLARIZER_ANGLES_DEG):
        dr, dc = cell[angle]
        sub = mosaic[dr::2, dc::2]
        rows, cols = np.mgrid[0:32, 0:32]
        site = {0: (rows % 2 == 0) & (cols % 2 == 0), 1: (rows + cols) % 2 == 1, 2: (rows % 2 == 1) & (cols % 2 == 1)}
        for k in range(3):
            rgb = nd_correlate(sub * site[k], k_cross if k == 1 else k_rect, mode="constant")
            full = np.zeros((64, 64))
            full[dr::2, dc::2] = rgb
            expected[3 * p + k] = nd_correlate(full, k_rect, mode="constant")
    out = demosaic_dofp_bilinear(mosaic, layout=layout)
    np.testing.assert_allclose(out[:, 4:-4, 4:-4], expected[:, 4:-4, 4:-4], atol=1e-6)


# -- stability and bad input -------------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("level", [0.0, 1e-7, 1e-3])
def test_dark_input_gives_finite_output(method, level):
    rng = np.random.default_rng(3)
    mosaic = (level * rng.random((32, 40))).astype(np.float32)
    out = METHODS[method](mosaic, layout="sony")
    assert np.all(np.isfinite(out))
    # white noise is the worst case of interpolation overshoot; it stays within 2x the input range
    assert out.min() >= 0.0 and out.max() <= 2 * level + 1e-12


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scale", [1e-2, 1e-3])
def test_dark_scene_is_as_accurate_as_a_bright_one(method, scale, scene64):
    """A scene 100x or 1000x darker is reconstructed as well, relative to its level.

    Bilinear is linear, so exactly so. EARI is not: its thresholds (MLRI eps, window-weight
    floor, direction-weight floor) are absolute on [0, 1] data, as in the reference; its
    relative error must still not degrade by more than 10 %.
    """
    mosaic = mosaic_of(scene64, "sony").astype(np.float64)
    def rmse(out, s):
        return float(np.sqrt(np.mean((out / s - scene64)[:, 8:-8, 8:-8] ** 2)))
    bright = METHODS[method](mosaic, layout="sony")
    dark = METHODS[method](mosaic * scale, layout="sony")
    assert rmse(dark, scale) <= 1.1 * rmse(bright, 1.0)
    if method == "dofp-bilinear":
        np.testing.assert_allclose(dark / scale, bright, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_saturated_and_extreme_input(method):
    rng = np.random.default_rng(4)
    mosaic = rng.random((40, 40)).astype(np.float32)  # white noise: the hardest texture
    mosaic[8:20, 8:30] = 1.0  # saturated block
    out = METHODS[method](mosaic, layout="sony")
    assert np.all(np.isfinite(out)) and out.min() >= 0.0 and out.max() <= 1.0 + 1e-6


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("shape", [(12, 12), (14, 18), (30, 22)])
def test_sizes_not_multiple_of_four(method, shape):
    """Even sides that cut a 4x4 colour period (2 mod 4) work; constants stay exact."""
    values = np.linspace(0.1, 0.9, 12)
    image = np.broadcast_to(values[:, None, None], (12, *shape)).copy()
    out = METHODS[method](mosaic_of(image, "sony"), layout="sony")
    assert out.shape == (12, *shape)
    np.testing.assert_allclose(out, image, atol=1e-5)


@pytest.mark.parametrize("bad, match", [
    (np.zeros((13, 16), np.float32), "even height and width"),
    (np.zeros((16, 15), np.float32), "even height and width"),
    (np.zeros((10, 16), np.float32), "at least 12x12"),
    (np.zeros((16, 16), np.uint16), "float mosaic"),
    (np.zeros((16, 16, 3), np.float32), "2-D mosaic"),
    (np.full((16, 16), np.nan, np.float32), "NaN"),
])
def test_bad_mosaics_are_rejected(bad, match):
    with pytest.raises(InputError, match=match):
        check_mosaic(bad)
    with pytest.raises(InputError, match=match):
        demosaic_dofp_eari(bad, layout="sony")


def test_unknown_layout_is_rejected(scene64):
    with pytest.raises(InputError, match="dofp_layout"):
        demosaic_dofp_bilinear(mosaic_of(scene64, "sony"), layout="sideways")


def test_tensor_in_tensor_out_and_float64(scene64):
    mosaic = torch.from_numpy(mosaic_of(scene64, "sony").astype(np.float64))
    for fn in METHODS.values():
        out = fn(mosaic, layout="sony")
        assert isinstance(out, torch.Tensor) and out.dtype == torch.float64 and out.shape == (12, 64, 64)
        out32 = fn(mosaic.numpy().astype(np.float32), layout="sony")
        np.testing.assert_allclose(out.numpy(), out32, atol=2e-4)


# -- registry path -------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", LAYOUTS)
def test_methods_run_through_the_registry(tmp_path, scene64, layout):
    from capssim.camera.sensor import make_sensor
    from capssim.captures.capture import list_reconstructions, write_capture
    from capssim.reconstruct.registry import available_methods, run_method
    from capssim.simulate import simulate_capture

    capture = simulate_capture(scene64, make_sensor("none"), seed=0, psf={"type": "none"}, dofp_layout=layout)
    path = write_capture(tmp_path / "cap", capture)
    for name in METHODS:
        assert available_methods()[name].input_kind == "dofp"
        record = run_method(path, name)
        assert record["params"]["layout"] == [list(r) for r in capture.dofp_layout]
        assert record["wall_time_s"] > 0 and record["stages_s"]
        assert all(v >= 0 for v in record["stages_s"].values())
    assert set(METHODS) <= set(list_reconstructions(path))
    from capssim.files.imageio import read_tiff
    from capssim.stokes.physical_validity import project_to_physical

    out = read_tiff(path / "recon" / "dofp-bilinear.tiff")
    expected = demosaic_dofp_bilinear(capture.dofp_float(), layout=layout)
    np.testing.assert_array_equal(out, project_to_physical(expected)[0])  # the registry's projection
    unprojected = run_method(path, "dofp-bilinear", physical_projection=False)
    assert unprojected["physical_projection"] is None
    np.testing.assert_array_equal(read_tiff(path / "recon" / "dofp-bilinear.tiff"), expected)


def test_eari_options_through_the_registry(scene64):
    from capssim.camera.sensor import make_sensor
    from capssim.reconstruct.registry import reconstruct
    from capssim.simulate import simulate_capture

    capture = simulate_capture(scene64, make_sensor("gaussian", sigma=0.02), seed=1, psf={"type": "none"})
    out, record = reconstruct(capture, "dofp-eari", precision="float64", eps=1e-12)
    assert record["params"]["precision"] == "float64" and record["params"]["eps"] == 1e-12
    assert np.all(np.isfinite(out.image))
    with pytest.raises(InputError, match="precision"):
        reconstruct(capture, "dofp-eari", precision="half")


@pytest.mark.parametrize("method, options, match", [
    ("dofp-eari", {"epss": 1e-3}, "unknown option 'epss'.*valid names are: .*eps"),
    ("dofp-igri2", {"iterations": 3}, "unknown option 'iterations'"),
    ("dofp-bilinear", {"eps": 1e-3}, "unknown option 'eps'.*no options"),
    ("dofp-eari", {"eps": "tiny"}, "eps.*a number"),
    ("dofp-igri2", {"eps": "nan"}, "eps.*finite"),
])
def test_dofp_methods_reject_unknown_or_bad_options(scene64, method, options, match):
    from capssim.camera.sensor import make_sensor
    from capssim.errors import UnknownNameError
    from capssim.reconstruct.registry import reconstruct
    from capssim.simulate import simulate_capture

    capture = simulate_capture(scene64, make_sensor("none"), seed=1, psf={"type": "none"})
    with pytest.raises((UnknownNameError, InputError), match=match):
        reconstruct(capture, method, **options)
