"""A suite run widened to every case its folder holds: what a report and a results page show after ``-m`` or
``--scene``.

``capssim bench suite SUITE -o RUN -m METHOD --results-page PAGE`` reruns one method; its page must still show the
suite's other methods and scenes. :func:`whole_suite_run` takes the run's own records and, for every other case of
the suite (a method label and a scene the suite file names), the latest ``ok`` record of that case in
``RUN/results.jsonl`` (by its ``finished`` time): a result of an earlier run, possibly of earlier code, which the
page's notes say (how many, and from which git revisions).
"""

from __future__ import annotations

import dataclasses

from .results import read_results
from .suite import BenchRun

__all__ = ["whole_suite_run"]


def _revision(record: dict) -> str:
    git = (record.get("environment") or {}).get("git") or {}
    revision = str(git.get("revision") or "unknown")[:12]
    return revision + (" (with uncommitted changes)" if git.get("dirty") else "")


def whole_suite_run(run: BenchRun, *, scene_names: set[str]) -> BenchRun:
    """``run`` with, after its own records, the latest ``ok`` record of each other case of its suite in its
    ``results.jsonl`` (cases of the suite's method labels on ``scene_names``); ``notes`` gains one line saying how
    many records come from earlier runs and their git revisions. ``run`` itself is left unchanged."""
    labels = {m["label"] for m in run.spec["methods"]}
    own = {r.get("key") for r in run.records}
    latest: dict[str, dict] = {}
    for record in read_results(run.results_path).values():
        key = record.get("key")
        if (record.get("status") != "ok" or key is None or key in own or record.get("method") not in labels
                or record.get("scene") not in scene_names):
            continue
        if key not in latest or str(record.get("finished", "")) >= str(latest[key].get("finished", "")):
            latest[key] = record
    earlier = list(latest.values())
    if not earlier:
        return run
    revisions = sorted({_revision(r) for r in earlier})
    note = (f"{len(earlier)} of the {len(run.records) + len(earlier)} cases on this page are the latest results of "
            f"earlier runs into the same folder, outside this run's -m/--scene selection of {len(run.records)} "
            f"(their code: git {', '.join(revisions)})")
    return dataclasses.replace(run, records=list(run.records) + earlier, notes=[*run.notes, note])
