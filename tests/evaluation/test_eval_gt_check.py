"""eval.gt_check / ``capssim gt-check``: inter-image offsets and Stokes consistency of a ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.ndimage import fourier_shift

from capssim.errors import InputError
from capssim.eval.gt_check import aligned_ground_truth, check_ground_truth


@pytest.fixture
def shifted_scene_of(smooth_random_scene):
    """Factory of :func:`shifted_scene` scenes."""

    def shifted_scene(dx: float, dy: float, *, angle_index: int = 2, size: int = 96, pad: int = 16,
                      dolp_max: float = 0.08) -> np.ndarray:
        """A consistent scene whose analyzer image ``angle_index`` is moved by ``(dx, dy)`` px (content)."""
        big = smooth_random_scene(size + 2 * pad, seed=3, dolp_max=dolp_max).astype(np.float64)
        sl = slice(3 * angle_index, 3 * angle_index + 3)
        for c in range(sl.start, sl.stop):
            big[c] = np.fft.ifft2(fourier_shift(np.fft.fft2(big[c]), (dy, dx))).real
        return big[:, pad:-pad, pad:-pad].astype(np.float32)

    return shifted_scene


def test_a_consistent_scene_is_consistent(shifted_scene_of):
    report = check_ground_truth(shifted_scene_of(0.0, 0.0))
    assert report["consistent"], report["verdict"]
    assert max(r["mean_displacement_px"] for r in report["alignment"]) < 0.02
    assert max(s["rms_percent_of_s0"] for s in report["stokes"]["per_colour"]) < 0.05
    assert report["stokes"]["gains"]["g90"] == pytest.approx(1.0, abs=1e-3)


def test_strong_polarization_texture_is_still_judged_consistent(shifted_scene_of):
    # the alignment estimate is biased by strong polarization texture (documented); Malus's law is not
    report = check_ground_truth(shifted_scene_of(0.0, 0.0, dolp_max=0.6))
    assert report["consistent"], report["verdict"]
    assert max(s["excess_percent"] for s in report["stokes"]["per_colour"]) < 0.05


def test_a_moved_analyzer_image_is_measured(shifted_scene_of):
    report = check_ground_truth(shifted_scene_of(0.3, -0.2))
    assert not report["consistent"]
    assert "inconsistent" in report["verdict"]
    row90 = report["alignment"][1]
    # content moved by +d: the reference pixel x is found at x + d in the moved image
    assert row90["shift_x_px"] == pytest.approx(0.3, abs=0.02)
    assert row90["shift_y_px"] == pytest.approx(-0.2, abs=0.02)
    for other in (report["alignment"][0], report["alignment"][2]):
        assert other["mean_displacement_px"] < 0.02
    assert report["stokes"]["per_colour"][1]["rms_percent_of_s0"] > 0.5
    chk = report["alignment_check"]
    assert chk["reliable"]
    assert chk["stokes_rms_percent_aligned"] < chk["stokes_rms_percent_unaligned"] / 3


def test_a_wrong_alignment_is_flagged_unreliable(shifted_scene_of):
    import torch

    from capssim.eval.gt_check import _alignment_check

    scene = torch.as_tensor(shifted_scene_of(0.0, 0.0, dolp_max=0.6), dtype=torch.float64).reshape(4, 3, 96, 96)
    lum = scene.mean(dim=1)
    valid = torch.ones(96, 96, dtype=torch.float64)
    wrong = np.stack([np.eye(3)] * 3)
    wrong[0, 0, 2] = 1.5                                                 # 45 deg image 1.5 px off
    chk = _alignment_check(lum, valid, wrong)
    assert not chk["reliable"]
    assert chk["stokes_rms_percent_aligned"] > chk["stokes_rms_percent_unaligned"]
    assert _alignment_check(lum, valid, np.stack([np.eye(3)] * 3))["reliable"]


def test_the_quantization_floor_is_not_an_inconsistency(shifted_scene_of):
    scene = shifted_scene_of(0.0, 0.0)
    eight_bit = np.round(scene * 255) / 255
    report = check_ground_truth(eight_bit.astype(np.float32), bit_depth=8)
    st = report["stokes"]["per_colour"][0]
    assert st["rms_percent_of_s0"] > 0.2                                  # the floor is there
    assert st["rms_percent_of_s0"] == pytest.approx(st["quantization_floor_percent"], rel=0.3)
    assert report["consistent"], report["verdict"]
    with pytest.raises(InputError, match="bit_depth"):
        check_ground_truth(scene, bit_depth=7)


def test_aligned_ground_truth_removes_the_offset(shifted_scene_of):
    moved = shifted_scene_of(0.3, -0.2)
    report = check_ground_truth(moved)
    fixed = aligned_ground_truth(moved, report["alignment_matrices"])
    assert fixed.shape == moved.shape and fixed.dtype == np.float32
    again = check_ground_truth(fixed)
    assert again["alignment"][1]["mean_displacement_px"] < 0.02
    assert again["stokes"]["per_colour"][1]["rms_percent_of_s0"] < report["stokes"]["per_colour"][1][
        "rms_percent_of_s0"] / 3


def test_unequal_gains_are_found(shifted_scene_of):
    scene = shifted_scene_of(0.0, 0.0)
    scene[6:9] *= 0.97                       # the 90 deg image 3 % darker (light drift between shots)
    report = check_ground_truth(scene)
    assert report["stokes"]["gains"]["g90"] == pytest.approx(1 / 0.97, abs=0.01)
    assert report["stokes"]["rms_percent_after_gain_fit"] < 0.1
    assert report["stokes"]["per_colour"][0]["low_frequency_share"] > 0.5


def test_flat_and_clipped_ground_truths_give_finite_reports(shifted_scene_of):
    flat = np.full((12, 48, 48), 0.5, np.float32)
    report = check_ground_truth(flat)
    assert np.isfinite(report["alignment"][0]["mean_displacement_px"])
    clipped = np.clip(shifted_scene_of(0.0, 0.0) * 3.0, 0, 1)
    report = check_ground_truth(clipped)
    assert min(report["clipped_share"]) > 0.0
    assert report["consistent"], report["verdict"]


@pytest.mark.parametrize("bad, match", [
    (np.zeros((4, 64, 64), np.float32), "shape"),
    (np.zeros((12, 16, 16), np.float32), "at least 32"),
    (np.zeros((12, 64, 64), np.uint8), "dtype"),
    (np.full((12, 64, 64), np.nan, np.float32), "NaN"),
])
def test_bad_ground_truths_are_rejected(bad, match):
    with pytest.raises(InputError, match=match):
        check_ground_truth(bad)


def test_cli_reports_and_writes_an_aligned_tiff(tmp_path, shifted_scene_of):
    from typer.testing import CliRunner

    from capssim.cli import app
    from capssim.files.imageio import read_gt_scene, write_tiff

    src = tmp_path / "moved.tiff"
    write_tiff(src, shifted_scene_of(0.25, 0.0))
    out = tmp_path / "aligned.tiff"
    result = CliRunner().invoke(app, ["gt-check", str(src), "--write-aligned", str(out)])
    assert result.exit_code == 0, result.output
    assert "inconsistent" in result.output and " 90 deg" in result.output
    printed = CliRunner().invoke(app, ["gt-check", str(src), "--json"])
    assert printed.exit_code == 0, printed.output
    report = json.loads(printed.stdout)  # stdout holds the JSON alone
    assert report["alignment"][1]["shift_x_px"] == pytest.approx(0.25, abs=0.02)
    aligned, _ = read_gt_scene(out)
    assert check_ground_truth(aligned)["alignment"][1]["mean_displacement_px"] < 0.02
    again = CliRunner().invoke(app, ["gt-check", str(src), "--write-aligned", str(out)])
    assert again.exit_code != 0 and "--overwrite" in str(again.exception)


def test_weak_polarization_cross_check_needs_enough_weakly_polarized_pixels(shifted_scene_of):
    from capssim.eval.gt_check import MIN_WEAKLY_POLARIZED_SHARE

    few = check_ground_truth(shifted_scene_of(0.0, 0.0), dolp_max=0.005)     # almost nothing that weak
    assert few["weakly_polarized_share"] < MIN_WEAKLY_POLARIZED_SHARE
    assert few["alignment_weakly_polarized"] is None
    many = check_ground_truth(shifted_scene_of(0.0, 0.0), dolp_max=0.5)
    assert many["weakly_polarized_share"] >= MIN_WEAKLY_POLARIZED_SHARE
    assert len(many["alignment_weakly_polarized"]) == 3
