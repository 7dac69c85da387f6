"""Dataset generation: byte-identical samples, resume after SIGKILL, leftovers, verify, rendered sources."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from capssim.dataset import load_config
from capssim.dataset.generate import generate_dataset
from capssim.dataset.manifest import DatasetLock
from capssim.dataset.sample import generate_sample
from capssim.dataset.verify import verify_dataset
from capssim.errors import InputError

REPO = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-m", "capssim.cli.__main__"]

def test_generate_in_process_verify_and_regenerate_identically(tmp_path, make_config, records_by_index, tree_bytes):
    cfg = load_config(make_config(tmp_path, samples=6))
    out = tmp_path / "out"
    result = generate_dataset(cfg, out, workers=0)
    assert result.complete and result.generated == 6 and result.already_done == 0
    report = verify_dataset(out)
    assert report.ok and report.checked == 6, report.summary()
    records = records_by_index(out)
    assert sorted(records) == list(range(6))
    rec = records[0]
    assert set(rec["files"]) == {"meta.json", "caps_raw.tiff", "dofp_raw.tiff", "gt.tiff"}
    assert rec["timing"]["total_s"] > 0 and "finished_at" in rec and rec["params"] == cfg.sample_spec(0)["params"]
    meta = json.loads((out / "samples" / "000000" / "meta.json").read_text())
    assert meta["dataset"]["index"] == 0 and meta["seed"] == rec["seed"]
    assert meta["source"]["path"] == rec["params"]["source"]["path"]
    assert "timing" not in meta and "finished_at" not in json.dumps(meta)  # no wall times in meta.json
    # the sizes drawn: source a cropped to 32, source b whole (32)
    assert meta["geometry"]["hr_height"] == 32
    # regenerating any sample elsewhere gives identical bytes
    for index in (0, 3):
        spec = cfg.sample_spec(index)
        again = tmp_path / f"again{index}"
        again.mkdir()
        record = generate_sample(spec, str(again))
        assert record["files"] == records[index]["files"]
        assert tree_bytes(again / spec["name"]) == tree_bytes(out / "samples" / spec["name"])
    # a second run has nothing to do
    result = generate_dataset(cfg, out, workers=0)
    assert result.generated == 0 and result.already_done == 6 and result.complete


def test_verify_reports_corruption_and_missing_samples(tmp_path, make_config):
    cfg = load_config(make_config(tmp_path, samples=5))
    out = tmp_path / "out"
    generate_dataset(cfg, out, workers=0)
    assert verify_dataset(out).ok
    samples = out / "samples"
    # flip one byte in a TIFF, delete a file, swap meta.json between samples
    raw = bytearray((samples / "000001" / "caps_raw.tiff").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (samples / "000001" / "caps_raw.tiff").write_bytes(bytes(raw))
    (samples / "000002" / "gt.tiff").unlink()
    shutil.copy(samples / "000004" / "meta.json", samples / "000003" / "meta.json")
    (samples / "000000" / "recon").mkdir()
    (samples / "000000" / "recon" / "x.json").write_text("{}")  # results written later are not corruption
    report = verify_dataset(out)
    assert not report.ok
    assert set(report.corrupt) == {1, 2, 3}, report.summary()
    assert "sha256" in report.corrupt[1][0] and "missing" in report.corrupt[2][0]
    assert report.extra_files == {0: ["recon/x.json"]}
    text = report.summary()
    assert "CORRUPT sample 1" in text and text.endswith("FAILED")
    # the CLI exits 1 and prints the same
    proc = subprocess.run([*CLI, "dataset", "--verify", str(out)], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert proc.returncode == 1 and "CORRUPT sample 2" in proc.stdout
    # a dataset with a sample lost from the manifest is incomplete
    lines = (out / "manifest.jsonl").read_bytes().splitlines(keepends=True)
    (out / "manifest.jsonl").write_bytes(b"".join(lines[1:]))
    first = json.loads(lines[0])["index"]
    report = verify_dataset(out)
    assert first in report.missing and report.leftovers
    with pytest.raises(InputError, match="dataset.json"):
        verify_dataset(tmp_path / "gt")


def test_resume_removes_leftovers_and_redoes_unfinished(tmp_path, make_config, records_by_index, tree_bytes):
    cfg = load_config(make_config(tmp_path, samples=6))
    ref = tmp_path / "ref"
    generate_dataset(cfg, ref, workers=0)
    out = tmp_path / "out"
    generate_dataset(cfg, out, workers=0)
    # simulate a killed run: samples 4, 5 unrecorded (one folder complete but unlisted, one temp folder),
    # a torn manifest line, an orphaned .old folder, and sample 2's folder lost
    lines = (out / "manifest.jsonl").read_bytes().splitlines(keepends=True)
    keep = [ln for ln in lines if json.loads(ln)["index"] < 4]
    (out / "manifest.jsonl").write_bytes(b"".join(keep) + b'{"index": 5, "name": "0000')
    shutil.rmtree(out / "samples" / "000005")
    (out / "samples" / ".000005.tmp-dead").mkdir()
    (out / "samples" / ".000005.tmp-dead" / "caps_raw.tiff").write_bytes(b"half")
    (out / "samples" / ".000001.old-123").mkdir()
    shutil.rmtree(out / "samples" / "000002")
    (out / "samples" / "000004" / "gt.tiff").write_bytes(b"garbage")  # unlisted: must be redone
    result = generate_dataset(cfg, out, workers=0)
    assert result.complete and result.generated == 3 and result.already_done == 3
    assert sorted(result.removed) == [".000001.old-123", ".000005.tmp-dead", "000004"]
    assert tree_bytes(out / "samples") == tree_bytes(ref / "samples")
    assert verify_dataset(out).ok
    text = (out / "manifest.jsonl").read_bytes()
    assert text.endswith(b"\n") and b'"name": "0000' not in text
    assert sorted(records_by_index(out)) == list(range(6))


def test_extend_refuse_other_config_and_lock(tmp_path, make_config, tree_bytes):
    path = make_config(tmp_path, samples=3)
    out = tmp_path / "out"
    generate_dataset(load_config(path), out, workers=0)
    before = tree_bytes(out / "samples")
    path.write_text(path.read_text().replace("samples: 3", "samples: 5"))
    result = generate_dataset(load_config(path), out, workers=0)
    assert result.already_done == 3 and result.generated == 2
    after = tree_bytes(out / "samples")
    assert all(after[k] == v for k, v in before.items())
    assert json.loads((out / "dataset.json").read_text())["samples"] == 5
    path.write_text(path.read_text().replace("seed: 11", "seed: 12"))
    with pytest.raises(InputError, match="different config"):
        generate_dataset(load_config(path), out, workers=0)
    path.write_text(path.read_text().replace("seed: 12", "seed: 11"))
    with DatasetLock(out):
        with pytest.raises(InputError, match="another capssim run"):
            generate_dataset(load_config(path), out, workers=0)


def test_failing_sample_is_recorded_and_bad_input_stops(tmp_path, make_config):
    cfg = load_config(make_config(tmp_path, samples=4))

    def flaky(spec, samples_dir):
        if spec["index"] == 2:
            raise RuntimeError("boom")
        return generate_sample(spec, samples_dir)

    out = tmp_path / "out"
    result = generate_dataset(cfg, out, workers=0, sample_function=flaky)
    assert not result.complete and list(result.failed) == [2] and "boom" in result.failed[2]
    result = generate_dataset(cfg, out, workers=0)  # a rerun retries it
    assert result.complete and result.generated == 1
    # a crop larger than the GT is a user error: it stops the run with a clear message
    bad = make_config(tmp_path / "bad", samples=2, size=32, gt_size=40)
    bad.write_text(bad.read_text().replace("size: 32", "size: 48", 1))
    with pytest.raises(InputError, match="at most the ground-truth size 40x40"):
        generate_dataset(load_config(bad), tmp_path / "bad" / "out", workers=0)


def test_rendered_sources_go_through_render_capture(tmp_path, monkeypatch, records_by_index, smooth_random_scene):
    """With a stand-in render_capture (simulate underneath), scene samples get the drawn
    parameters, record_timing=False, and byte-identical regeneration."""
    import capssim.dataset.sample as sample_module
    from capssim.camera.psf import DEFAULT_PSF, PSF
    from capssim.simulate import simulate_capture

    calls = []

    def render_capture(scene, *, size=256, spp=None, seed=0, setup=None, variant="auto", scene_params=None,
                       geometry_params=None, target_noise=None, record_timing=True, progress=None):
        calls.append(dict(scene=scene, size=size, spp=spp, seed=seed, variant=variant, scene_params=scene_params,
                          geometry_params=geometry_params, record_timing=record_timing, psf=setup.psf,
                          extinction_ratio=setup.extinction_ratio))
        gt = smooth_random_scene(size, seed=seed % 1000)
        return simulate_capture(gt, setup.replace(psf=PSF.none()), seed=seed, kind="rendered",
                                source={"scene": scene})

    monkeypatch.setattr(sample_module, "render_capture", render_capture)
    path = tmp_path / "config.yaml"
    path.write_text(textwrap.dedent("""
        seed: 4
        samples: 4
        sources:
          - scene: materials
            size: {choice: [16, 32]}
            spp: 8
            scene_params: {light: {choice: [8.0, 9.5]}, scale: {uniform: [2, 4]}}
            geometry_params: {depth_m: {uniform: [2, 10]}}
            sensor: {noise: gaussian, sigma: 0.01}
            extinction_ratio: 50
            psf_sigma_hr_px: 0.7
          - scene: siemens-star
            size: 16
    """))
    cfg = load_config(path)
    out = tmp_path / "out"
    result = generate_dataset(cfg, out, workers=0)
    assert result.complete
    assert all(c["record_timing"] is False for c in calls)
    first = calls[0]
    assert first["scene"] == "materials" and first["spp"] == 8 and first["scene_params"]["light"] in (8.0, 9.5)
    assert 2 <= first["geometry_params"]["depth_m"] < 10 and 2 <= first["scene_params"]["scale"] < 4
    assert first["extinction_ratio"] == 50 and first["psf"] == PSF.gaussian(0.7)
    assert calls[1]["scene_params"] is None and calls[1]["spp"] is None
    assert calls[1]["psf"] == DEFAULT_PSF and calls[1]["extinction_ratio"] is None  # the set-up's defaults
    records = records_by_index(out)
    assert "render_s" in records[0]["timing"]
    meta = json.loads((out / "samples" / "000000" / "meta.json").read_text())
    assert meta["kind"] == "rendered" and meta["dataset"]["params"]["source"]["scene_params"] == first["scene_params"]
    again = tmp_path / "again"
    again.mkdir()
    assert generate_sample(cfg.sample_spec(2), str(again))["files"] == records[2]["files"]
    # scene parameters are checked against the scene's own
    path.write_text(path.read_text().replace("scale:", "scal:"))
    with pytest.raises(InputError, match=r"sources\[0\]\.scene_params\.scal.*light, scale, sky"):
        load_config(path)


def _wait_for_lines(manifest: Path, n: int, proc: subprocess.Popen, timeout: float) -> int:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if manifest.is_file():
            count = manifest.read_bytes().count(b"\n")
            if count >= n:
                return count
        if proc.poll() is not None:
            raise AssertionError(f"the run ended before being killed: {proc.communicate()}")
        time.sleep(0.01)
    raise AssertionError("timed out waiting for samples")


@pytest.mark.processes
def test_sigkill_mid_run_then_rerun_is_complete_and_byte_identical(tmp_path, make_config, records_by_index, tree_bytes):
    """Done-when (a): SIGKILL the CLI mid-run, rerun it, and get the uninterrupted dataset."""
    total = 9  # enough that the kill (after 3 samples) lands mid-run; each sample costs the test three times
    path = make_config(tmp_path, samples=total, size=64, gt_size=72)
    ref = tmp_path / "ref"
    generate_dataset(load_config(path), ref, workers=0)  # uninterrupted, in-process
    out = tmp_path / "out"
    cmd = [*CLI, "dataset", str(path), "-o", str(out), "--workers", "1"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        done_at_kill = _wait_for_lines(out / "manifest.jsonl", 3, proc, timeout=240)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert done_at_kill < total, "the run finished before the kill; make the samples slower"
    # the worker processes die with their parent: nothing changes in the folder afterwards
    time.sleep(1.5)
    snapshot = sorted(p.name for p in (out / "samples").iterdir())
    lines = (out / "manifest.jsonl").read_bytes()
    time.sleep(1.0)
    assert sorted(p.name for p in (out / "samples").iterdir()) == snapshot
    assert (out / "manifest.jsonl").read_bytes() == lines
    # make the kill's damage certain: a torn manifest line and a temporary folder
    with open(out / "manifest.jsonl", "ab") as fh:
        fh.write(f'{{"index": {total - 1}, "name": "{total - 1:06d}", "fil'.encode())
    (out / "samples" / f".{total - 1:06d}.tmp-killed").mkdir(exist_ok=True)
    report = verify_dataset(out)
    assert report.missing and not report.corrupt
    # rerun: finishes, removes the leftovers, redoes only the unfinished samples
    proc = subprocess.run(cmd + ["--verify"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    finished_before = len([ln for ln in lines.splitlines() if ln.strip()])
    assert f"{finished_before} from earlier runs" in proc.stdout, proc.stdout
    assert "OK" in proc.stdout
    assert not [p for p in (out / "samples").iterdir() if p.name.startswith(".")]
    records = records_by_index(out)
    assert sorted(records) == list(range(total))
    assert len((out / "manifest.jsonl").read_bytes().splitlines()) == total  # each sample once
    ref_records = records_by_index(ref)
    assert all(records[i]["files"] == ref_records[i]["files"] for i in range(total))
    assert tree_bytes(out / "samples") == tree_bytes(ref / "samples")
    proc = subprocess.run([*CLI, "dataset", "--verify", str(out)], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("OK")
