"""A results page after ``-m``/``--scene`` shows the whole suite: :func:`whole_suite_run`."""

from __future__ import annotations

import json

from capssim.eval.benchmarks.suite import BenchRun
from capssim.eval.benchmarks.whole_suite import whole_suite_run


def _record(method, scene, finished, case_id, *, status="ok", revision="aaaa"):
    return {"case_id": case_id, "key": f"{scene}/n/seed0/{method}", "method": method, "scene": scene,
            "noise": "n", "seed": 0, "status": status, "finished": finished, "metrics": {"psnr_mean": 30.0},
            "environment": {"git": {"revision": revision, "dirty": False}}}


def test_whole_suite_run_adds_the_latest_record_of_every_other_case(tmp_path):
    spec = {"name": "s", "methods": [{"label": "a"}, {"label": "b"}]}
    own = _record("a", "x", "2026-11-29T06:00:00", "a-new", revision="bbbb")
    older = [
        _record("a", "x", "2026-11-28T06:00:00", "a-old"),                    # superseded by this run's record
        _record("b", "x", "2026-11-28T06:00:00", "b-1"),
        _record("b", "x", "2026-11-28T07:00:00", "b-2"),                      # the latest of case b/x
        _record("b", "y", "2026-11-28T06:00:00", "b-y", status="error"),      # not ok: left out
        _record("c", "x", "2026-11-28T06:00:00", "c-x"),                      # a label the suite no longer has
        _record("b", "gone", "2026-11-28T06:00:00", "b-gone"),                # a scene the suite no longer has
    ]
    path = tmp_path / "results.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in [*older, own]))
    run = BenchRun(spec=spec, output=tmp_path, results_path=path, records=[own], environment={}, notes=["sub"])
    page = whole_suite_run(run, scene_names={"x", "y"})
    assert [r["case_id"] for r in page.records] == ["a-new", "b-2"]
    assert page.notes[0] == "sub" and "1 of the 2 cases" in page.notes[1] and "git aaaa" in page.notes[1]
    assert run.records == [own] and run.notes == ["sub"]  # the run itself unchanged


def test_whole_suite_run_of_a_complete_run_is_the_run(tmp_path):
    spec = {"name": "s", "methods": [{"label": "a"}]}
    own = _record("a", "x", "2026-11-29T06:00:00", "a-new")
    path = tmp_path / "results.jsonl"
    path.write_text(json.dumps(own) + "\n")
    run = BenchRun(spec=spec, output=tmp_path, results_path=path, records=[own], environment={})
    assert whole_suite_run(run, scene_names={"x"}) is run
