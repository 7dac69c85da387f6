"""Issue 21, cases 8 and 9: one meaning per flag, self-explaining pictures and reports, dark-scene scores."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture, write_reconstruction
from capssim.cli import app
from capssim.eval import plots as P
from capssim.eval.evaluate import EstimateScore
from capssim.eval.metric_records import flatten
from capssim.eval.metrics import PSNR_CAP_DB, psnr, score
from capssim.eval.suite_report import TABLE_LEGEND, dark_scene_line, results_table
from capssim.simulate import simulate_capture
from capssim.visualize import panel_figure, preview_panel

runner = CliRunner()


# -- case 8: --json means one thing ------------------------------------------------------------
def _commands(command: click.Command, path: str = "capssim"):
    yield path, command
    for name, sub in getattr(command, "commands", {}).items():
        yield from _commands(sub, f"{path} {name}")


def test_every_json_option_is_a_flag_that_prints():
    """``--json`` is a flag (stdout) in every command; ``-o/--output`` is what the command makes."""
    seen = []
    for path, command in _commands(typer.main.get_command(app)):
        for param in command.params:
            if "--json" in getattr(param, "opts", []):
                seen.append(path)
                assert param.is_flag, f"{path}: --json takes a value"
    assert {"capssim design", "capssim evaluate", "capssim mtf", "capssim scenes"} <= set(seen)


def test_design_json_prints_to_stdout(tmp_path):
    printed = runner.invoke(app, ["design", "--json"])
    assert printed.exit_code == 0, printed.output
    numbers = json.loads(printed.stdout)
    assert numbers["r_sr"] == 2.0
    table = runner.invoke(app, ["design"])
    assert table.exit_code == 0 and "r_SR (eq. 5)" in table.stdout
    out = tmp_path / "design.json"
    assert runner.invoke(app, ["design", "--json", str(out)]).exit_code == 2  # --json takes no value
    assert runner.invoke(app, ["design", "-o", str(out)]).exit_code == 2  # 0.2.0: design makes nothing; no -o
    assert not out.exists()


# -- case 8: pictures explain themselves ---------------------------------------------------------
def _texts(fig) -> str:
    return " | ".join([t.get_text() for ax in fig.axes for t in (ax.title, ax.xaxis.label, ax.yaxis.label)]
                      + [t.get_text() for t in fig.texts])


def test_demosaic_panel_has_titles_scales_and_keys(smooth_random_scene):
    image = smooth_random_scene(48, seed=2)
    fig = panel_figure(image, dolp_max=0.4, title="raw.png: dofp-eari")
    text = _texts(fig)
    for words in ("intensity S0/2", "DoLP of R, G, B", "AoP: hue = angle", "AoP (deg)", "raw.png: dofp-eari"):
        assert words in text, words
    maps, keys = fig.axes[0::2], fig.axes[1::2]
    assert len(maps) == 3 and all(ax.get_title() for ax in maps)
    white = float(keys[0].get_xlim()[1])
    assert f"{white:.3g}" in maps[0].get_title()  # the intensity scale names its white
    assert keys[1].get_xlim() == pytest.approx((0, 0.4))  # DoLP scale 0 .. dolp_max
    assert keys[2].get_xlim() == pytest.approx((0, 180)) and keys[2].get_ylim() == pytest.approx((0, 0.4))
    rendered = preview_panel(image, dolp_max=0.4)
    assert rendered.ndim == 3 and rendered.shape[1] > 3 * 260 and 0 <= rendered.min() and rendered.max() <= 1


def test_report_crops_have_titles_and_keys(tmp_path, monkeypatch, smooth_random_scene):
    figures = []
    monkeypatch.setattr(P, "_save", lambda fig, path: figures.append(fig) or path)
    gt = smooth_random_scene(48, seed=4)
    P.crops(gt, {"m": gt * 0.9}, tmp_path / "c.png", title="scene / noise", crop=32)
    text = _texts(figures[0])
    for words in ("white =", "DoLP of R, G, B", "AoP: hue = angle", "AoP (deg)", "DoLP", "scene / noise"):
        assert words in text, words


# -- case 8: the report's memory column is the method's -----------------------------------------------
def _record(method: str, rss: float, delta: float, psnr_mean: float, gt_peak: float = 1.0) -> dict:
    return {"status": "ok", "scene": "s", "noise": "n", "seed": 0, "method": method, "wall_time_s": 1.0,
            "peak_rss_mb": rss, "peak_rss_delta_mb": delta, "cuda_peak_mb": None,
            "metrics": {"psnr_mean": psnr_mean}, "metric_settings": {"gt_peak": gt_peak}}


def test_report_shows_per_method_memory_and_says_what_it_is():
    recs = [_record("caps", 600.0, 337.0, 30.0), _record("dofp-bilinear", 830.0, 4.0, 25.0)]
    table = results_table(recs, ["caps", "dofp-bilinear"])
    assert "memory (MB)" in table and "peak RSS" not in table
    assert "| dofp-bilinear | 25.00 | 1.00 | 4 | 1 |" in table and "830" not in table
    assert "peak_rss_delta_mb" in TABLE_LEGEND and "rose above its level just before the method" in TABLE_LEGEND
    gpu = results_table([dict(recs[0], cuda_peak_mb=123.4)], ["caps"])
    assert "CUDA peak (MB)" in gpu and "| 123 |" in gpu


# -- case 9: dark scenes -------------------------------------------------------------------------
@pytest.fixture
def dark_pair(smooth_random_scene):
    """``(gt, good, poor)``: a nearly black ``(12, 48, 48)`` scene and estimates with 1 % and 10 % error."""
    gt = smooth_random_scene(48, seed=1).astype(np.float64) * 1e-4
    rng = np.random.default_rng(0)
    good = gt * (1 + 0.01 * rng.standard_normal(gt.shape))
    poor = gt * (1 + 0.10 * rng.standard_normal(gt.shape))
    return gt, good, poor


def test_dark_scene_scores_tell_methods_apart_and_fixed_peak_ones_are_unchanged(dark_pair):
    gt, good, poor = dark_pair
    a, b = score(good, gt), score(poor, gt)
    # the fixed-peak scores: at the cap and SSIM 1.0000 for both, as before (values by their definitions)
    for r, est in ((a, good), (b, poor)):
        assert r["psnr_mean"] == PSNR_CAP_DB and round(r["ssim_mean"], 4) == 1.0
        assert r["cpsnr"]["0"] == psnr(est[0:3, 8:-8, 8:-8], gt[0:3, 8:-8, 8:-8], data_range=1.0) == PSNR_CAP_DB
        assert any("cap with a non-zero error" in n for n in r["notes"])
        assert any("DoLP scores compare zeros" in n for n in r["notes"])
    # the scores against the ground truth's peak: 20 dB apart (10x the error), SSIM well apart
    assert a["psnr_gt_peak_mean"] - b["psnr_gt_peak_mean"] == pytest.approx(20.0, abs=1.0)
    assert a["ssim_gt_peak_mean"] > 0.98 > 0.8 > b["ssim_gt_peak_mean"]
    for key in ("s0_psnr_gt_peak", "s1_psnr_gt_peak", "s2_psnr_gt_peak"):
        assert a[key] > b[key] + 10, key
    assert all(a["cpsnr_gt_peak"][k] > b["cpsnr_gt_peak"][k] + 10 for k in a["cpsnr_gt_peak"])
    peak = a["settings"]["gt_peak"]
    assert peak == pytest.approx(float(gt[:, 8:-8, 8:-8].max()))
    # scale invariance: the dark scene's GT-peak scores are those of the same scene at full exposure
    bright = score(good / peak, gt / peak)
    assert bright["psnr_gt_peak_mean"] == pytest.approx(a["psnr_gt_peak_mean"], abs=1e-6)
    assert bright["ssim_gt_peak_mean"] == pytest.approx(a["ssim_gt_peak_mean"], abs=1e-6)
    assert bright["psnr_mean"] == pytest.approx(a["psnr_gt_peak_mean"], abs=1e-6)


def test_gt_peak_scores_on_ordinary_and_empty_scenes(smooth_random_scene):
    gt = smooth_random_scene(48, seed=3).astype(np.float64)
    est = gt + 0.01
    r = score(est, gt, with_ssim=False)
    peak = r["settings"]["gt_peak"]
    # below the cap: the fixed-peak PSNR shifted by 20 log10(P) (P < 1: lower)
    assert r["psnr_gt_peak_mean"] == pytest.approx(r["psnr_mean"] + 20 * math.log10(peak), abs=1e-9)
    assert r["ssim_gt_peak_mean"] is None and not r["notes"]
    for conv in ("tokyotech", "qiu"):  # Stokes scaling of every convention
        c = score(est, gt, convention=conv, with_ssim=False)
        assert c["s0_psnr_gt_peak"] == pytest.approx(c["s0_psnr"] + 20 * math.log10(c["settings"]["gt_peak"]))
    zero = score(np.full_like(gt, 0.1), np.zeros_like(gt))
    assert zero["psnr_gt_peak_mean"] is None and zero["ssim_gt_peak"] is None
    assert any("*_gt_peak" in n for n in zero["notes"])
    flat = flatten(zero)
    assert "psnr_gt_peak_mean" in flat and flat["psnr_gt_peak_mean"] is None


def _dark_capture(path: Path, dark_pair) -> Path:
    gt, good, poor = dark_pair
    cap = simulate_capture(gt.astype(np.float32), make_sensor("none"), seed=0)
    write_capture(path, cap)
    write_reconstruction(path, "good", good.astype(np.float32), {"wall_time_s": 1.0})
    write_reconstruction(path, "poor", poor.astype(np.float32), {"wall_time_s": 1.0})
    return path


def test_dark_scene_scores_reach_metrics_json_tables_results_and_report(tmp_path, dark_pair):
    cap = _dark_capture(tmp_path / "dark", dark_pair)
    r = runner.invoke(app, ["evaluate", str(cap)])
    assert r.exit_code == 0, r.output
    assert "PSNR-GTpk" in r.output and "SSIM-GTpk" in r.output and "the ground truth's peak" in r.output
    methods = json.loads((cap / "metrics.json").read_text())["methods"]
    good, poor = (methods[m]["metrics"] for m in ("good", "poor"))
    assert good["psnr_mean"] == poor["psnr_mean"] == PSNR_CAP_DB
    assert good["psnr_gt_peak_mean"] > poor["psnr_gt_peak_mean"] + 10
    printed = json.loads(runner.invoke(app, ["evaluate", str(cap), "--json"]).stdout)
    assert printed["methods"]["good"]["metrics"]["psnr_gt_peak_mean"] == good["psnr_gt_peak_mean"]
    # results.jsonl holds EstimateScore.flat(); the report's tables show the new columns and a dark-scene line
    flat = EstimateScore(good).flat()
    assert flat["psnr_gt_peak_mean"] == good["psnr_gt_peak_mean"] and "ssim_gt_peak.0-R" in flat
    recs = [dict(_record(m, 500.0, 10.0, PSNR_CAP_DB, good["settings"]["gt_peak"]), metrics=EstimateScore(x).flat())
            for m, x in (("good", good), ("poor", poor))]
    table = results_table(recs, ["good", "poor"])
    assert "PSNR/GT peak" in table and "SSIM/GT peak" in table
    assert "Dark scene" in dark_scene_line(recs) and dark_scene_line([_record("m", 1, 1, 30.0)]) == ""
