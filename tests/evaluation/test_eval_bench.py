"""The suite runner through ``capssim bench suite``: a tiny suite with test-only methods, resume, baselines, skips, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from capssim.cli import app
from capssim.errors import InputError, UnknownNameError
from capssim.eval.benchmarks.baseline import DEFAULT_TOLERANCES, check_against_baseline, tolerance_for
from capssim.eval.benchmarks.suite import BenchRun, load_suite
from capssim.eval.plots import pareto_front
from capssim.reconstruct.registry import MethodOutput, available_methods, register_method

CALLS = {"test-upsample": 0}


def _upsample(capture, context, interpolation):
    import cv2

    lr, _ = capture.lr_images()
    with context.timer.stage("upsample"):
        chans = []
        for n in range(4):
            for qs in ([0], [1, 2], [3]):
                sub = np.mean([lr[4 * n + q] for q in qs], axis=0)
                chans.append(cv2.resize(sub, None, fx=4, fy=4, interpolation=interpolation))
    return MethodOutput(np.stack(chans).astype(np.float32), params={"interpolation": int(interpolation)})


if "test-upsample" not in available_methods():
    @register_method("test-upsample", input_kind="caps", description="test only: bicubic x4 of each sub-image",
                     reference="tests/test_eval_bench.py")
    def _test_upsample(capture, *, context):
        import cv2

        CALLS["test-upsample"] += 1
        return _upsample(capture, context, cv2.INTER_CUBIC)

    @register_method("test-nearest-dofp", input_kind="dofp", description="test only: nearest x4 (needs DoFP)",
                     reference="tests/test_eval_bench.py")
    def _test_nearest(capture, *, context):
        import cv2

        return _upsample(capture, context, cv2.INTER_NEAREST)

    @register_method("test-broken", input_kind="caps", description="test only: always fails",
                     reference="tests/test_eval_bench.py")
    def _test_broken(capture, *, context):
        raise RuntimeError("this method is broken on purpose")


@pytest.fixture
def texture_gt_folder(write_png_gt):
    """Factory: ``(path, size=48) -> path`` of a texture scene as PNGs."""

    def _write_gt_folder(path: Path, size: int = 48) -> Path:
        from capssim.eval.synthetic import texture_scene

        return write_png_gt(path, texture_scene(size, seed=5)[0])

    return _write_gt_folder


SUITE = """
name: tiny
seeds: [0]
noise:
  - {name: gauss-0.01, model: gaussian, sigma: 0.01}
methods: [test-upsample, test-nearest-dofp]
scenes:
  - {name: rendered-star, source: render, scene: no-such-scene-anywhere, size: 64, fallback: star}
  - {name: star, source: synthetic, generator: star, size: 96, cycles: 24}
  - {name: texture, source: synthetic, generator: texture, size: 48}
  - {name: real, source: shared-gt, path: gt/fake-scene}
"""


@pytest.fixture
def tiny(tmp_path, monkeypatch, texture_gt_folder):
    """The tiny suite, with the shared data of ``real`` and without a renderer (``rendered-star`` falls back)."""
    from capssim.eval.benchmarks import captures

    def no_renderer():
        raise captures.Unavailable("rendering unavailable (test)")

    monkeypatch.setattr(captures, "rendered_scene_names", no_renderer)
    shared = tmp_path / "shared"
    texture_gt_folder(shared / "gt" / "fake-scene")
    monkeypatch.setenv("CAPSSIM_SHARED_DATA", str(shared))
    suite = tmp_path / "tiny.yaml"
    suite.write_text(SUITE)
    return suite, tmp_path


def _bench(suite, *args):
    return CliRunner().invoke(app, ["bench", "suite", str(suite), *map(str, args)])


def _records(out: Path) -> dict[str, dict]:
    return {r["key"]: r for r in map(json.loads, (out / "results.jsonl").read_text().splitlines())}


def test_bench_runs_resumes_and_checks(tiny, monkeypatch):
    suite, tmp = tiny
    out, baseline = tmp / "out", tmp / "baseline.json"
    r = _bench(suite, "-o", out, "--update-baseline", baseline)
    assert r.exit_code == 0, r.output
    recs = _records(out)
    ok = {k for k, v in recs.items() if v["status"] == "ok"}
    assert ok == {f"{s}/gauss-0.01/seed0/{m}" for s in ("star", "texture", "real")
                  for m in ("test-upsample", "test-nearest-dofp")}
    star = recs["star/gauss-0.01/seed0/test-upsample"]
    assert star["requested_scene"] == "rendered-star"  # the fallback was used and recorded
    for key in ("psnr_mean", "ssim_mean", "s0_psnr", "dolp_psnr", "aop_rmse_deg", "mtf_magnification_hv"):
        assert star["metrics"][key] is not None, key
    assert 0.3 < star["metrics"]["mtf_magnification_hv"] < 1.05  # bicubic: no super-resolution credited
    assert star["wall_time_s"] >= 0 and "upsample" in star["stages_s"] and star["peak_rss_mb"] > 0
    env = star["environment"]
    assert {"versions", "git", "cpu", "gpu", "device"} <= set(env)
    report = (out / "report.md").read_text()
    assert "## Notes" in report
    for name in ("speed_vs_psnr.png", "crops_star_gauss-0.01.png", "mtf_star_gauss-0.01.png"):
        assert (out / "plots" / name).is_file(), name
    base = json.loads(baseline.read_text())
    assert len(base["cases"]) == 6 and base["tolerances"] == DEFAULT_TOLERANCES

    # resume: nothing is redone; after losing the last line only that case is redone
    calls = CALLS["test-upsample"]
    assert _bench(suite, "-o", out, "--no-plots").exit_code == 0
    assert CALLS["test-upsample"] == calls
    lines = (out / "results.jsonl").read_text().splitlines()
    dropped = next(i for i, line in enumerate(lines) if '"test-upsample"' in line and '"status": "ok"' in line)
    (out / "results.jsonl").write_text("\n".join(lines[:dropped] + lines[dropped + 1:]) + "\n{corrupt")
    assert _bench(suite, "-o", out, "--no-plots").exit_code == 0
    assert CALLS["test-upsample"] == calls + 1

    # the check passes against its own baseline
    r = _bench(suite, "-o", out, "--no-plots", "--check", baseline)
    assert r.exit_code == 0, r.output
    assert "PASSED (6 case(s) compared" in r.output

    # a degraded higher-is-better and lower-is-better metric fail, saying which and by how much
    worse = json.loads(baseline.read_text())
    case = worse["cases"]["texture/gauss-0.01/seed0/test-upsample"]["metrics"]
    case["psnr_mean"] += 0.5
    case["aop_rmse_deg"] -= 1.0
    case["mtf_magnification_hv"] = 9.0  # not measured on this scene: ignored, never a false alarm
    worse_path = tmp / "worse.json"
    worse_path.write_text(json.dumps(worse))
    r = _bench(suite, "-o", out, "--no-plots", "--check", worse_path)
    assert r.exit_code == 1
    assert "texture/gauss-0.01/seed0/test-upsample psnr_mean" in r.output and "fell by 0.5000" in r.output
    assert "aop_rmse_deg" in r.output and "rose by 1.0000" in r.output
    assert "FAILED" in r.output

    # without the shared data its cases are skipped explicitly and not compared; the rest passes
    monkeypatch.setenv("CAPSSIM_SHARED_DATA", str(tmp / "nowhere"))
    r = _bench(suite, "-o", tmp / "out2", "--no-plots", "--check", baseline)
    assert r.exit_code == 0, r.output
    assert "not compared: real/gauss-0.01/seed0/test-upsample (skipped: real: shared data" in r.output
    assert "PASSED (4 case(s) compared" in r.output


def test_a_partial_rerun_reports_the_whole_suite(tiny):
    """``-m METHOD --fresh --results-page``: the page and report.md keep the suite's other method (their latest
    results in the folder, noted as from an earlier run); the summary shows only this run's cases."""
    suite, tmp = tiny
    out, page = tmp / "out", tmp / "page.md"
    assert _bench(suite, "-o", out, "--no-plots").exit_code == 0
    r = _bench(suite, "-o", out, "--no-plots", "-m", "test-upsample", "--fresh", "--results-page", page)
    assert r.exit_code == 0, r.output
    text = page.read_text()
    assert "| test-nearest-dofp |" in text and "| test-upsample |" in text
    assert "3 of the 6 cases on this page are the latest results of earlier runs" in text
    assert "| test-nearest-dofp |" in (out / "report.md").read_text()
    assert "test-nearest-dofp" not in r.output.split("results:")[0]  # the summary: this run's cases
    # a whole run's page has no such note
    assert _bench(suite, "-o", out, "--no-plots", "--results-page", page).exit_code == 0
    assert "earlier runs" not in page.read_text()


def test_check_fails_on_errors_missing_methods_and_empty_runs(tiny):
    suite, tmp = tiny
    text = suite.read_text().replace("[test-upsample, test-nearest-dofp]", "[test-upsample]")
    text = text.replace("  - {name: star, source: synthetic, generator: star, size: 96, cycles: 24}\n", "")
    text = text.replace("  - {name: rendered-star, source: render, scene: no-such-scene-anywhere, size: 64, "
                        "fallback: star}\n", "")
    suite.write_text(text.replace("  - {name: real, source: shared-gt, path: gt/fake-scene}\n", ""))
    out, baseline = tmp / "out", tmp / "b.json"
    assert _bench(suite, "-o", out, "--no-plots", "--update-baseline", baseline).exit_code == 0
    # the method breaks: the case errors, the run and the check fail
    broken = suite.read_text().replace("methods: [test-upsample]", "methods: [{name: test-broken, label: test-upsample}]")
    suite.write_text(broken)
    r = _bench(suite, "-o", tmp / "out3", "--no-plots", "--check", baseline)
    assert r.exit_code == 1
    assert "error (RuntimeError: this method is broken on purpose)" in r.output
    report = (tmp / "out3" / "report.md").read_text()
    assert "## Failed cases" in report and "broken on purpose" in report


def test_suites_and_helpers():
    for name in ("quick", "paper", "full", "ablation"):
        spec = load_suite(name)
        assert spec["methods"] and spec["scenes"]
    ablation = load_suite("ablation")
    assert {m["name"] for m in ablation["methods"]} == {"caps", "caps-iccp", "caps-no-cagf", "caps-no-nlstr", "caps-naive",
                                                        "caps-plus", "caps-plus-cv"}
    assert not any(m.get("true_warps") for m in ablation["methods"])  # estimated warps, as the paper's study
    quick = load_suite("quick")
    assert {m["name"] for m in quick["methods"]} >= {"caps", "caps-naive", "dofp-bilinear", "dofp-eari"}
    assert any(s["source"] == "synthetic" and not s.get("fallback") for s in quick["scenes"])
    assert any(s["source"] == "render" and s.get("scene") == "siemens-star" for s in quick["scenes"])
    assert tolerance_for("psnr.0-R", DEFAULT_TOLERANCES) == DEFAULT_TOLERANCES["psnr_db"]
    assert tolerance_for("aop_mae_deg", DEFAULT_TOLERANCES) == DEFAULT_TOLERANCES["aop_deg"]
    assert tolerance_for("aop_fraction", DEFAULT_TOLERANCES) is None
    assert tolerance_for("wall_time_s", DEFAULT_TOLERANCES) is None
    front = pareto_front(np.array([1.0, 2.0, 3.0, 0.5]), np.array([30.0, 29.0, 35.0, 20.0]))
    assert front.tolist() == [3, 0, 2]
    front = pareto_front(np.array([1.0, 2.0]), np.array([5.0, 3.0]), higher_is_better=False)
    assert front.tolist() == [0, 1]


def test_bad_suite_and_baseline(tmp_path):
    with pytest.raises(UnknownNameError, match="quick"):
        load_suite("no-such-suite")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nscenes: [{name: a, source: nowhere}]\nmethods: [caps]\n")
    with pytest.raises(InputError, match="source"):
        load_suite(bad)
    r = CliRunner().invoke(app, ["bench", "suite", str(bad), "-o", str(tmp_path / "o")])
    assert r.exit_code != 0
    run = BenchRun(spec={"name": "x"}, output=tmp_path, results_path=tmp_path / "r", records=[], environment={})
    with pytest.raises(InputError, match="update-baseline"):
        check_against_baseline(run, tmp_path / "missing.json")


def test_a_suite_times_reused_registration_as_if_computed():
    from capssim.eval.benchmarks.cases import reused_registration_s

    assert reused_registration_s({"registration": {"store": "reused", "time_s": 2.5}}) == 2.5
    assert reused_registration_s({"registration": {"store": "computed", "time_s": 2.5}}) == 0.0
    assert reused_registration_s({"registration": {"source": "true"}}) == 0.0
    assert reused_registration_s({}) == 0.0


def test_code_fingerprint_follows_the_shipped_weights(tmp_path, monkeypatch):
    """New weights rerun the cases they score: a changed ``.pt`` or ``.npz`` under a part changes its key; other
    files (notes, images) do not."""
    from capssim.eval.benchmarks import provenance

    weights = tmp_path / "reconstruct" / "weights"
    weights.mkdir(parents=True)
    (tmp_path / "reconstruct" / "method.py").write_text("X = 1\n")
    (weights / "net.pt").write_bytes(b"first")
    monkeypatch.setattr(provenance, "REPO_ROOT", tmp_path)
    first = provenance.code_fingerprint("reconstruct")
    (weights / "README.txt").write_text("notes")
    assert provenance.code_fingerprint("reconstruct") == first
    (weights / "net.pt").write_bytes(b"second")
    second = provenance.code_fingerprint("reconstruct")
    (weights / "dictionary.npz").write_bytes(b"atoms")
    assert len({first, second, provenance.code_fingerprint("reconstruct")}) == 3


def test_a_weights_file_retrained_in_place_changes_the_case_hash(tmp_path):
    """``-p weights=PATH``: the case hash holds the file's bytes, so a file trained again at the same path reruns
    the cases that read it; options that name no file add nothing."""
    import os

    from capssim.eval.benchmarks.provenance import option_file_hashes

    weights = tmp_path / "model.pt"
    weights.write_bytes(b"first weights")
    first = option_file_hashes({"weights": str(weights), "iterations": 5, "init": "fusion"})
    assert set(first) == {"weights"}
    assert option_file_hashes({"weights": str(weights)}) == first  # the same bytes: the same hash
    weights.write_bytes(b"other weights")
    os.utime(weights, ns=(1, 1))
    assert option_file_hashes({"weights": str(weights)}) != first
    assert option_file_hashes({"weights": str(tmp_path / "missing.pt"), "name": ""}) == {}
    assert option_file_hashes(None) == {}
