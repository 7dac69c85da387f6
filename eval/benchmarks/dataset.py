"""Throughput benchmark of dataset generation: samples/hour for 1, 2, ... local workers.

    capssim bench dataset examples/dataset-bench-gt.yaml -w 1 -w 2

For each worker count it generates the config's dataset into a fresh temporary folder (on a
local Dask cluster, or in this process for 0) and prints one row: the steady rate (samples
finished per hour after the first one, so cluster start-up and first-use imports/JIT are
left out), the overall rate (wall time of the whole command, start-up included), the mean time
per sample of each stage from the manifest (load, simulate or render, write, checksum), and
the load average before the run (other processes on the machine skew the numbers).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from datetime import datetime
from pathlib import Path

from capssim.dataset.config import load_config
from capssim.dataset.generate import generate_dataset
from capssim.dataset.manifest import MANIFEST, read_manifest


def _steady_rate(records: list[dict]) -> float | None:
    """Samples per hour between the first and the last finished sample."""
    times = sorted(datetime.fromisoformat(r["finished_at"]).timestamp() for r in records)
    if len(times) < 2 or times[-1] <= times[0]:
        return None
    return 3600.0 * (len(times) - 1) / (times[-1] - times[0])


def run_dataset_benchmark(config_path: str | Path, worker_counts: list[int], *,
                          keep: str | Path | None = None) -> list[dict]:
    """One row per worker count (0: in this process); ``keep``: move each generated dataset into this folder."""
    cfg = load_config(config_path)
    rows = []
    for workers in worker_counts:
        load_before = os.getloadavg()[0]
        out = Path(tempfile.mkdtemp(prefix=f"capssim-bench-{workers}w-"))
        t0 = time.perf_counter()
        result = generate_dataset(cfg, out / "ds", workers=workers)
        wall = time.perf_counter() - t0
        records = list(read_manifest(out / "ds" / MANIFEST).records.values())
        stages: dict[str, float] = {}
        for r in records:
            for k, v in r["timing"].items():
                stages[k] = stages.get(k, 0.0) + v / len(records)
        size = sum(f["bytes"] for r in records for f in r["files"].values())
        rows.append({"workers": workers, "samples": len(records), "failed": len(result.failed),
                     "steady_per_hour": _steady_rate(records), "overall_per_hour": 3600.0 * len(records) / wall,
                     "wall_s": wall, "stages_mean_s": stages, "mb_per_sample": size / len(records) / 1e6,
                     "load_before": load_before, "load_after": os.getloadavg()[0]})
        if keep:
            shutil.move(str(out / "ds"), str(Path(keep) / f"workers-{workers}"))
        shutil.rmtree(out, ignore_errors=True)
    return rows


def format_table(rows: list[dict]) -> str:
    """Markdown table of :func:`run_dataset_benchmark`'s rows."""
    stage_keys = sorted({k for r in rows for k in r["stages_mean_s"] if k != "total_s"})
    head = ["workers", "samples", "steady/h", "overall/h", "wall s", *[k.removesuffix("_s") + " s" for k in stage_keys],
            "total s", "MB/sample", "load before/after"]
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    for r in rows:
        steady = f"{r['steady_per_hour']:.0f}" if r["steady_per_hour"] else "-"
        cells = [str(r["workers"]), str(r["samples"]), steady, f"{r['overall_per_hour']:.0f}", f"{r['wall_s']:.1f}",
                 *[f"{r['stages_mean_s'].get(k, 0.0):.3f}" for k in stage_keys],
                 f"{r['stages_mean_s'].get('total_s', 0.0):.3f}", f"{r['mb_per_sample']:.2f}",
                 f"{r['load_before']:.1f}/{r['load_after']:.1f}"]
        lines.append(" | ".join(cells))
    return "\n".join("| " + line + " |" for line in lines)
