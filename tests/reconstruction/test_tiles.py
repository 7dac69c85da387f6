"""Issue 35 items 1-2: tile geometry, seamless blending, the memory choice, the tile's capture and the
tiled run (equal to the untiled one, resumable after a kill)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.errors import InputError, ResourceError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.selection import SELECTED_NOTHING
from capssim.reconstruct.tiles import (
    MIN_TILE,
    TileBlender,
    estimate_bytes,
    plan_tiles,
    reconstruct_tiled,
    split_axis,
    tile_for_budget,
    tile_weight,
)
from capssim.reconstruct.tiles.crop import crop_capture, translation
from capssim.reconstruct.tiles.memory import FRAME_BYTES_PER_HR_PIXEL
from capssim.reconstruct.tiles.run import choose_layout
from capssim.simulate import simulate_capture

#: the selection record of a run whose every choice was given as an option

GIB = 2**30


# -- geometry ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("length, tile", [(1024, 512), (2048, 512), (1000, 300), (128, 64), (64, 500), (2560, 700)])
def test_split_axis_covers_the_frame_in_aligned_cores(length, tile):
    cores = split_axis(length, tile)
    assert cores[0][0] == 0 and cores[-1][1] == length
    assert all(a[1] == b[0] for a, b in zip(cores, cores[1:]))
    assert all(a % 4 == 0 and b - a <= tile + 4 for a, b in cores)
    assert len(cores) == -(-length // tile)


def test_plan_tiles_1024_in_4_tiles_of_at_most_512():
    layout = plan_tiles((1024, 1024), 512, margin=40)
    assert len(layout.tiles) == 4 and layout.grid == (2, 2)
    for t in layout.tiles:
        top, left, bottom, right = t.core
        assert bottom - top <= 512 and right - left <= 512
        assert all(v % 4 == 0 for v in t.window)
        assert t.window[0] == max(0, top - 40) and t.window[2] == min(1024, bottom + 40)
    assert layout.largest_window == (552, 552)


@pytest.mark.parametrize("tile, margin, overlap", [(MIN_TILE - 4, 8, None), (128, 6, None), (128, 8, 20)])
def test_plan_tiles_refuses_bad_sizes(tile, margin, overlap):
    with pytest.raises(InputError):
        plan_tiles((256, 256), tile, margin=margin, overlap=overlap)


# -- blending -------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape, tile, margin, overlap", [((256, 192), 64, 16, 16), ((256, 256), 100, 24, 30),
                                                          ((128, 256), 64, 8, 0), ((96, 96), 96, 8, 8)])
def test_weights_are_a_partition_of_unity(shape, tile, margin, overlap):
    layout = plan_tiles(shape, tile, margin=margin, overlap=overlap)
    total = np.zeros(shape)
    for t in layout.tiles:
        w = tile_weight(t, shape, overlap)
        assert w.min() >= 0 and w.max() <= 1
        total[t.window[0]:t.window[2], t.window[1]:t.window[3]] += w
    np.testing.assert_allclose(total, 1.0, atol=1e-12)


def _blend(layout, frame):
    blender = TileBlender(layout, frame.shape[0])
    for t in layout.tiles:
        blender.add(t, frame[:, t.window[0]:t.window[2], t.window[1]:t.window[3]])
    return blender.result()


def test_blending_keeps_a_constant_and_a_linear_ramp_exactly():
    layout = plan_tiles((256, 192), 64, margin=16)
    rows, cols = np.mgrid[0:256, 0:192].astype(np.float32)
    frame = np.stack([np.full((256, 192), 0.37, np.float32), 0.002 * rows + 0.003 * cols + 0.1])
    np.testing.assert_allclose(_blend(layout, frame), frame, rtol=0, atol=1e-6)


def test_blending_fades_between_disagreeing_tiles_without_a_step():
    layout = plan_tiles((64, 128), 64, margin=16, overlap=16)
    blender = TileBlender(layout, 1)
    for t, value in zip(layout.tiles, (0.0, 1.0)):
        blender.add(t, np.full((1, *t.shape), value))
    row = blender.result()[0, 10]
    assert row[0] == 0 and row[-1] == 1 and np.all(np.diff(row) >= 0)
    assert np.max(np.diff(row)) <= 1 / 16 + 1e-6  # a ramp over the 16 px overlap, no step


# -- memory ---------------------------------------------------------------------------------------
def test_tile_for_budget_fits_and_grows_with_the_budget():
    shape = (2048, 2560)
    frame = FRAME_BYTES_PER_HR_PIXEL * shape[0] * shape[1]
    sides = [tile_for_budget(shape, gib * GIB, margin=40) for gib in (2, 3, 4)]
    assert sides == sorted(sides) and sides[0] < sides[-1]
    for gib, side in zip((2, 3, 4), sides):
        assert side % 4 == 0 and frame + estimate_bytes((side + 80, side + 80)) <= gib * GIB
        assert frame + estimate_bytes((side + 84, side + 84)) > gib * GIB  # the largest that fits
    two = tile_for_budget(shape, 4 * GIB, margin=40, workers=2)  # workers share the budget
    assert two < sides[-1] and frame + 2 * estimate_bytes((two + 80, two + 80)) <= 4 * GIB
    assert tile_for_budget((256, 256), 64 * GIB, margin=40) == 256  # the whole frame fits


def test_tile_for_budget_refuses_a_budget_below_the_smallest_tile():
    with pytest.raises(ResourceError, match="--memory-gb"):
        tile_for_budget((1024, 1024), 0.2 * GIB, margin=40)


@pytest.fixture(scope="module")
def capture128(smooth_random_scene):
    return simulate_capture(smooth_random_scene(128, seed=1), seed=3)


def test_choose_layout_untiled_when_the_frame_fits_else_tiles(capture128):
    homs = capture128.aperture_homographies()
    assert choose_layout(capture128, {}, aperture_homographies=homs, memory_gb=64) is None
    # 0.375 GiB leaves ~27 MB past the process's base: the 128^2 frame needs ~40 MB untiled; tiled, ~3 MB for
    # the frame and ~16 MB for an 80^2 window
    layout = choose_layout(capture128, {}, aperture_homographies=homs, memory_gb=0.375, margin=8)
    assert layout is not None and len(layout.tiles) == 4 and layout.margin == 8
    assert all(estimate_bytes(t.shape) + FRAME_BYTES_PER_HR_PIXEL * 128**2 <= 0.375 * GIB for t in layout.tiles)
    assert len(choose_layout(capture128, {}, aperture_homographies=homs, tile=64).tiles) == 4


# -- the tile's capture ---------------------------------------------------------------------------
def test_crop_rebases_the_warps_and_keeps_the_bayer_sites(capture128):
    homs = capture128.aperture_homographies()
    layout = plan_tiles(capture128.hr_shape, 64, margin=16)
    t = layout.tiles[3]
    part = crop_capture(capture128, t, homs)
    assert part.hr_shape == t.shape and part.caps_raw.shape == (4, t.shape[0] // 2, t.shape[1] // 2)
    np.testing.assert_allclose(part.aperture_homographies()[0], np.eye(3), atol=1e-12)
    for n, (oy, ox) in enumerate(part.meta["tile"]["aperture_offsets_hr"]):
        assert oy % 4 == 0 and ox % 4 == 0
        np.testing.assert_array_equal(part.caps_raw[n], capture128.caps_raw[n, oy // 2:oy // 2 + t.shape[0] // 2,
                                                                            ox // 2:ox // 2 + t.shape[1] // 2])
        whole = translation(-ox, -oy) @ homs[n] @ translation(t.window[1], t.window[0])
        np.testing.assert_allclose(part.aperture_homographies()[n], whole, atol=1e-9)


# -- the tiled run --------------------------------------------------------------------------------
def _psnr(image, gt):
    return 10 * np.log10(1.0 / np.mean((image - gt) ** 2))


def test_tiled_caps_plus_equals_untiled(capture128, smooth_random_scene):
    """caps-plus's front-end initialization (the demosaicked apertures) is cut with the tile like the rest."""
    gt = smooth_random_scene(128, seed=1)
    fixed = {"iterations": 2, "polarization_filter": "none", "data_term": "cagf-stokes", "init": "agree"}
    whole, _ = reconstruct(capture128, "caps-plus", true_warps=True, **fixed)
    tiled, record = reconstruct_tiled(capture128, "caps-plus", tile=64, true_warps=True, **fixed)
    assert record["tiles"]["grid"] == [2, 2]
    assert record["frame_options"] == fixed  # every choice given: nothing selected, the values passed on
    assert abs(_psnr(tiled.image, gt) - _psnr(whole.image, gt)) < 0.05


def test_tiled_caps_equals_untiled_and_resumes_after_a_kill(capture128, smooth_random_scene, tmp_path):
    gt = smooth_random_scene(128, seed=1)
    whole, _ = reconstruct(capture128, "caps", true_warps=True, iterations=2)
    tiled, record = reconstruct_tiled(capture128, "caps", tile=64, true_warps=True, iterations=2)
    assert record["tiles"]["grid"] == [2, 2]
    assert abs(_psnr(tiled.image, gt) - _psnr(whole.image, gt)) < 0.05
    assert np.max(np.abs(tiled.image - whole.image)) < 5e-3

    def killed_after_two(function, jobs):
        for index, job in enumerate(jobs[:2]):
            yield index, function(*job)
        raise KeyboardInterrupt  # the run is killed while the third tile runs

    parts = tmp_path / "parts"
    with pytest.raises(KeyboardInterrupt):
        reconstruct_tiled(capture128, "caps", tile=64, true_warps=True, iterations=2, parts=parts,
                          runner=killed_after_two)
    assert len(list(parts.glob("tile_*.npz"))) == 2
    resumed, record = reconstruct_tiled(capture128, "caps", tile=64, true_warps=True, iterations=2, parts=parts)
    assert sum(t["resumed"] for t in record["tiles"]["tiles"]) == 2
    np.testing.assert_array_equal(resumed.image, tiled.image)


# -- registration within the budget -----------------------------------------------------------------
def test_registration_window_only_when_the_frame_does_not_fit():
    from capssim.reconstruct.tiles.memory import registration_bytes
    from capssim.reconstruct.tiles.run import registration_window

    assert registration_window((2048, 2560), 64 * GIB) is None
    window = registration_window((2048, 2560), 4 * GIB)
    top, left, bottom, right = window
    assert registration_bytes((bottom - top, right - left)) <= 4 * GIB
    assert (bottom - top, right - left) != (2048, 2560) and all(v % 4 == 0 for v in window)
    assert abs((top + bottom) / 2 - 1024) <= 4 and abs((left + right) / 2 - 1280) <= 4  # centred


def test_warps_registered_on_a_window_are_the_whole_frames(capture128, monkeypatch):
    """The window's warps, re-based to the frame, are the frame's: with a registration that returns the true
    warps of the cropped apertures, the composition gives back the frame's true warps exactly."""
    import capssim.reconstruct.tiles.run as tiles_run
    from capssim.camera.array_geometry import ArrayGeometry
    from capssim.reconstruct.run_context import RunContext, StageTimer

    truth = capture128.aperture_homographies()
    window = (16, 24, 112, 104)

    def true_crop_geometry(cropped, context, *, images, saturated):
        offsets = cropped.meta["tile"]["aperture_offsets_hr"]
        homs = np.stack([translation(-ox, -oy) @ h @ translation(window[1], window[0])
                         for (oy, ox), h in zip(offsets, truth)])
        return ArrayGeometry(homs, cropped.hr_shape), {"mode": "test"}

    monkeypatch.setattr(tiles_run, "method_geometry", true_crop_geometry)
    context = RunContext(device=torch.device("cpu"), timer=StageTimer(), reuse_registration=False)
    homs, record = tiles_run._registered_on_window(capture128, context, window)
    assert record["window"] == list(window)
    np.testing.assert_allclose(homs, truth, atol=1e-9)


def test_a_tiled_caps_plus_makes_its_choices_once_for_the_frame(capture128, monkeypatch):
    """caps-plus chooses its count and filter on the frame's central window: a tiled run chooses them once, before
    the frame is cut, and every tile runs them as given (a tile's own validation could choose otherwise). The
    untiled run's choices on the same window: tests/reconstruction/test_caps_plus_model.py."""
    import capssim.reconstruct.selection.holdout_selection as holdout_selection

    monkeypatch.setattr(holdout_selection, "HOLDOUT_WINDOW", 64)  # a window inside the frame, as on a large one
    calls = []

    def recording_runner(function, jobs):
        for index, job in enumerate(jobs):
            calls.append(dict(job[3]))
            yield index, function(*job)

    _, record = reconstruct_tiled(capture128, "caps-plus", tile=64, true_warps=True, runner=recording_runner,
                                  prior="none")
    frame = record["frame_options"]
    assert set(frame) == {"iterations", "polarization_filter", "data_term", "init"}
    assert isinstance(frame["iterations"], int)
    assert calls == [{"prior": "none", **frame}] * 4 and record["options"] == {"prior": "none", **frame}
    assert record["params"]["iterations"] == frame["iterations"]
    assert record["params"]["selection"] == SELECTED_NOTHING  # the tile selected nothing
    _, record = reconstruct_tiled(capture128, "caps-plus", tile=64, true_warps=True, iterations=1,
                                  polarization_filter="4,0.01", prior="none")
    assert record["frame_options"] == {"iterations": 1, "polarization_filter": "4,0.01",
                                       "data_term": frame["data_term"], "init": frame["init"]}
    assert record["params"]["iterations"] == 1 and record["params"]["polarization_filter"] == "4,0.01"
