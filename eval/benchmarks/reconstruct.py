"""Speed benchmark of ``caps`` (or other CAPS methods): wall time and peak memory per stage, per HR size and device.

Run ``capssim bench reconstruct``. For each HR size (``N`` for ``N x N``, or ``W x H``: the prototype's full frame is
2560x2048) a capture is simulated (the paper's protocol, Gaussian noise 0.01) from
``../shared/data/gt/qiu-kettle`` when present, else from a synthetic scene; then ``caps``
(and every other ``methods`` entry, e.g. ``caps-plus``) runs at its defaults in a fresh subprocess per
(size, device, method, repeat), so the peak
memory of one run is not inflated by another. With a ``tile`` the frame is also reconstructed in
tiles (:func:`capssim.reconstruct.tiles.run.reconstruct_tiled`), and untiled only where its memory estimate
(:func:`capssim.reconstruct.tiles.memory.estimate_bytes`) fits the machine's limit. Peak memory is the process RSS (CPU,
sampled every 5 ms and attributed to the stage running) or ``torch.cuda.max_memory_allocated``
(CUDA). The machine's load average is recorded with each run: other processes sharing
the cores make timings noisy, so use ``--repeats`` and read the fastest.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_capture, write_capture
from capssim.files.imageio import centre_crop, read_gt_scene
from capssim.reconstruct.registry import RunContext, StageTimer, get_method, resolve_device
from capssim.reconstruct.tiles.memory import fits, memory_budget
from capssim.reconstruct.tiles.run import reconstruct_tiled
from capssim.runtime.threads import adaptive_decisions, is_adaptive, set_threads
from capssim.simulate import prepare_ground_truth, simulate_capture
from capssim.stokes.polarization import twelve_from_stokes

from .provenance import shared_data_dir
from .reconstruct_report import paired_ratios

#: the worker's module, run in a fresh subprocess per timed run
WORKER_MODULE = "capssim.eval.benchmarks.reconstruct"



def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


class MemoryStageTimer(StageTimer):
    """A :class:`StageTimer` that also records the peak memory seen during each stage."""

    def __init__(self, device: torch.device, *, interval_s: float = 0.005):
        super().__init__(device)
        self.peaks: dict[str, int] = {}
        self.overall_peak = 0
        self._current: str | None = None
        self._stop = threading.Event()
        self._interval = interval_s
        self._thread = None
        if device.type != "cuda":
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()

    def _sample(self) -> None:
        while not self._stop.is_set():
            rss = _rss_bytes()
            self.overall_peak = max(self.overall_peak, rss)
            if self._current is not None:
                self.peaks[self._current] = max(self.peaks.get(self._current, 0), rss)
            time.sleep(self._interval)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        previous = self._current
        self._current = name
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
        else:
            rss = _rss_bytes()
            self.peaks[name] = max(self.peaks.get(name, 0), rss)
        try:
            with super().stage(name):
                yield
        finally:
            if self.device.type == "cuda":
                peak = int(torch.cuda.max_memory_allocated(self.device))
                self.peaks[name] = max(self.peaks.get(name, 0), peak)
                self.overall_peak = max(self.overall_peak, peak)
            self._current = previous

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1)


def hr_dims(size) -> tuple[int, int]:
    """``(width, height)`` of an HR size: an int ``N`` (``N x N``) or a ``(width, height)`` pair."""
    if isinstance(size, (tuple, list)):
        return int(size[0]), int(size[1])
    return int(size), int(size)


def size_label(size) -> str:
    """``'WxH'`` of an HR size (:func:`hr_dims`)."""
    w, h = hr_dims(size)
    return f"{w}x{h}"


def make_capture(size, directory: Path, gt: Path | None = None, *, sigma: float = 0.01, seed: int = 0) -> Path:
    """Simulate an HR capture of ``size`` (``N`` or ``(width, height)``) into ``directory`` and return its path:
    a centred crop of the ground truth when it is large enough, else a synthetic scene."""
    width, height = hr_dims(size)
    if gt is None:
        shared = shared_data_dir() / "gt" / "qiu-kettle"
        gt = shared if shared.is_dir() else None
    if gt is not None:
        image, source = read_gt_scene(gt)
        if image.shape[1] >= height and image.shape[2] >= width:
            if width == height:
                image, info = prepare_ground_truth(image, crop=width)
            else:  # a centred crop of the sides asked for
                image, info = prepare_ground_truth(centre_crop(image, (height, width)))
                info["crop"] = [height, width]
            source.update(info)
        else:
            image, source = None, None
    else:
        image = None
    if image is None:
        image, source = _synthetic_scene(height, width, seed), {"type": "synthetic"}
    capture = simulate_capture(image, make_sensor("gaussian", sigma=sigma), seed=seed, source=source)
    path = directory / f"capture-{width}x{height}"
    write_capture(path, capture, overwrite=True)
    return path


def _synthetic_scene(height: int, width: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = (height, width)
    s0 = np.stack([0.2 + 0.6 * gaussian_filter(rng.random(shape), 3) / 0.6 for _ in range(3)]).clip(0, 1)
    d = 0.5 * gaussian_filter(rng.random(shape), 8) / 0.5
    a = np.pi * gaussian_filter(rng.random(shape), 8) * 2
    return twelve_from_stokes(np.stack([s0, s0 * d * np.cos(2 * a), s0 * d * np.sin(2 * a)])).astype(np.float32)


def _thread_range(decisions: list[tuple[float, int]]) -> str:
    counts = sorted({count for _, count in decisions})
    if not counts:
        return "1 thread"
    return f"{counts[0]} thread{'s' if counts[0] > 1 else ''}" if len(counts) == 1 else f"{counts[0]}-{counts[-1]} threads"


def _run_method(method: str, capture, ctx: RunContext, tile: int | None):
    """The method's output, untiled, or in tiles of ``tile`` HR pixels (one worker, the run's device), and the
    tiled run's record (``None`` untiled)."""
    if tile is None:
        return get_method(method).function(capture, context=ctx), None
    return reconstruct_tiled(capture, method, tile=tile, device=str(ctx.device), true_warps=ctx.true_warps,
                             reuse_registration=False, **ctx.options)


def _tiled_stages(record: dict, wall: float) -> dict:
    """A tiled run's stages: each summed over the tiles (their record), plus ``tiles_other`` = the rest of the
    wall time (cropping the capture, blending, the physical projection)."""
    stages = {k: float(v) for k, v in record.get("stages_s", {}).items()}
    stages["tiles_other"] = max(0.0, wall - sum(stages.values()))
    return stages


def worker(capture_path: Path, device: str, iterations: int | None, true_warps: bool, method: str = "caps",
           threads: int | None = None, tile: int | None = None) -> dict:
    """One timed run in this process (called in a fresh subprocess by :func:`run_benchmark`); ``tile``: the
    HR core side of a tiled run (its stages are summed over the tiles; their peaks are not measured).

    ``iterations``: the ADMM iterations, or None for the method's own default.
    ``threads``: a fixed count, or None for the inherited setting (``$CAPSSIM_THREADS``; ``auto``: the
    count adapts to the machine's load at each stage, :func:`capssim.runtime.threads.adapt_threads`)."""
    set_threads(threads)
    adaptive = is_adaptive(threads)
    dev = resolve_device(device)
    capture = read_capture(capture_path, load_gt=False)
    timer = MemoryStageTimer(dev)
    baseline = _rss_bytes() if dev.type != "cuda" else 0
    options = {} if iterations is None else {"iterations": iterations}
    ctx = RunContext(device=dev, timer=timer, options=options, true_warps=true_warps,
                     reuse_registration=False)  # --estimated-warps times the registration in every run
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    with torch.no_grad():
        out, tiled_record = _run_method(method, capture, ctx, tile)
    wall = time.perf_counter() - t0
    timer.close()
    if not np.all(np.isfinite(out.image)):
        raise RuntimeError("benchmark run produced non-finite values")
    return {
        "method": method, "hr_size": capture.hr_shape[0], "hr_shape": list(capture.hr_shape), "tile": tile,
        "device": str(dev),
        "threads": f"auto, {_thread_range(adaptive_decisions())}" if adaptive else torch.get_num_threads(),
        "iterations": out.params.get("iterations", iterations), "true_warps": true_warps, "wall_s": wall,
        "stages_s": dict(timer.stages) if tiled_record is None else _tiled_stages(tiled_record, wall),
        "stage_peak_mb": {k: v / 2**20 for k, v in timer.peaks.items()},
        "peak_mb": timer.overall_peak / 2**20, "baseline_mb": baseline / 2**20,
        "load_before": load_before, "load_after": os.getloadavg()[0],
        "n_groups": out.params.get("n_groups"), "rematches": sum(bool(h.get("rematched")) for h in out.history),
    }


def _variants(size, tile: int | None) -> list[int | None]:
    """``None`` (untiled) where the untiled run's memory estimate fits the machine, and ``tile`` when given."""
    if tile is None:
        return [None]
    width, height = hr_dims(size)
    return ([None] if fits((height, width), memory_budget(None)[0]) else []) + [tile]


def _worker_command(path: Path, dev: str, method: str, tiled: int | None, *, iterations: int | None,
                    true_warps: bool, threads: int | None) -> list[str]:
    """The command line of one timed run (:func:`worker` in a fresh process)."""
    cmd = [sys.executable, "-m", WORKER_MODULE, "--worker", str(path), "--device", dev, "--method", method]
    cmd += [] if true_warps else ["--estimated-warps"]
    cmd += [] if iterations is None else ["--iterations", str(iterations)]
    cmd += [] if threads is None else ["--threads", str(threads)]
    cmd += [] if tiled is None else ["--tile", str(tiled)]
    return cmd


def run_benchmark(*, sizes=(256, 512, 1024), devices=("cpu", "cuda"), iterations: int | None = None,
                  repeats: int = 1, gt: Path | None = None, true_warps: bool = True, threads: int | None = None,
                  tile: int | None = None, methods=("caps",),
                  log: Callable[[str], None] = lambda msg: None) -> list[dict]:
    """Time each method of ``methods`` (CAPS-input methods; ``caps`` by default) for each size (``N`` or
    ``(width, height)``) and device, on the same capture; returns the fastest run of each.

    The ``repeats`` run in rounds: each round times every (size, device, tiling, method) once, then the reference
    run again (the first size's untiled run of each device and method), so a drift of the machine's speed between
    or within rounds touches every size alike. Each result carries ``all_wall_s`` (one per round),
    ``median_wall_s`` and ``per_pixel_vs_reference``: the median over the rounds of its time per pixel over that of
    the round's reference, the geometric mean of the reference's opening and closing runs (``closing_wall_s``;
    :func:`paired_ratios`).

    ``iterations``: the ADMM iterations of every method (None: each method's own default; ``caps``: 25).
    ``threads``: torch CPU threads of each run (None: torch's choice). ``tile``: also run in tiles of this HR
    side, and untiled only where the memory estimate fits (:func:`_variants`).
    """
    devs = [d for d in devices if d != "cuda" or torch.cuda.is_available()]
    with tempfile.TemporaryDirectory(prefix="capssim-bench-") as tmp:
        by_label = {size_label(size): size for size in sizes}  # 512 and 512x512: one capture
        paths = {label: make_capture(hr_dims(size), Path(tmp), gt) for label, size in by_label.items()}
        jobs = [(size_label(size), d, t, m) for size in sizes for d in devs for t in _variants(size, tile)
                for m in methods]
        jobs = list(dict.fromkeys(jobs))
        runs: dict[tuple, list[dict]] = {job: [] for job in jobs}
        references = _reference_jobs(jobs)  # they close each round too, where it has other runs to bracket
        closing: dict[tuple, list[float]] = {job: [] for job in references} if len(jobs) > len(references) else {}

        def timed(job: tuple, r: int, note: str = "") -> dict:
            label, dev, tiled, method = job
            what = ("untiled" if tiled is None else f"tiles of {tiled}") + note
            log(f"{method} {label} ({what}) on {dev}, round {r + 1}/{repeats} ...")
            cmd = _worker_command(paths[label], dev, method, tiled, iterations=iterations,
                                  true_warps=true_warps, threads=threads)
            proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if proc.returncode != 0:
                raise RuntimeError(f"benchmark worker failed:\n{proc.stderr[-2000:]}")
            return json.loads(proc.stdout.strip().splitlines()[-1])

        for r in range(repeats):
            for job in jobs:
                runs[job].append(timed(job, r))
            for job, walls in closing.items():
                walls.append(timed(job, r, ", closing")["wall_s"])
    results = []
    for job in jobs:
        best = dict(min(runs[job], key=lambda run: run["wall_s"]))
        best["repeats"] = repeats
        best["all_wall_s"] = [run["wall_s"] for run in runs[job]]
        best["median_wall_s"] = float(np.median(best["all_wall_s"]))
        if closing.get(job):
            best["closing_wall_s"] = closing[job]
        results.append(best)
    return paired_ratios(results)


def _reference_jobs(jobs: list[tuple]) -> list[tuple]:
    """The reference job of each (device, method): its first untiled job (:func:`paired_ratios`), which also
    closes every round, so that each round's reference brackets the round's other runs."""
    first: dict[tuple, tuple] = {}
    for job in jobs:
        if job[2] is None:
            first.setdefault((job[1], job[3]), job)
    return list(first.values())


def _worker_main(argv=None) -> None:
    """``python -m capssim.eval.benchmarks.reconstruct --worker CAPTURE ...``: one timed run, its JSON on stdout."""
    parser = argparse.ArgumentParser(prog=f"python -m {WORKER_MODULE}",
                                     description="internal worker of 'capssim bench reconstruct'")
    parser.add_argument("--worker", type=Path, required=True, help="run one timed reconstruction of this capture")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--method", default="caps")
    parser.add_argument("--estimated-warps", action="store_true")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--tile", type=int, default=None)
    args = parser.parse_args(argv)
    print(json.dumps(worker(args.worker, args.device, args.iterations, not args.estimated_warps,
                            method=args.method, threads=args.threads, tile=args.tile)))


if __name__ == "__main__":
    _worker_main()
