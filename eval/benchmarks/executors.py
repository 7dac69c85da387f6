"""Where the tasks of a suite run run: in this process, or on Dask workers.

Both executors take tasks with ``submit(fn, *args, tag=..., case=..., after=..., name=..., **kwargs)``
and hand back ``(tag, result, error)`` as tasks finish, from :meth:`completed`, which also
yields the tasks submitted while it runs:

* :class:`InProcess` runs one task at a time, here, when :meth:`completed` asks for the next:
  a pending ``case`` task before any other (a capture), each in the order submitted. A suite
  run therefore goes capture 1, its cases, capture 2, its cases..., as it always did;
* :class:`OnDask` submits each task to a Dask cluster at once and yields them in the order they
  finish; the captures have the higher priority, so that as many cases as possible are ready
  for the workers early. ``after`` (handles of earlier tasks) makes a task wait for those: the
  suite runner uses it so that two tasks never write the same cache folder at the same time, and
  so that a capture is registered once.

:func:`open_executor` picks one: the local cluster or the scheduler connection is
:func:`capssim.dataset.generate.open_dask_client`, the one ``capssim dataset`` uses (worker
processes of one Dask thread, their compute threads limited).
"""

from __future__ import annotations

import itertools
import uuid
from collections import deque
from contextlib import contextmanager
from typing import Callable, Iterator

from capssim.dataset.generate import check_local_workers, check_scheduler_address, open_dask_client
from capssim.errors import InputError
from capssim.files.output_paths import resolve_output
from capssim.runtime.threads import resolve_threads


class InProcess:
    """Runs the tasks in this process, one at a time, when :meth:`completed` asks for the next."""

    kind = "in-process"
    #: the tasks run here and may tell the progress display at once
    live_events = True

    def __init__(self, started: Callable[[object], None] | None = None):
        self.started = started or (lambda tag: None)
        self._cases: deque = deque()
        self._rest: deque = deque()

    def submit(self, fn, *args, tag, case: bool = False, after=(), name: str = "", **kwargs):
        (self._cases if case else self._rest).append((tag, fn, args, kwargs))
        return tag

    def completed(self) -> Iterator[tuple[object, object, BaseException | None]]:
        while self._cases or self._rest:
            tag, fn, args, kwargs = (self._cases or self._rest).popleft()
            self.started(tag)
            try:
                result, error = fn(*args, **kwargs), None
            except Exception as exc:  # the task's own failure; the caller records it
                result, error = None, exc
            yield tag, result, error


def _after(_finished: list, fn, *args, **kwargs):
    """Run ``fn`` once the tasks whose futures are in ``_finished`` are done (Dask resolves them first)."""
    return fn(*args, **kwargs)


class OnDask:
    """Runs the tasks on the workers of a :class:`distributed.Client`, as many at once as it has threads."""

    kind = "dask"
    live_events = False

    def __init__(self, client, compute_threads: int):
        from distributed import as_completed

        self.client = client
        self.compute_threads = compute_threads
        self.workers = len(client.nthreads())
        self._completed = as_completed()
        self._tags: dict[str, object] = {}
        self._run = uuid.uuid4().hex[:8]
        self._count = itertools.count()

    def submit(self, fn, *args, tag, case: bool = False, after=(), name: str = "", **kwargs):
        key = f"capssim-bench-{self._run}-{next(self._count)}-{name}"
        priority = 0 if case else 1
        if after:
            future = self.client.submit(_after, list(after), fn, *args, key=key, priority=priority, pure=False,
                                        **kwargs)
        else:
            future = self.client.submit(fn, *args, key=key, priority=priority, pure=False, **kwargs)
        self._tags[future.key] = tag
        self._completed.add(future)
        return future

    def completed(self) -> Iterator[tuple[object, object, BaseException | None]]:
        for future in self._completed:
            tag = self._tags.pop(future.key)
            try:
                result, error = future.result(), None
            except Exception as exc:  # the task raised, or its worker died too often (KilledWorker)
                result, error = None, exc
            yield tag, result, error


def check_execution(*, workers: int | None = None, scheduler: str | None = None, cache=None) -> None:
    """Refuse ``workers`` < 0, ``workers`` with ``scheduler``, a ``scheduler`` address that names no scheduler,
    more local workers than this machine takes, and a ``cache`` folder that cannot be one (:func:`check_cache_folder`)."""
    if workers is not None and workers < 0:
        raise InputError("--workers", workers, "an integer >= 0 (0: run in this process without Dask)")
    if workers and scheduler is not None:
        raise InputError("--workers", workers, "no --workers with --scheduler (the cluster has its own workers)")
    check_scheduler_address(scheduler)
    check_cache_folder(cache)
    if workers:
        check_local_workers(workers)


def check_cache_folder(cache) -> None:
    """Refuse a ``--cache`` the captures cannot be cached in (a file, a link loop, a place that refuses new
    entries), before any case runs: every case would fail on it."""
    if cache is not None:
        resolve_output(cache, kind="folder", overwrite=True, argument="--cache")


@contextmanager
def open_executor(*, workers: int | None = None, scheduler: str | None = None, threads: int | None = None,
                  started: Callable[[object], None] | None = None):
    """The executor of a run: in this process (``workers`` None or 0, no ``scheduler``), else Dask.

    ``workers``: a local cluster of that many processes, one task at a time each;
    ``scheduler``: the address of a running cluster. Each worker computes with ``threads``
    (:func:`capssim.runtime.threads.resolve_threads`: ``--threads``, ``$CAPSSIM_THREADS`` or the
    default), the count a run in this process uses, so that both give the same numbers.
    ``started(tag)`` is told when an in-process task starts.
    """
    check_execution(workers=workers, scheduler=scheduler)
    if not workers and scheduler is None:
        yield InProcess(started)
        return
    compute_threads = resolve_threads(threads)
    cluster, client, compute_threads = open_dask_client(workers=workers, scheduler=scheduler,
                                                        compute_threads=compute_threads)
    try:
        yield OnDask(client, compute_threads)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
