"""The dataset folder on disk: ``dataset.json``, ``manifest.jsonl``, ``samples/``, and its lock.

Layout::

    OUT/
      dataset.json      the config (as written), its fingerprint, the sample count, versions
      manifest.jsonl    one JSON line per finished sample: index, name, seed, source, params,
                        files {name: {sha256, bytes}}, timing {...}, worker, finished_at
      samples/NAME/     one capture folder per sample (NAME = zero-padded index)
      .lock             held (flock) by the run that is writing the dataset

Only the process driving a run writes the manifest. It appends one line per finished sample
and ``fsync``\\ s it, so a kill loses at most the line being written: a torn last line is
dropped (and the file rewritten atomically without it) by the next run. A sample counts as
finished only once its line is in the manifest; a folder without a line is a leftover.
"""

from __future__ import annotations

import fcntl
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from capssim import __version__
from capssim.errors import CaptureFormatError, InputError
from capssim.files.imageio import append_line_durably, atomic_write_bytes, atomic_write_json

log = logging.getLogger(__name__)

DATASET_SCHEMA = "capssim.dataset"
DATASET_SCHEMA_VERSION = 1
DATASET_JSON = "dataset.json"
MANIFEST = "manifest.jsonl"
SAMPLES_DIR = "samples"
LOCK = ".lock"


@dataclass
class ManifestContents:
    records: dict[int, dict] = field(default_factory=dict)  # index -> last record of it
    lines: list[bytes] = field(default_factory=list)         # every valid line, in order
    bad_lines: list[int] = field(default_factory=list)       # 1-based line numbers that are not valid records
    torn_tail: bool = False                                   # last line cut short (a kill mid-write)
    duplicates: int = 0


_REQUIRED = ("index", "name", "files")


def read_manifest(path) -> ManifestContents:
    """Parse ``manifest.jsonl``; never raises on bad lines, it reports them."""
    path = Path(path)
    out = ManifestContents()
    if not path.is_file():
        return out
    data = path.read_bytes()
    raw_lines = data.split(b"\n")
    complete, tail = raw_lines[:-1], raw_lines[-1]
    if tail.strip():
        out.torn_tail = True  # no final newline: the writer was killed mid-line
    for number, line in enumerate(complete, start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            ok = isinstance(rec, dict) and all(k in rec for k in _REQUIRED) and isinstance(rec["index"], int)
        except (json.JSONDecodeError, UnicodeDecodeError):
            ok = False
        if not ok:
            out.bad_lines.append(number)
            continue
        if rec["index"] in out.records:
            out.duplicates += 1
        out.records[rec["index"]] = rec
        out.lines.append(line)
    return out


def rewrite_manifest(path, lines: list[bytes]) -> None:
    """Atomically replace the manifest with ``lines`` (used to drop a torn or bad line)."""
    atomic_write_bytes(path, b"".join(line + b"\n" for line in lines))


class ManifestWriter:
    """Appends records, one line each, flushed and fsync'ed before :meth:`append` returns."""

    def __init__(self, path):
        self.path = Path(path)
        self.path.touch()

    def append(self, record: dict) -> None:
        append_line_durably(self.path, json.dumps(record, sort_keys=True, separators=(",", ":")).encode("utf-8") + b"\n")

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class DatasetLock:
    """An exclusive ``flock`` on ``OUT/.lock``: one writing run per dataset folder."""

    def __init__(self, out):
        self.path = Path(out) / LOCK
        self._fh = None

    def __enter__(self):
        self._fh = open(self.path, "a")
        try:
            fcntl.flock(self._fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._fh.close()
            raise InputError("output", f"{str(self.path.parent)!r}, which another capssim run is writing",
                             "a dataset folder no other run is using",
                             "Wait for that run to finish (or stop it), then rerun.") from None
        return self

    def __exit__(self, *exc):
        fcntl.flock(self._fh, fcntl.LOCK_UN)
        self._fh.close()


def read_dataset_json(out) -> dict | None:
    path = Path(out) / DATASET_JSON
    if not path.is_file():
        return None
    try:
        info = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CaptureFormatError(f"{path}: corrupt JSON ({exc}).") from exc
    if info.get("schema") != DATASET_SCHEMA:
        raise CaptureFormatError(f"{path}: schema is {info.get('schema')!r}; expected {DATASET_SCHEMA!r}.")
    return info


def write_dataset_json(out, config) -> dict:
    """Create or check ``dataset.json`` for ``config``; refuse a folder made from another config."""
    out = Path(out)
    existing = read_dataset_json(out)
    fingerprint = config.fingerprint()
    if existing is not None and existing.get("fingerprint") != fingerprint:
        raise InputError("output", f"{str(out)!r}, a dataset made from a different config "
                         f"(fingerprint {str(existing.get('fingerprint'))[:12]} != {fingerprint[:12]})",
                         "the folder of a dataset made from this config, or a new folder",
                         "Use another -o, or delete the folder. Only 'samples' may change between runs.")
    if existing is not None and existing.get("sample_name_width", config.name_width) != config.name_width:
        raise InputError("samples", config.samples, f"a count whose sample names keep {existing['sample_name_width']} digits",
                         "Generate the larger dataset into a new folder.")
    _refuse_shrinking(out, config.samples)
    info = {"schema": DATASET_SCHEMA, "schema_version": DATASET_SCHEMA_VERSION, "name": config.name,
            "fingerprint": fingerprint, "samples": config.samples, "sample_name_width": config.name_width,
            "master_seed": config.seed, "config": config.raw, "config_file": config.config_file,
            "capssim": __version__}
    if existing != info:
        atomic_write_json(out / DATASET_JSON, info)
    return info


def _refuse_shrinking(out: Path, samples: int) -> None:
    """Refuse a ``samples`` count below a finished sample's index.

    ``dataset.json``, the manifest, ``samples/`` and the loader must agree on the samples, and
    finished samples may have cost hours of rendering: a lower count is refused rather than
    deleting them. A count that only drops unfinished samples is accepted.
    """
    beyond = sorted(i for i in read_manifest(out / MANIFEST).records if i >= samples)
    if beyond:
        raise InputError("samples", samples, f"at least {beyond[-1] + 1}: samples {_show_indices(beyond)} of "
                         f"{str(out)!r} are already finished",
                         f"Set samples: {beyond[-1] + 1} or more, generate the smaller dataset into a new folder, "
                         "or load a subset with CaptureDataset(..., indices=...).")


def _show_indices(indices: list[int]) -> str:
    return ", ".join(map(str, indices[:5])) + (f" ... ({len(indices)} in all)" if len(indices) > 5 else "")


def is_sample_name(name: str) -> bool:
    return name.isdigit()


def is_leftover_name(name: str) -> bool:
    """Temporary/old folders of ``atomic_directory``: ``.NAME.tmp-XXXX``, ``.NAME.old-PID``."""
    return name.startswith(".") and (".tmp-" in name or ".old-" in name)
