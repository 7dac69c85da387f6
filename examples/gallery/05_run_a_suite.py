"""Run a small benchmark suite.

A suite is a YAML file of scenes x noise levels x seeds x methods (the guide
[Benchmarks](../guides/benchmarks.md) has its format; the shipped ones are in ``eval/suites/``).
`capssim.eval.benchmarks.suite.run_suite` makes each capture once, runs every method on it,
scores it, appends one JSON line per case to ``OUTPUT/results.jsonl`` and returns the records;
`capssim.eval.suite_report.write_report` writes the ``report.md`` and plots that
`capssim bench suite` writes. Run again into the same folder, a suite does only the cases that
are missing. This one has two synthetic scenes of 48 and 64 px and three fast methods, on one
thread so that the timings compare.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

from capssim.eval.benchmarks.suite import load_suite, run_suite
from capssim.eval.suite_report import write_report

SUITE = """
name: gallery
description: Two small synthetic scenes, three fast methods.
seeds: [0]
noise:
  - {name: gauss-0.01, noise: gaussian, sigma: 0.01}
methods:
  - caps-naive
  - dofp-bilinear
  - dofp-eari
scenes:
  - {name: texture, source: synthetic, generator: texture, size: 48}
  - {name: star, source: synthetic, generator: star, size: 64, cycles: 16}
"""

with tempfile.TemporaryDirectory() as tmp:
    suite_file = Path(tmp) / "gallery.yaml"
    suite_file.write_text(SUITE)
    spec = load_suite(suite_file)                              # validated: unknown methods or scenes are named
    run = run_suite(spec, Path(tmp) / "out", threads=1)
    print(f"{len(run.records)} cases, {run.n_errors} failed, {run.wall_time_s:.1f} s")
    print(f"{'scene':<8} {'method':<14} {'PSNR (dB)':>9} {'DoLP PSNR':>9} {'time (s)':>8}")
    for rec in run.ok_records():
        m = rec["metrics"]
        print(f"{rec['scene']:<8} {rec['method']:<14} {m['psnr_mean']:9.2f} {m['dolp_psnr']:9.2f} "
              f"{rec['wall_time_s']:8.2f}")
    report = write_report(run, Path(tmp) / "out", plots=False)
    print(f"\nreport.md: {len(report.read_text().splitlines())} lines; results.jsonl: "
          f"{len(run.results_path.read_text().splitlines())} lines")

fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
for ax, scene in zip(axes, ["texture", "star"]):
    recs = [r for r in run.ok_records() if r["scene"] == scene]
    for rec in recs:
        ax.scatter(rec["wall_time_s"], rec["metrics"]["psnr_mean"], s=60, label=rec["method"])
    ax.set_xscale("log")
    ax.set_xlabel("wall time (s, log scale)")
    ax.set_title(f"scene {scene}")
axes[0].set_ylabel("mean PSNR (dB)")
axes[0].legend()
fig.suptitle("Speed against quality, one point per method")
plt.show()
