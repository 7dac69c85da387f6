"""Generating a dataset on Dask: resumable, one sample per task, nothing half-written.

:func:`generate_dataset` runs every unfinished sample of a config as one Dask task:

* on a :class:`distributed.LocalCluster` it starts (``workers`` processes, one thread each,
  compute threads per worker = cores // workers), on an existing cluster (``scheduler``
  address), on a :class:`distributed.Client` you pass, or in this process (``workers=0``);
* each task writes its capture folder under a temporary name and renames it when complete
  (:func:`capssim.captures.capture.write_capture`), then returns the checksums; this process appends the
  sample's line to the manifest (fsync'ed). A worker that dies mid-sample loses that sample only:
  Dask reschedules the task on another worker, and its temporary folder is swept at the end;
* a rerun skips the samples listed in the manifest (whose folder exists), removes leftovers
  (temporary folders, folders without a manifest line, a torn last manifest line) and redoes
  the rest. Samples are a function of (config, index) only, so the result is byte-identical to
  an uninterrupted run, whatever the number of workers or the order of completion.

Workers must see the output folder and the ground-truth paths at the same paths (a shared file
system) and have capssim installed.
"""

from __future__ import annotations

import logging
import shutil
import time
import traceback
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

from capssim.dataset._dask import ThreadLimitPlugin
from capssim.dataset.config import DatasetConfig
from capssim.dataset.manifest import (
    MANIFEST,
    SAMPLES_DIR,
    DatasetLock,
    ManifestWriter,
    is_leftover_name,
    is_sample_name,
    read_dataset_json,
    read_manifest,
    rewrite_manifest,
    write_dataset_json,
)
from capssim.dataset.sample import generate_sample
from capssim.errors import CapssimError, InputError
from capssim.runtime.resources import check_memory, check_range
from capssim.runtime.threads import CHILD_ENV_VARS, available_cores

log = logging.getLogger(__name__)


@dataclass
class ProgressInfo:
    """What a progress display needs. ``rate_per_hour`` and ``eta_s`` count this run's samples only."""

    done: int            # finished samples (including those finished by earlier runs)
    total: int
    generated: int       # finished by this run
    failed: int
    elapsed_s: float
    rate_per_hour: float | None
    eta_s: float | None
    last: dict | None = None


@dataclass
class GenerateResult:
    out: Path
    total: int
    already_done: int
    generated: int
    failed: dict[int, str] = field(default_factory=dict)
    removed: list[str] = field(default_factory=list)
    wall_s: float = 0.0
    workers: int | None = None
    compute_threads: int | None = None

    @property
    def complete(self) -> bool:
        return not self.failed and self.already_done + self.generated == self.total

    @property
    def samples_per_hour(self) -> float | None:
        return 3600.0 * self.generated / self.wall_s if self.generated and self.wall_s > 0 else None


def _rmtree(path: Path, removed: list[str], why: str) -> None:
    shutil.rmtree(path, ignore_errors=True)
    if path.exists():  # a file, not a folder
        path.unlink(missing_ok=True)
    removed.append(path.name)
    log.info("removed %s (%s)", path, why)


def sweep_leftovers(samples_dir: Path, finished_names: set[str]) -> list[str]:
    """Remove temporary folders and sample folders that have no manifest line."""
    removed: list[str] = []
    if not samples_dir.is_dir():
        return removed
    for entry in sorted(samples_dir.iterdir()):
        if is_leftover_name(entry.name):
            _rmtree(entry, removed, "temporary folder of an unfinished sample")
        elif is_sample_name(entry.name) and entry.name not in finished_names:
            _rmtree(entry, removed, "sample folder without a manifest line")
    return removed


#: a local worker process's memory before its first task (Python, torch, Dask), about
WORKER_BYTES_ESTIMATE = 300 * 2**20
#: local workers per core past which more only add start-up time and memory
MAX_WORKERS_PER_CORE = 4


def check_local_workers(workers: int, *, option: str = "--workers") -> None:
    """Refuse a local worker count past :data:`MAX_WORKERS_PER_CORE` per core or the memory limit."""
    cores = available_cores()
    check_range(option, workers, high=MAX_WORKERS_PER_CORE * cores, what="the number of local worker processes",
                reason=f"{MAX_WORKERS_PER_CORE} per core on this {cores}-core machine",
                fix=f"Use --workers {cores} (one per core), or --scheduler ADDRESS for a larger cluster.")
    check_memory(option, workers * WORKER_BYTES_ESTIMATE, what=f"{workers} worker processes",
                 fix="Use fewer --workers.")


#: the address schemes a Dask client connects with (``host:port`` alone means ``tcp://``)
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")


def check_scheduler_address(address: str | None, *, option: str = "--scheduler") -> None:
    """Refuse a Dask scheduler address that cannot name one, before any work (Dask's own parser
    raises a ``ValueError`` only when the client connects): ``[SCHEME://]HOST:PORT``, the scheme one
    of :data:`SCHEDULER_SCHEMES`, the port an integer in 1 ... 65535 (IPv6 hosts in brackets)."""
    if address is None:
        return
    text = str(address).strip()
    valid = ("an address of a running Dask scheduler, [SCHEME://]HOST:PORT with the port an integer in "
             f"1 ... 65535 and SCHEME one of {', '.join(SCHEDULER_SCHEMES)}")
    fix = "For example --scheduler tcp://localhost:8786 (the address 'dask scheduler' prints)."
    scheme, sep, location = text.partition("://")
    if not sep:
        scheme, location = "tcp", text
    if scheme.lower() not in SCHEDULER_SCHEMES:
        raise InputError(option, f"{text!r} (scheme {scheme!r})", valid, fix)
    host, colon, port = location.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not colon or not host or any(c.isspace() or c in "/[]" for c in host):
        what = "nothing" if not text else f"{text!r} (no HOST:PORT)"
        raise InputError(option, what, valid, fix)
    if not (port.isascii() and port.isdigit() and 1 <= int(port) <= 65535):
        raise InputError(option, f"{text!r} (port {port!r})", valid, fix)


#: environment variables Dask's nanny would give its workers and that capssim's workers must not have:
#: an explicit ``MALLOC_TRIM_THRESHOLD_`` turns off glibc's dynamic mmap threshold, so every array of
#: 128 kB or more is a fresh mmap (page faults, zeroing): the methods ran 3x slower in a worker
#: (docs/notes/distributed-bench.md)
UNSET_WORKER_ENV = ("MALLOC_TRIM_THRESHOLD_",)


def _start_local_cluster(workers: int, compute_threads: int):
    import dask
    from distributed import Client, LocalCluster

    check_local_workers(workers)

    env = {var: str(compute_threads) for var in CHILD_ENV_VARS}
    unset = {f"distributed.nanny.pre-spawn-environ.{var}": None for var in UNSET_WORKER_ENV}
    with dask.config.set(unset):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                               env=env, silence_logs=logging.ERROR)
    return cluster, Client(cluster)


def open_dask_client(*, workers: int | None = None, scheduler: str | None = None,
                     compute_threads: int | None = None):
    """``(cluster or None, client, compute threads)``: a Dask client that limits its workers' compute threads.

    ``scheduler``: a client of the running cluster at that address (compute threads default 1);
    else a new :class:`distributed.LocalCluster` of ``workers`` processes of 1 thread each
    (default: one per core; compute threads default cores // workers). The caller closes the
    client, then the cluster. Shared by ``capssim dataset`` and ``capssim bench suite``.
    """
    from distributed import Client

    if scheduler is None:
        workers = workers or available_cores()
        compute_threads = compute_threads or max(1, available_cores() // workers)
        log.info("starting a local Dask cluster: %d workers x 1 thread, %d compute threads each",
                 workers, compute_threads)
        cluster, client = _start_local_cluster(workers, compute_threads)
    else:
        log.info("connecting to the Dask scheduler at %s", scheduler)
        try:
            client = Client(scheduler, timeout="30s")
        except (OSError, ValueError) as exc:  # ValueError: an address Dask cannot parse
            raise InputError("scheduler", repr(scheduler), "the address of a running Dask scheduler",
                             f"Could not connect ({exc}). Start one with 'dask scheduler' and "
                             "'dask worker ADDRESS', or leave --scheduler out for a local cluster.") from None
        cluster, compute_threads = None, compute_threads or 1
    client.register_plugin(ThreadLimitPlugin(compute_threads), name=ThreadLimitPlugin.name)
    return cluster, client, compute_threads


def dataset_is_finished(config: DatasetConfig, out) -> bool:
    """True when folder ``out`` holds every sample of ``config``: read-only, takes no lock.

    Readers (training, scoring) call it first so that any number of them can share a finished
    dataset while :func:`generate_dataset` keeps one writer per folder.
    """
    out = Path(out)
    info = read_dataset_json(out) if out.is_dir() else None
    if info is None or info.get("fingerprint") != config.fingerprint() or info.get("samples") != config.samples:
        return False
    records = read_manifest(out / MANIFEST).records
    return len(finished_records(records, out / SAMPLES_DIR, config.samples)) == config.samples


def finished_records(records: dict[int, dict], samples_dir: Path, samples: int) -> dict[int, dict]:
    """The manifest records of samples ``0 .. samples-1`` whose folder exists: the finished samples."""
    return {i: r for i, r in records.items() if i < samples and (samples_dir / r["name"]).is_dir()}


def generate_dataset(config: DatasetConfig, out, *, workers: int | None = None, scheduler: str | None = None,
                     client=None, compute_threads: int | None = None, max_in_flight: int | None = None,
                     progress: Callable[[ProgressInfo], None] | None = None,
                     sample_function: Callable[[dict, str], dict] = generate_sample) -> GenerateResult:
    """Generate (or finish) the dataset of ``config`` in folder ``out``.

    Execution: ``client`` if given; else ``scheduler`` (address of an existing Dask cluster);
    else a local cluster of ``workers`` processes (default: one per core); ``workers=0`` runs in
    this process without Dask. ``compute_threads`` is the torch/OpenMP/Mitsuba thread count of
    each worker (default: cores // workers locally, 1 on an existing cluster). At most
    ``max_in_flight`` samples are submitted at once (default: 2 x the cluster's threads + 2).

    A sample that raises a :class:`~capssim.errors.CapssimError` (bad input: the config is
    wrong for it) stops the run and the error is raised; other failures (crashes, a worker
    killed 3 times) are recorded in the result and the run goes on.
    """
    t_start = time.perf_counter()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output", f"existing file {str(out)!r}", "a folder for the dataset")
    if workers is not None and workers < 0:
        raise InputError("workers", workers, "an integer >= 0 (0: run in this process without Dask)")
    if compute_threads is not None and compute_threads < 1:
        raise InputError("compute_threads", compute_threads, "an integer >= 1")
    if workers and client is None and scheduler is None:
        check_local_workers(workers)
    out.mkdir(parents=True, exist_ok=True)
    samples_dir = out / SAMPLES_DIR
    with DatasetLock(out):
        write_dataset_json(out, config)
        samples_dir.mkdir(exist_ok=True)
        manifest_path = out / MANIFEST
        contents = read_manifest(manifest_path)
        if contents.torn_tail or contents.bad_lines:
            if contents.bad_lines:
                log.warning("manifest %s: dropped invalid lines %s; their samples will be redone",
                            manifest_path, contents.bad_lines)
            rewrite_manifest(manifest_path, contents.lines)
        finished = finished_records(contents.records, samples_dir, config.samples)
        missing = sorted(set(contents.records) - set(finished))
        missing = [i for i in missing if i < config.samples]
        if missing:
            log.warning("%d samples listed in the manifest have no folder; they will be redone: %s",
                        len(missing), missing[:10])
        listed_names = {r["name"] for i, r in contents.records.items() if i in finished or i >= config.samples}
        removed = sweep_leftovers(samples_dir, listed_names)
        todo = [i for i in range(config.samples) if i not in finished]
        result = GenerateResult(out=out, total=config.samples, already_done=len(finished), generated=0,
                                removed=removed)
        log.info("dataset %s: %d samples, %d already finished, %d to make, %d leftovers removed",
                 out, config.samples, len(finished), len(todo), len(removed))
        if todo:
            with ManifestWriter(manifest_path) as writer:
                runner = _run_in_process if (client is None and scheduler is None and workers == 0) else _run_on_dask
                runner(config, samples_dir, todo, writer, result, t_start=t_start, progress=progress,
                       sample_function=sample_function, client=client, scheduler=scheduler, workers=workers,
                       compute_threads=compute_threads, max_in_flight=max_in_flight)
            now_listed = {r["name"] for r in read_manifest(manifest_path).records.values()}
            result.removed += sweep_leftovers(samples_dir, now_listed)
    result.wall_s = time.perf_counter() - t_start
    return result


def _record_done(record: dict, writer: ManifestWriter, result: GenerateResult, t_first: float,
                 progress, config) -> None:
    record["finished_at"] = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
    writer.append(record)
    result.generated += 1
    _report(result, t_first, progress, record)


def _report(result: GenerateResult, t_first: float, progress, record=None) -> None:
    elapsed = time.perf_counter() - t_first
    rate = 3600.0 * result.generated / elapsed if result.generated and elapsed > 0 else None
    done = result.already_done + result.generated
    remaining = result.total - done - len(result.failed)
    eta = remaining / rate * 3600.0 if rate else None
    info = ProgressInfo(done=done, total=result.total, generated=result.generated, failed=len(result.failed),
                        elapsed_s=elapsed, rate_per_hour=rate, eta_s=eta, last=record)
    if progress is not None:
        progress(info)
    log.debug("%d/%d samples (%s/h, ETA %s s)", done, result.total, f"{rate:.0f}" if rate else "-",
              f"{eta:.0f}" if eta else "-")


def _run_in_process(config, samples_dir, todo, writer, result, *, t_start, progress, sample_function, **_):
    t_first = time.perf_counter()
    result.workers, result.compute_threads = 0, None
    _report(result, t_first, progress)
    for index in todo:
        spec = config.sample_spec(index)
        try:
            record = sample_function(spec, str(samples_dir))
        except CapssimError:
            raise
        except Exception as exc:  # a crash in one sample must not stop the others
            log.error("sample %s failed: %s", spec["name"], exc)
            result.failed[index] = f"{type(exc).__name__}: {exc}"
            _report(result, t_first, progress)
            continue
        _record_done(record, writer, result, t_first, progress, config)


def _run_on_dask(config, samples_dir, todo, writer, result, *, t_start, progress, sample_function, client,
                 scheduler, workers, compute_threads, max_in_flight):
    from distributed import as_completed

    cluster = own_client = None
    try:
        if client is None:
            cluster, client, compute_threads = open_dask_client(workers=workers, scheduler=scheduler,
                                                                compute_threads=compute_threads)
            own_client = client
        else:
            compute_threads = compute_threads or 1
            client.register_plugin(ThreadLimitPlugin(compute_threads), name=ThreadLimitPlugin.name)
        result.compute_threads = compute_threads
        nthreads = sum(client.nthreads().values()) or 1
        result.workers = len(client.nthreads())
        window = max_in_flight or 2 * nthreads + 2
        queue = iter(todo)
        completed = as_completed()
        tag = config.fingerprint()[:10]

        def submit_next() -> bool:
            index = next(queue, None)
            if index is None:
                return False
            spec = config.sample_spec(index)
            future = client.submit(sample_function, spec, str(samples_dir), key=f"capssim-{tag}-{spec['name']}",
                                   pure=False)
            future.capssim_index = index
            completed.add(future)
            return True

        for _ in range(window):
            if not submit_next():
                break
        t_first = time.perf_counter()
        _report(result, t_first, progress)
        for future in completed:
            index = future.capssim_index
            try:
                record = future.result()
            except CapssimError:
                for f in list(completed.futures):
                    f.cancel()
                raise
            except Exception as exc:  # crash, or the worker died too often (KilledWorker)
                log.error("sample %d failed: %s: %s", index, type(exc).__name__, exc)
                log.debug("".join(traceback.format_exception(exc)))
                result.failed[index] = f"{type(exc).__name__}: {exc}"
                _report(result, t_first, progress)
            else:
                _record_done(record, writer, result, t_first, progress, config)
            future.release()
            submit_next()
    finally:
        if own_client is not None:
            own_client.close()
        if cluster is not None:
            cluster.close()
