"""Tiles of one frame, or the frames of a folder of captures, on Dask (``--workers N`` or ``--scheduler ADDR``).

The client is the project's (:func:`capssim.dataset.generate.open_dask_client`: a local cluster of ``N``
processes of one thread each, compute threads limited per worker, or the running cluster at ``ADDR``).
Every part is written as soon as it finishes: a tile (by this process) into the frame's parts folder, a
frame (by its worker) into its own ``recon/``; a rerun after a kill skips what is written. Workers of a remote cluster
must see the capture folders at the same paths (a shared file system).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Iterable, Iterator

from capssim.dataset.generate import open_dask_client

from .frames import frame_is_finished, frame_job_key, reconstruct_frame

log = logging.getLogger(__name__)

__all__ = ["DaskSession", "dask_runner", "reconstruct_frames"]


def dask_runner(client) -> Callable[[Callable, list], Iterable[tuple[int, object]]]:
    """A tile runner on ``client``: submits every job, yields ``(index, result)`` as each finishes."""

    def run(function: Callable, jobs: list) -> Iterator[tuple[int, object]]:
        from distributed import as_completed

        if not jobs:
            return
        futures = {client.submit(function, *job, pure=False): index for index, job in enumerate(jobs)}
        try:
            for future in as_completed(list(futures)):
                yield futures[future], future.result()
        finally:
            for future in futures:
                future.cancel()

    return run


class DaskSession:
    """A context manager: a Dask client (local cluster of ``workers``, or ``scheduler``), closed on exit."""

    def __init__(self, *, workers: int | None = None, scheduler: str | None = None):
        self.workers, self.scheduler = workers, scheduler
        self.cluster = self.client = None

    def __enter__(self) -> "DaskSession":
        for name in ("distributed", "distributed.scheduler", "distributed.nanny", "distributed.core"):
            logging.getLogger(name).setLevel(logging.WARNING)  # the cluster's start and stop are no news
        self.cluster, self.client, _ = open_dask_client(workers=self.workers, scheduler=self.scheduler)
        return self

    def __exit__(self, *exc) -> None:
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()

    @property
    def runner(self):
        return dask_runner(self.client)


def reconstruct_frames(folders: list[Path], method: str, *, client=None, tile: int | None = None,
                       memory_gb: float | None = None, **kwargs) -> Iterator[tuple[Path, dict | None]]:
    """Reconstruct every capture of ``folders`` with ``method``; yields ``(folder, record)`` as each is written.

    A frame already finished with the same job (:func:`~.frames.frame_is_finished`) is skipped and yields
    ``(folder, None)``. ``client``: a Dask client that runs one frame per task (``None``: here, in order); each
    frame writes its own ``recon/METHOD.{tiff,json}`` (atomically) as it finishes. ``tile``, ``memory_gb`` and
    ``**kwargs``: as :func:`~.frames.reconstruct_frame` (its tiles run serially inside the frame's task).
    """
    todo = []
    for folder in folders:
        key = frame_job_key(folder, method, {**kwargs, "tile": tile, "memory_gb": memory_gb})
        if frame_is_finished(folder, method, key):
            yield folder, None
        else:
            todo.append(folder)
    jobs = [(str(folder),) for folder in todo]

    def one(path: str) -> dict:
        return reconstruct_frame(path, method, tile=tile, memory_gb=memory_gb, **kwargs)

    if client is None:
        for folder in todo:
            yield folder, one(str(folder))
        return
    for index, record in dask_runner(client)(one, jobs):
        yield todo[index], record
