"""Run a design map: cells x seeds x methods, on the suites' case runner, into ``DIR/map.jsonl``.

``capssim bench map SPEC -o DIR`` (:func:`run_map`). Each cell (one combination of the axes' values,
:func:`~.spec.expand_cells`) and seed is one capture, built once and cached (:class:`~.cells.MapCaptureFactory`);
every method runs on it (:func:`~.cells.map_task`), and camera-array methods that estimate warps register it
once (the runner's registration order: the first registers and stores the warps, the others reuse them).
The case runner (:func:`capssim.eval.benchmarks.runner.run_cases`) gives the rest, as for a suite:

* the folder's lock and owner (``bench-map.json``): one run at a time, one map per folder;
* resume: ``map.jsonl`` gets one line per case as it finishes (one durable append each); run again, only the
  cases without an ``ok`` line of the same case hash (capture content, method entry, device, code) run;
* the same lines in serial and on Dask (``-w N``, ``--scheduler``): each case depends on its own seeded capture
  only, and the file is rewritten in plan order (cells, the first axis slowest, then seeds, then methods) at the
  end. Times, workers and timestamps differ between runs; everything else is equal.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from capssim.reconstruct.registry import resolve_device
from capssim.runtime.resources import check_scene_size

from ..benchmarks.output_claim import OutputKind
from ..benchmarks.provenance import code_fingerprint, environment
from ..benchmarks.runner import CaseTask, run_cases
from ..benchmarks.suite import RECONSTRUCTION_CODE, SCORING_CODE, BenchRun
from ..benchmarks.suite_schema import _scene_size
from .cells import cell_scene, map_capture_task, map_task
from .spec import expand_cells

MAP_OUTPUT = OutputKind("bench map", "map.jsonl", "bench-map.json")
#: the source files whose change re-runs a map's cases (besides the suites' reconstruction and scoring code)
MAP_CODE = ("eval/maps/cells.py", "eval/maps/theory.py", "eval/maps/sweep.py")
#: the runner's noise level of every cell (each cell carries its own sensor: ``scene["map"]["noise"]``)
CELL_NOISE = {"name": "map", "noise": "none"}


def plan_map(spec: dict) -> list[dict]:
    """The cell scenes of a map in plan order (:func:`~.cells.cell_scene`), after the resource guard of the
    scene's size (:func:`capssim.runtime.resources.check_scene_size`, as a suite)."""
    size = _scene_size(spec["scene"])
    if size is not None:
        check_scene_size(f"map {spec.get('path', spec['name'])}, key 'scene'", size,
                         fix="Use a smaller size or crop, or raise CAPSSIM_MEMORY_LIMIT_GB.")
    return [cell_scene(spec["scene"], cell) for cell in expand_cells(spec)]


def run_map(spec: dict, output: str | Path, *, device: str = "cpu", cache_dir: str | Path | None = None,
            fresh: bool = False, workers: int | None = None, scheduler: str | None = None,
            threads: int | None = None, events: Callable[..., None] | None = None) -> BenchRun:
    """Run (or resume) a design map into ``output`` (module docstring).

    Parameters
    ----------
    spec : dict
        A map from :func:`~.spec.load_map`.
    output : str or pathlib.Path
        The map's folder: ``map.jsonl``, the captures' cache (``cache/``).
    device, cache_dir, fresh, workers, scheduler, threads : keyword-only
        Torch device; the captures' cache (default ``output/cache``); redo every case; a local Dask cluster of
        that many processes or the one at that address (default: this process); compute threads per worker.
    events : callable, optional
        ``events(kind, **info)``: the runner's progress events (``start``, ``case``, ``done``, ``note``, ...).

    Returns
    -------
    capssim.eval.benchmarks.suite.BenchRun
        The finished map, as a suite's run: ``records`` in plan order, the folder, ``map.jsonl``, notes, wall
        time, the environment and where it ran.
    """
    t0 = time.perf_counter()
    scenes = plan_map(spec)
    runner_spec = dict(spec, noise=[CELL_NOISE])
    env = environment(str(resolve_device(device)))
    task = CaseTask(map_task, MAP_OUTPUT, record={"environment": env}, capture_fn=map_capture_task,
                    identity={"recon": code_fingerprint(*RECONSTRUCTION_CODE),
                              "scoring": code_fingerprint(*SCORING_CODE), "map": code_fingerprint(*MAP_CODE)})
    outcome = run_cases(runner_spec, output, task, plan_scenes=scenes, plan_methods=spec["methods"],
                        scene_by_name={s["name"]: s for s in scenes}, device=device, cache_dir=cache_dir, fresh=fresh,
                        workers=workers, scheduler=scheduler, threads=threads, events=events)
    return BenchRun(spec=spec, output=Path(output), results_path=outcome.results_path, records=outcome.records,
                    environment=env, notes=outcome.notes, wall_time_s=time.perf_counter() - t0,
                    execution=outcome.execution)
