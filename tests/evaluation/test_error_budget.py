"""The error budget (issue 32): each oracle is the oracle, each step is a difference of real runs, the run resumes,
the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from capssim.cli import app
from capssim.eval.error_budget import budget_report, ladder, runner
from capssim.eval.error_budget.oracles import model_exact_capture
from capssim.eval.evaluate import CaptureScorer
from capssim.operators.camera import caps_raw_operator, dofp_raw_operator
from capssim.psf import PSF
from capssim.reconstruct.registry import reconstruct
from capssim.sensor import make_sensor
from capssim.simulate import simulate_capture

FAST_CAPS = {"name": "caps", "options": {"iterations": 2}, "registration": "local-correlation"}

SUITE = """
name: tiny-budget
seeds: [0]
noise:
  - {name: gauss-0.02, noise: gaussian, sigma: 0.02}
methods: [dofp-bilinear]
scenes:
  - {name: texture, source: synthetic, generator: texture, size: 32}
"""


@pytest.fixture(scope="module")
def capture():
    from capssim.eval.synthetic import texture_scene

    gt = texture_scene(32, seed=3)[0]
    return simulate_capture(gt, make_sensor("gaussian", sigma=0.02), seed=7, psf=PSF.gaussian(0.7))


def _independent_raw(capture, *, noise: bool):
    """``sensor(A x)`` built here from the operators and the seed's streams, not by the oracle's code."""
    import torch

    gt = torch.from_numpy(np.asarray(capture.gt, dtype=np.float64))
    kernel = capture.psf.kernel()
    caps = caps_raw_operator(capture.hr_shape, capture.aperture_homographies(), kernel)(gt).numpy()
    dofp = dofp_raw_operator(capture.hr_shape, kernel, layout=capture.dofp_layout)(gt).numpy()
    if not noise:
        return caps.astype(np.float32), dofp.astype(np.float32)
    _, caps_rng, dofp_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(7).spawn(3))
    sensor = make_sensor("gaussian", sigma=0.02)
    return sensor.capture(caps, caps_rng), sensor.capture(dofp, dofp_rng)


def test_model_exact_capture_is_the_operator_plus_the_same_noise_draw(capture):
    caps, dofp = _independent_raw(capture, noise=True)
    oracle = model_exact_capture(capture)
    assert np.array_equal(oracle.caps_raw, caps) and np.array_equal(oracle.dofp_raw, dofp)
    # a capture that the operator does not model exactly: the oracle stays the model, not the capture
    bent = type(capture)(meta=capture.meta, caps_raw=capture.caps_raw // 2, dofp_raw=capture.dofp_raw, gt=capture.gt)
    assert np.array_equal(model_exact_capture(bent).caps_raw, caps)
    assert not np.array_equal(bent.caps_raw, caps)


def test_noise_free_rung_has_no_noise(capture):
    caps, dofp = _independent_raw(capture, noise=False)
    oracle = model_exact_capture(capture, noise=False)
    assert oracle.sensor.model == "none" and oracle.meta["oracle"]["kind"] == "noise-free"
    assert oracle.caps_raw.dtype == np.float32 and np.array_equal(oracle.caps_raw, caps)
    assert np.array_equal(oracle.dofp_raw, dofp)
    assert np.array_equal(oracle.caps_float(), caps)  # read back without any level or noise


def test_model_exact_needs_the_ground_truth(capture):
    from capssim.errors import InputError

    bare = type(capture)(meta=capture.meta, caps_raw=capture.caps_raw, dofp_raw=capture.dofp_raw, gt=None)
    with pytest.raises(InputError, match="ground truth"):
        model_exact_capture(bare)


@pytest.fixture(scope="module")
def caps_ladder(capture):
    return ladder.run_ladder(capture, FAST_CAPS, CaptureScorer(capture), views=True)


def test_ladder_steps_are_the_differences_of_independent_runs(capture, caps_ladder):
    """Each rung's scores are those of the run it names, made here independently (the capture with estimated
    warps, the noise-free oracle with true warps); each step is the later rung minus the earlier one, and the
    gap is the ceiling minus as-captured. A ladder with swapped rungs, a step of the wrong sign, a rung run on
    the wrong capture or a gap against the wrong rung fails here (the sum of the steps telescopes whatever the
    rungs hold, so it is not the check)."""
    rungs, steps = caps_ladder["rungs"], caps_ladder["steps"]
    assert [r["rung"] for r in rungs] == list(ladder.CAPS_RUNGS)
    scorer = CaptureScorer(capture)
    as_captured, _ = reconstruct(capture, "caps", iterations=2, registration="local-correlation")
    noise_free, _ = reconstruct(model_exact_capture(capture, noise=False), "caps", true_warps=True, iterations=2)
    independent = {"as-captured": scorer.score(as_captured.image).flat(),
                   "noise-free": scorer.score(noise_free.image).flat()}
    by_name = {r["rung"]: r["scores"] for r in rungs}
    for name, flat in independent.items():
        assert all(by_name[name][k] == pytest.approx(flat[k], abs=1e-9) for k in ladder.BUDGET_METRICS), name
    assert independent["noise-free"]["psnr_mean"] > independent["as-captured"]["psnr_mean"]  # the rungs differ
    for step, (a, b) in zip(steps, zip(rungs, rungs[1:])):
        assert (step["from"], step["to"], step["cause"]) == (a["rung"], b["rung"], ladder.STEP_CAUSE[b["rung"]])
        for key in ladder.BUDGET_METRICS:
            assert step[f"d_{key}"] == b["scores"][key] - a["scores"][key]
    for key in ladder.BUDGET_METRICS:
        assert caps_ladder["gap"][key] == pytest.approx(independent["noise-free"][key] - independent["as-captured"][key],
                                                       abs=1e-9)
    assert caps_ladder["ceiling"] == by_name["noise-free"]
    # a simulated capture is model-exact already: that step costs exactly nothing
    assert [s["d_psnr_mean"] for s in steps if s["to"] == "model-exact"] == [0.0]


def test_true_warps_rung_equals_a_true_warps_run(capture, caps_ladder):
    out, _ = reconstruct(capture, "caps", true_warps=True, iterations=2)
    scores = CaptureScorer(capture).score(out.image).flat()
    rung = next(r for r in caps_ladder["rungs"] if r["rung"] == "true-warps")
    assert all(rung["scores"][k] == scores[k] for k in ladder.BUDGET_METRICS)


def test_second_views_at_the_ceiling(caps_ladder):
    views = caps_ladder["views"]
    assert views["converged"]["options"] == {"iterations": ladder.CONVERGED_FACTOR * 2}
    assert views["converged"]["iterations"] == ladder.CONVERGED_FACTOR * 2
    assert math.isfinite(views["prior-on-truth"]["scores"]["psnr_mean"])


def test_dofp_methods_get_the_mosaic_and_noise_rungs(capture):
    result = ladder.run_ladder(capture, {"name": "dofp-bilinear", "options": {}}, CaptureScorer(capture))
    assert [r["rung"] for r in result["rungs"]] == list(ladder.DOFP_RUNGS)
    assert result["views"] == {}
    assert [s["cause"] for s in result["steps"]] == [ladder.STEP_CAUSE["model-exact"], ladder.STEP_CAUSE["noise-free"]]
    assert result["gap"]["psnr_mean"] > 0  # noise costs the DoFP demosaicking something


def test_a_loss_decomposes_exactly_into_its_terms():
    def rec(scores, steps):
        rungs = [{"rung": "as-captured", "scores": {"psnr_mean": scores[0]}}]
        return {"rungs": rungs, "ceiling": {"psnr_mean": scores[1]},
                "steps": [{"to": to, "d_psnr_mean": d} for to, d in steps]}

    caps = rec((30.0, 33.5), [("true-warps", 0.5), ("model-exact", 0.0), ("noise-free", 3.0)])
    dofp = rec((32.0, 33.0), [("model-exact", 0.0), ("noise-free", 1.0)])
    explained = budget_report.explain_loss(caps, dofp)
    assert explained["loss"] == pytest.approx(2.0)
    assert sum(explained["terms"].values()) == pytest.approx(explained["loss"], abs=1e-12)
    assert explained["rung"] == "noise" and explained["rung_db"] == pytest.approx(2.0)


def test_run_resumes_and_the_cli_writes_everything(tmp_path, monkeypatch):
    suite = tmp_path / "tiny.yaml"
    suite.write_text(SUITE)
    out = tmp_path / "budget"
    result = CliRunner().invoke(app, ["bench", "budget", str(suite), "-o", str(out), "-m", "dofp-bilinear",
                                      "-m", "caps-naive"])
    assert result.exit_code == 0, result.output
    lines = [json.loads(x) for x in (out / "budget.jsonl").read_text().splitlines()]
    assert {r["method"] for r in lines} == {"dofp-bilinear", "caps-naive"} and all(r["status"] == "ok" for r in lines)
    report = (out / "budget.md").read_text()
    assert "dofp-bilinear" in report and "ceiling" in report
    assert len(list(out.glob("waterfall-*.png"))) == 2

    calls = []
    monkeypatch.setattr(runner, "budget_task", lambda *a, **k: calls.append(a))
    from capssim.eval.benchmarks.suite import load_suite

    again = runner.run_budget(load_suite(suite), out, methods=["dofp-bilinear", "caps-naive"], views=False)
    assert calls == [] and [r["case_id"] for r in again.records] == [r["case_id"] for r in lines]


@pytest.mark.parametrize("args, needle", [
    (["no-such-suite"], "suite"),
    (["quick", "-m", "no-such-method"], "--method"),
])
def test_bad_input_is_one_line(tmp_path, args, needle):
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "capssim.cli.__main__", "bench", "budget", *args, "-o",
                             str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert needle in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
