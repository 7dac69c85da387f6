"""The error budget's model-fidelity measure and the results page's generated findings (issue 32)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from capssim.camera.psf import PSF
from capssim.camera.sensor import make_sensor
from capssim.captures.capture import Capture
from capssim.eval.error_budget import findings
from capssim.eval.error_budget.oracles import capture_mismatch, model_exact_capture
from capssim.simulate import simulate_capture


@pytest.fixture(scope="module")
def capture():
    from capssim.eval.synthetic import texture_scene

    gt = texture_scene(32, seed=5)[0]
    return simulate_capture(gt, make_sensor("gaussian", sigma=0.02), seed=3, psf=PSF.gaussian(0.7))


def test_a_simulated_capture_is_model_exact(capture):
    fid = capture_mismatch(capture, model_exact_capture(capture))
    assert fid["caps_rms"] == 0.0 and fid["dofp_rms"] == 0.0
    assert fid["caps_rms_per_aperture"] == [0.0] * 4 and fid["caps_rms_over_noise"] == 0.0
    assert fid["noise_sigma"] == pytest.approx(0.02, rel=0.01)


def test_the_mismatch_is_what_the_operator_does_not_model(capture):
    """A signal added to one aperture only (in raw units) comes back as that aperture's RMS."""
    oracle = model_exact_capture(capture)
    sensor = capture.sensor
    bent = np.array(capture.caps_float(), dtype=np.float64)
    bump = np.zeros_like(bent)
    bump[2, 10:20, 10:20] = 0.1
    raw = np.asarray(np.round((bent + bump) * (sensor.white_level - sensor.black_level) + sensor.black_level),
                     dtype=capture.caps_raw.dtype)
    fid = capture_mismatch(Capture(meta=capture.meta, caps_raw=raw, dofp_raw=capture.dofp_raw, gt=capture.gt), oracle)
    inner = bump[2, 4:-4, 4:-4]
    step = 1.0 / (sensor.white_level - sensor.black_level)
    assert fid["caps_rms_per_aperture"][2] == pytest.approx(np.sqrt(np.mean(inner ** 2)), abs=step)
    assert fid["caps_rms_per_aperture"][0] == fid["caps_rms_per_aperture"][1] == fid["caps_rms_per_aperture"][3] == 0.0
    assert fid["caps_rms_over_noise"] == pytest.approx(fid["caps_rms"] / fid["noise_sigma"])


def _record(scene, method, rungs, fid=None):
    out = {"status": "ok", "scene": scene, "noise": "n", "seed": 0, "method": method, "scene_source": "render",
           "rungs": [{"rung": name, "scores": {"psnr_mean": v, "s0_psnr": v + 1, "dolp_psnr": None,
                                               "aop_mae_deg": None}} for name, v in rungs],
           "model_fidelity": fid}
    out["steps"] = [{"from": a["rung"], "to": b["rung"], "cause": b["rung"],
                     **{f"d_{k}": None if a["scores"][k] is None else b["scores"][k] - a["scores"][k]
                        for k in a["scores"]}}
                    for a, b in zip(out["rungs"], out["rungs"][1:])]
    return out


def test_fidelity_table_flags_a_model_exact_step_over_the_limit():
    fid = {"caps_rms": 0.01, "caps_rms_per_aperture": [0, 0.01, 0.01, 0.01], "dofp_rms": 0.0,
           "noise_sigma": 0.01, "caps_rms_over_noise": 1.0}
    small = _record("a", "caps", [("as-captured", 30), ("true-warps", 30.1), ("model-exact", 30.2), ("noise-free", 31)],
                    fid)
    large = _record("b", "caps", [("as-captured", 30), ("true-warps", 30.1), ("model-exact", 29.0), ("noise-free", 31)],
                    fid)
    run = SimpleNamespace(spec={"name": "s"}, records=[small, large])
    rows = {line.split(" | ")[1]: line for line in findings.fidelity_table([run]).splitlines()[2:]}
    assert rows["a"].endswith("| no |") and "caps: +0.10 / +0.10" in rows["a"]
    assert rows["b"].endswith("| **yes** |") and "caps: -1.10 / -1.10" in rows["b"]


def test_cases_section_puts_the_two_ladders_side_by_side():
    caps = _record("textured", "caps", [("as-captured", 30), ("true-warps", 31), ("model-exact", 31), ("noise-free", 33)])
    iccp = _record("textured", "caps-iccp", [("as-captured", 31), ("true-warps", 31.5), ("model-exact", 31.5),
                                             ("noise-free", 32)])
    text = findings.cases_section([SimpleNamespace(spec={"name": "ablation"}, records=[caps, iccp])])
    assert "`textured` (ablation, n, seed 0): `caps` against `caps-iccp`" in text
    assert "as-captured: +1.00; true-warps: +0.50; model-exact: +0.50; noise-free: -1.00 dB" in text
    assert findings.cases_section([SimpleNamespace(spec={"name": "x"}, records=[caps])]).startswith("None")


def test_a_rung_with_the_same_input_is_reused_and_equals_a_real_run(capture):
    """A simulated capture is model-exact: the model-exact rung reuses the true-warps run; running it for
    real gives the same scores, bit for bit (the reconstruction is deterministic)."""
    from capssim.eval.error_budget.ladder import BUDGET_METRICS, run_ladder
    from capssim.eval.evaluate import CaptureScorer
    from capssim.reconstruct.registry import reconstruct

    scorer = CaptureScorer(capture)
    result = run_ladder(capture, {"name": "caps", "options": {"iterations": 2}}, scorer, views=False)
    rungs = {r["rung"]: r for r in result["rungs"]}
    assert rungs["model-exact"]["same_input_as"] == "true-warps" and rungs["model-exact"]["wall_time_s"] == 0.0
    assert "same_input_as" not in rungs["true-warps"] and "same_input_as" not in rungs["noise-free"]
    out, _ = reconstruct(model_exact_capture(capture), "caps", true_warps=True, iterations=2)
    real = scorer.score(out.image).flat()
    assert all(rungs["model-exact"]["scores"][k] == real[k] for k in BUDGET_METRICS)


def test_scene_geometry_reads_the_capture_meta(tmp_path):
    import json

    for name, meta in {"star": {"kind": "rendered", "scene": {"planar": True}},
                       "glass": {"kind": "rendered", "scene": {"planar": False}},
                       "sim": {"kind": "simulated"}}.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "meta.json").write_text(json.dumps(meta))
    geometry = {n: findings.scene_geometry({"capture": str(tmp_path / n)}) for n in ("star", "glass", "sim", "gone")}
    assert geometry == {"star": "planar", "glass": "3-D", "sim": "simulated", "gone": "?"}


def test_report_only_rewrites_the_reports_from_stored_records_and_runs_nothing(tmp_path, monkeypatch):
    import json

    from typer.testing import CliRunner

    from capssim.cli import app
    from capssim.eval.error_budget import runner

    suite = tmp_path / "tiny.yaml"
    suite.write_text("name: tiny\nseeds: [0]\nnoise:\n  - {name: clean, noise: none}\nmethods: [caps]\n"
                     "scenes:\n  - {name: a, source: synthetic, generator: texture, size: 32}\n")
    rungs = [("as-captured", 30.0), ("true-warps", 30.5), ("model-exact", 30.5), ("noise-free", 31.0)]
    records = [dict(_record("a", m, rungs), suite="tiny", key=f"a/clean/seed0/{m}", case_id=m) for m in ("caps", "x")]
    for r in records:
        r["ceiling"] = r["rungs"][-1]["scores"]
    out = tmp_path / "out"
    out.mkdir()
    (out / "budget.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    monkeypatch.setattr(runner, "run_budget", lambda *a, **k: pytest.fail("--report-only ran the budget"))
    result = CliRunner().invoke(app, ["bench", "budget", str(suite), "-o", str(out), "--report-only", "-m", "caps",
                                      "--no-plots"])
    assert result.exit_code == 0, result.output
    report = (out / "budget.md").read_text()
    assert "| a | caps | 30.00 | +0.50 | +0.00 | +0.50 | 31.00 |" in report and "| a | x |" not in report
    empty = CliRunner().invoke(app, ["bench", "budget", str(suite), "-o", str(tmp_path / "none"), "--report-only"])
    from capssim.errors import InputError  # the command line prints it as one line (test_error_budget.py)

    assert isinstance(empty.exception, InputError) and "--report-only" in str(empty.exception)
    assert "\n" not in str(empty.exception) and not (tmp_path / "none" / "budget.md").exists()
