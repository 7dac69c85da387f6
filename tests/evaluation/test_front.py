"""The front in words: per time budget, the best camera-array and DoFP methods (issue 58)."""

from __future__ import annotations

from capssim.eval.front import front_rows, front_table


def _record(method, scene, time_s, psnr, dolp, *, true_warps=False):
    return {"status": "ok", "method": method, "method_name": method.removesuffix("-true-warps"), "scene": scene,
            "noise": "g", "seed": 0, "wall_time_s": time_s, "metrics": {"psnr_mean": psnr, "dolp_psnr": dolp},
            "registration": {"source": "true (meta.json)" if true_warps else "estimated"}}


def test_each_budget_names_the_best_method_of_each_kind_and_the_margin():
    records = []
    for scene, shift in (("a", 0.0), ("b", 1.0)):
        records += [_record("dofp-bilinear", scene, 0.1, 30 + shift, 20 + shift),
                    _record("dofp-igri2", scene, 1.0, 33 + shift, 24 + shift),
                    _record("caps-naive", scene, 2.0, 32 + shift, 22 + shift),
                    _record("caps", scene, 20.0, 34 + shift, 27 + shift),
                    _record("caps-true-warps", scene, 19.0, 40, 40, true_warps=True)]  # an oracle: left out
    rows = front_rows(records)
    assert [(r["budget_s"], r["array"], r["dofp"]) for r in rows] == [
        (0.1, None, "dofp-bilinear"), (1.0, None, "dofp-igri2"), (2.0, "caps-naive", "dofp-igri2"),
        (20.0, "caps", "dofp-igri2")]
    assert rows[2]["margin"]["psnr_mean"] == -1.0 and rows[3]["margin"]["dolp_psnr"] == 3.0
    table = front_table(records)
    assert "| <= 20.00 s | `caps` (34.50 / 27.50 dB) | `dofp-igri2` (33.50 / 24.50 dB) | +1.00 / +3.00 dB |" in table


def test_no_front_without_both_kinds():
    records = [_record("dofp-igri2", "a", 1.0, 33, 24), _record("dofp-bilinear", "a", 0.1, 30, 20)]
    assert front_table(records) is None
