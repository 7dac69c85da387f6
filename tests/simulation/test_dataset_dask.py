"""Done-when (b): a real Dask LocalCluster with 2 workers, one of which dies mid-sample."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

from capssim.dataset import load_config
from capssim.dataset.generate import generate_dataset
from capssim.dataset.sample import generate_sample
from capssim.dataset.verify import verify_dataset

CRASH_INDEX = 3


def crash_once(spec: dict, samples_dir: str) -> dict:
    """Kill the worker process the first time sample CRASH_INDEX runs, after leaving a
    half-written temporary folder behind (as a real crash would)."""
    marker = Path(samples_dir).parent / f"crashed-{spec['index']}"
    if spec["index"] == CRASH_INDEX and not marker.exists():
        marker.write_text(str(os.getpid()))
        tmp = Path(samples_dir) / f".{spec['name']}.tmp-crash"
        tmp.mkdir()
        (tmp / "caps_raw.tiff").write_bytes(b"partial")
        os._exit(17)
    time.sleep(0.1)
    return generate_sample(spec, samples_dir)


@pytest.mark.processes
def test_local_cluster_two_workers_survives_a_dying_worker(make_config, records_by_index, tree_bytes, tmp_path):
    pytest.importorskip("distributed")
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    total = 8
    cfg = load_config(make_config(tmp_path, samples=total))
    ref = tmp_path / "ref"
    generate_dataset(cfg, ref, workers=0)
    out = tmp_path / "out"
    seen = []
    result = generate_dataset(cfg, out, workers=2, sample_function=crash_once, progress=seen.append)
    assert result.workers == 2 and result.compute_threads == 1
    assert result.complete and result.generated == total, result.failed
    assert (out / "crashed-3").is_file()  # the crash did happen
    crashed_pid = int((out / "crashed-3").read_text())
    records = records_by_index(out)
    assert sorted(records) == list(range(total))
    assert len((out / "manifest.jsonl").read_bytes().splitlines()) == total  # no sample made twice
    assert not records[CRASH_INDEX]["worker"].endswith(f":{crashed_pid}")
    assert all(r["worker"].split(":")[1] != str(os.getpid()) for r in records.values())  # not in this process
    # the half-written folder was swept; the dataset equals the in-process one byte for byte
    assert not [p for p in (out / "samples").iterdir() if p.name.startswith(".")]
    assert tree_bytes(out / "samples") == tree_bytes(ref / "samples")
    assert verify_dataset(out).ok
    # progress was reported with rate and ETA
    assert seen[-1].done == total and seen[-1].rate_per_hour > 0 and seen[-1].eta_s == 0
    assert any(p.eta_s for p in seen if p.done < total)
