"""The development/test protocol: paired comparisons (``capssim bench compare``), suite roles, ``paired:`` and the
mark of scores on a suite a method was tuned on."""

from __future__ import annotations

import json
import math

import pytest
from support.fuzz import one_error_line, run_cli
from typer.testing import CliRunner

from capssim.cli import app
from capssim.errors import InputError
from capssim.eval.benchmarks.compare import load_run_records, paired_rows, summarize
from capssim.eval.benchmarks.suite_schema import check_suite, load_suite
from capssim.eval.suite_report import TUNED_MARK, paired_section, results_table, tuned_labels
from capssim.files.schema import ConfigError


def _record(scene, noise, method, psnr, dolp=None, seed=0):
    return {"case_id": f"{scene}/{noise}/{seed}/{method}", "key": f"{scene}/{noise}/{seed}/{method}", "scene": scene,
            "noise": noise, "seed": seed, "method": method, "status": "ok",
            "metrics": {"psnr_mean": psnr, "dolp_psnr": dolp}}


A = [30.0, 31.0, 29.5, 33.0]
B = [29.0, 30.8, 29.9, 32.0]
RECORDS = ([_record(f"s{i}", "g", "a", a, dolp=20.0 + i) for i, a in enumerate(A)]
           + [_record(f"s{i}", "g", "b", b, dolp=20.0 + i) for i, b in enumerate(B)]
           + [_record("only-a", "g", "a", 50.0)])


def test_the_paired_statistics_are_those_of_the_differences():
    rows = paired_rows(RECORDS, RECORDS, "a", "b", "psnr_mean")
    assert [c for c, _, _ in rows] == ["s0 / g / 0", "s1 / g / 0", "s2 / g / 0", "s3 / g / 0"]  # only-a unpaired
    s = summarize(rows, "psnr_mean")
    d = [a - b for a, b in zip(A, B)]
    mean = sum(d) / 4
    se = math.sqrt(sum((x - mean) ** 2 for x in d) / 3 / 4)
    assert s.n == 4 and s.mean == pytest.approx(mean) and s.se == pytest.approx(se)
    assert (s.wins, s.losses, s.ties) == (3, 1, 0)
    assert s.worst == pytest.approx(-0.4) and s.worst_case == "s2 / g / 0"
    assert s.beats == (mean - se > 0)
    same = summarize(paired_rows(RECORDS, RECORDS, "a", "b", "dolp_psnr"), "dolp_psnr")
    assert same.ties == 4 and same.mean == 0 and not same.beats


def test_lower_is_better_metrics_flip_the_sign_of_a_win():
    recs = [_record("x", "g", "a", 1.0), _record("x", "g", "b", 1.0)]
    recs[0]["metrics"]["aop_mae_deg"], recs[1]["metrics"]["aop_mae_deg"] = 2.0, 5.0
    recs += [_record("y", "g", "a", 1.0), _record("y", "g", "b", 1.0)]
    recs[2]["metrics"]["aop_mae_deg"], recs[3]["metrics"]["aop_mae_deg"] = 3.0, 7.0
    s = summarize(paired_rows(recs, recs, "a", "b", "aop_mae_deg"), "aop_mae_deg")
    assert s.wins == 2 and s.mean == pytest.approx(-3.5) and s.beats


def test_the_command_compares_two_methods_of_one_run_and_two_runs(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in RECORDS))
    runner = CliRunner()
    result = runner.invoke(app, ["bench", "compare", str(run), "-m", "a", "--against", "b", "--json"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.output)["comparisons"]
    assert out[0]["metric"] == "psnr_mean" and out[0]["n"] == 4 and len(out[0]["cases"]) == 4
    assert out[0]["mean"] == pytest.approx(sum(a - b for a, b in zip(A, B)) / 4)
    other = tmp_path / "other"
    other.mkdir()
    shifted = [{**r, "metrics": {**r["metrics"], "psnr_mean": r["metrics"]["psnr_mean"] - 1.0}} for r in RECORDS]
    (other / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in shifted))
    result = runner.invoke(app, ["bench", "compare", str(run), str(other), "--metric", "psnr_mean"])
    assert result.exit_code == 0, result.output
    assert "| a | a | psnr_mean | 5 | +1.000 | 0.000 | 5 / 0 / 0" in result.output


@pytest.mark.parametrize("args, argument", [
    (["-m", "zz", "--against", "b"], "--method"),
    (["-m", "a", "--against", "zz"], "--against"),
    (["-m", "a", "--against", "b", "--metric", "psnr_men"], "--metric"),  # a typo: not an empty table
    ([], "--method"),  # one run and nothing to compare it with
])
def test_bad_labels_are_refused_in_one_line(tmp_path, args, argument, capsys, monkeypatch):
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in RECORDS))
    status, text = run_cli(["bench", "compare", str(run), *args], capsys, monkeypatch)
    one_error_line(status, text, argument)


def test_scene_patterns_keep_and_leave_out_cases(tmp_path, capsys, monkeypatch):
    """``--scene`` / ``--exclude-scene``: shell patterns on the scene name, e.g. to leave out a network's training
    scenes; a selection that keeps no scene is refused in one line naming the scenes there are."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in RECORDS))
    result = CliRunner().invoke(app, ["bench", "compare", str(run), "-m", "a", "--against", "b", "--json",
                                      "--exclude-scene", "s[01]", "--metric", "psnr_mean"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.output)
    assert [c["case"] for c in out["comparisons"][0]["cases"]] == ["s2 / g / 0", "s3 / g / 0"]
    assert out["exclude_scenes"] == ["s[01]"]
    assert out["comparisons"][0]["mean"] == pytest.approx(((29.5 - 29.9) + (33.0 - 32.0)) / 2)
    kept = CliRunner().invoke(app, ["bench", "compare", str(run), "-m", "a", "--against", "b", "--json",
                                    "--scene", "s*", "--exclude-scene", "s3", "--metric", "psnr_mean"])
    assert json.loads(kept.output)["comparisons"][0]["n"] == 3
    status, text = run_cli(["bench", "compare", str(run), "-m", "a", "--against", "b", "--scene", "qiu-*"],
                           capsys, monkeypatch)
    one_error_line(status, text, "--scene")
    assert "only-a, s0, s1, s2, s3" in text


def test_a_folder_without_results_is_refused(tmp_path):
    with pytest.raises(InputError, match="RUN_A"):
        load_run_records(tmp_path, argument="RUN_A")


def _suite(**extra):
    return {"name": "dev", "methods": ["caps", "caps-plus"],
            "scenes": [{"name": "t", "source": "synthetic", "generator": "texture", "size": 32}], **extra}


def test_a_suite_declares_its_role_and_paired_method():
    assert check_suite(_suite())["role"] == "development"
    assert check_suite(_suite(role="test", paired="caps-plus"))["paired"] == "caps-plus"
    with pytest.raises(ConfigError, match="role"):
        check_suite(_suite(role="final"))
    with pytest.raises(ConfigError, match="paired.*Did you mean 'caps-plus'"):
        check_suite(_suite(paired="caps-pls"))
    assert load_suite("test")["role"] == "test"
    for name in ("quick", "ablation", "baselines", "paper", "dev"):
        assert load_suite(name)["role"] == "development"


def test_a_suites_method_options_are_checked_when_it_loads():
    suite = _suite(methods=[{"name": "caps-plus", "options": {"stoping": "noise"}}])
    with pytest.raises(ConfigError, match=r"methods\[0\]\.options.*holdout_fraction"):
        check_suite(suite)
    with pytest.raises(ConfigError, match=r"methods\[0\]\.options.*init"):
        check_suite(_suite(methods=[{"name": "caps-plus", "options": {"init": "bogus"}}]))
    assert check_suite(_suite(methods=[{"name": "caps-plus", "options": {"init": "fusion"}}]))


def test_scores_on_a_suite_a_method_was_tuned_on_are_marked():
    spec = check_suite(_suite(name="baselines"))
    assert tuned_labels(spec) == {"caps-plus"}  # caps's defaults are the paper's
    assert tuned_labels(check_suite(_suite(name="test"))) == set()
    table = results_table([_record("t", "g", "caps", 30.0), _record("t", "g", "caps-plus", 31.0)],
                          ["caps", "caps-plus"], tuned_labels(spec))
    assert f"| caps-plus {TUNED_MARK} |" in table and f"| caps {TUNED_MARK}" not in table


def test_the_paired_section_compares_the_named_method_with_every_other():
    spec = check_suite(_suite(paired="caps-plus"))
    recs = [_record("t", "g", "caps", 30.0, 20.0), _record("t", "g", "caps-plus", 31.5, 19.0),
            _record("u", "g", "caps", 28.0, 21.0), _record("u", "g", "caps-plus", 28.5, 21.5)]
    text = "\n".join(paired_section(spec, recs))
    assert "| caps-plus | caps | psnr_mean | 2 | +1.000 | 0.500 | 2 / 0 / 0" in text
    assert "| caps-plus | caps | dolp_psnr | 2 | -0.250 | 0.750 | 1 / 1 / 0" in text
    assert paired_section(check_suite(_suite()), recs) == []
