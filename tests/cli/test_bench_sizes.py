"""``capssim bench reconstruct --size``: N or WxH (issue 35, item 4), refused with one line when malformed."""

from __future__ import annotations

import json

import pytest
from support.fuzz import invoke
from typer.testing import CliRunner

from capssim.cli import app
from capssim.cli.bench import parse_hr_size
from capssim.reconstruct.selection import HOLDOUT_MAX_ITERATIONS


@pytest.mark.parametrize("text, want", [("512", 512), ("2560x2048", (2560, 2048)), ("64X96", (64, 96)),
                                        (" 128x64 ", (128, 64))])
def test_sizes_parse(text, want):
    assert parse_hr_size(text) == want


@pytest.mark.parametrize("text, hint", [("2560x2050", "2560x2048"), ("9", "--size 16"), ("9x", "N or WxH"),
                                        ("1x2x3", "N or WxH"), ("-64", "N or WxH"), ("64.0", "N or WxH"),
                                        ("100000x100000", "--size")])
def test_bad_sizes_give_one_line(text, hint):
    outcome, message = invoke(["bench", "reconstruct", "--size", text, "--iterations", "1"])
    assert outcome == "error" and "--size" in message and hint in message


@pytest.mark.slow
def test_a_non_square_size_runs_untiled_and_tiled():
    r = CliRunner().invoke(app, ["bench", "reconstruct", "--size", "64x96", "--tile", "64", "--device", "cpu",
                                 "--iterations", "1", "--threads", "1", "--json"])
    assert r.exit_code == 0, r.output
    runs = json.loads(r.stdout)
    assert [run["tile"] for run in runs] == [None, 64]
    assert all(run["hr_shape"] == [96, 64] and run["wall_s"] > 0 and run["peak_mb"] > 0 for run in runs)


def test_methods_are_timed_on_the_same_capture_each_at_its_own_iterations():
    """``-m caps -m caps-plus`` (issue 36, cost): one run per method, each at its defaults unless --iterations."""
    r = CliRunner().invoke(app, ["bench", "reconstruct", "--size", "32", "-m", "caps", "-m", "caps-plus",
                                 "--device", "cpu", "--threads", "1", "--json"])
    assert r.exit_code == 0, r.output
    runs = json.loads(r.stdout)
    assert [run["method"] for run in runs] == ["caps", "caps-plus"] and runs[0]["iterations"] == 25
    # caps-plus's count is chosen by held-out validation, which runs at most HOLDOUT_MAX_ITERATIONS
    assert 0 <= runs[1]["iterations"] <= HOLDOUT_MAX_ITERATIONS
    assert all(run["hr_shape"] == [32, 32] and run["wall_s"] > 0 and run["peak_mb"] > 0 for run in runs)


@pytest.mark.parametrize("name, hint", [("dofp-igri2", "capssim bench dofp"), ("capz", "caps")])
def test_a_method_that_is_not_a_caps_method_gives_one_line(name, hint):
    outcome, message = invoke(["bench", "reconstruct", "--size", "32", "-m", name])
    assert outcome == "error" and hint in message


def test_paired_ratios_divide_round_by_round_and_take_the_median():
    """Issue 35, linear time: each round's run is divided by the same round's reference run, so a machine that
    slows down between rounds moves both alike; the median of the rounds is kept."""
    from capssim.eval.benchmarks.reconstruct_report import paired_ratios

    ref = {"device": "cpu", "method": "caps", "tile": None, "hr_shape": [512, 512], "wall_s": 10.0,
           "all_wall_s": [10.0, 20.0, 12.0]}
    big = {"device": "cpu", "method": "caps", "tile": None, "hr_shape": [1024, 1024], "wall_s": 44.0,
           "all_wall_s": [44.0, 88.0, 60.0]}
    tiled = {**big, "tile": 512, "all_wall_s": [48.0, 80.0, 48.0]}
    other = {**big, "method": "caps-plus", "tile": 512}  # no untiled run of its own: no reference
    out = paired_ratios([ref, big, tiled, other])
    assert out[0]["per_pixel_vs_reference"] == 1.0 and out[0]["reference"] == "512x512"
    assert out[1]["per_pixel_vs_reference"] == pytest.approx(1.1)        # rounds 1.1, 1.1, 1.25
    assert out[2]["per_pixel_vs_reference"] == pytest.approx(1.0)        # rounds 1.2, 1.0, 1.0
    assert out[3]["per_pixel_vs_reference"] is None


def test_a_reference_that_closes_each_round_brackets_it():
    """The reference runs again at the end of each round; the round's reference is the geometric mean of its
    opening and closing runs, so a machine that slows down within a round moves the reference too."""
    from capssim.eval.benchmarks.reconstruct_report import paired_ratios

    ref = {"device": "cpu", "method": "caps", "tile": None, "hr_shape": [512, 512], "wall_s": 10.0,
           "all_wall_s": [10.0, 10.0, 10.0], "closing_wall_s": [10.0, 40.0, 22.5]}
    big = {"device": "cpu", "method": "caps", "tile": None, "hr_shape": [1024, 1024], "wall_s": 44.0,
           "all_wall_s": [44.0, 80.0, 60.0]}
    out = paired_ratios([ref, big])
    assert out[0]["per_pixel_vs_reference"] == 1.0
    assert out[1]["per_pixel_vs_reference"] == pytest.approx(1.0)  # rounds 1.1, 1.0 (ref 20), 1.0 (ref 15)


@pytest.mark.slow
def test_repeats_run_in_rounds_and_report_the_median_and_the_paired_ratio():
    r = CliRunner().invoke(app, ["bench", "reconstruct", "--size", "32", "--size", "64x32", "--repeats", "2",
                                 "--device", "cpu", "--iterations", "1", "--threads", "1", "--json"])
    assert r.exit_code == 0, r.output
    runs = json.loads(r.stdout)
    assert [len(run["all_wall_s"]) for run in runs] == [2, 2]
    assert all(min(run["all_wall_s"]) == run["wall_s"] <= run["median_wall_s"] for run in runs)
    assert runs[0]["per_pixel_vs_reference"] == 1.0 and runs[1]["reference"] == "32x32"
    assert runs[1]["per_pixel_vs_reference"] > 0
