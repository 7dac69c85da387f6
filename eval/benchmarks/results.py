"""``results.jsonl`` of a suite run: one JSON line per case, appended as each case finishes.

* :meth:`ResultsLog.append` writes one complete line with one ``write`` on a descriptor opened
  with ``O_APPEND``, then ``fsync``: a run killed at any moment leaves the line of every case
  finished before whole, and at most a partial last line;
* :func:`read_results` takes the last line of each ``case_id`` and ignores, with a warning, any
  line that is not a JSON object with a ``case_id`` (a partial last line, a corrupted line);
* a run starts by rewriting the file atomically with its valid lines only (so that the next
  line starts on a line of its own), and ends by rewriting it atomically in the plan's order
  (:meth:`ResultsLog.finish`), so that a serial and a distributed run write the same file.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from capssim.files.imageio import append_line_durably, atomic_write_text

from .provenance import json_default

log = logging.getLogger(__name__)


def read_results(path: Path) -> dict[str, dict]:
    """The records of ``path`` by ``case_id`` (the last line of a case wins); ``{}`` if there is no file."""
    done: dict[str, dict] = {}
    if not path.is_file():
        return done
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        line = line.strip()
        if not line:
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            log.warning("ignoring line %d of %s: not complete JSON (a run killed while writing it?)", number, path)
            continue
        if isinstance(rec, dict) and "case_id" in rec:
            done[rec["case_id"]] = rec
        else:
            log.warning("ignoring line %d of %s: not a case record", number, path)
    return done


def results_text(records: list[dict]) -> str:
    """``records`` as JSON lines."""
    return "".join(json.dumps(r, default=json_default) + "\n" for r in records)


class ResultsLog:
    """The ``results.jsonl`` of one run: the previous run's records, appends, the final rewrite.

    ``fresh``: redo this run's cases (:meth:`done` answers ``None``); the previous records of cases outside this
    run's plan (other methods or scenes of the suite) are kept, as in any run.
    """

    def __init__(self, path: Path, *, fresh: bool = False):
        self.path = Path(path)
        self.fresh = bool(fresh)
        self.previous = read_results(self.path)
        atomic_write_text(self.path, results_text(list(self.previous.values())))

    def done(self, case_id: str) -> dict | None:
        """The previous run's record of ``case_id`` if that case finished ``ok`` (never with ``fresh``)."""
        if self.fresh:
            return None
        rec = self.previous.get(case_id)
        return rec if rec is not None and rec.get("status") == "ok" else None

    def append(self, record: dict) -> None:
        """Append ``record`` as one line, durably (one write, then fsync)."""
        append_line_durably(self.path, results_text([record]).encode())

    def finish(self, records: list[dict]) -> None:
        """Rewrite the file atomically: ``records`` (this plan's, in its order), then the previous
        run's ``ok`` records of cases outside this plan (another subset of the suite). A previous
        record of a case this plan ran again (same ``key``, another hash: changed code or options)
        is superseded and dropped."""
        keep, keys = {r["case_id"] for r in records}, {r.get("key") for r in records}
        extra = [r for cid, r in self.previous.items()
                 if cid not in keep and r.get("status") == "ok" and (r.get("key") is None or r.get("key") not in keys)]
        atomic_write_text(self.path, results_text(records + extra))
