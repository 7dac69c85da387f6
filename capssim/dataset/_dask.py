"""Dask pieces that need ``distributed`` at import time: the worker plugin that limits compute threads."""

from __future__ import annotations

from distributed.diagnostics.plugin import WorkerPlugin

from capssim.dataset.sample import limit_threads


class ThreadLimitPlugin(WorkerPlugin):
    """Limits each worker's compute threads (torch, OpenMP/BLAS, Dr.Jit) so that
    workers x threads does not oversubscribe the cores (see :func:`limit_threads`)."""

    name = "capssim-thread-limit"

    def __init__(self, threads: int):
        self.threads = int(threads)

    def setup(self, worker):
        limit_threads(self.threads)
