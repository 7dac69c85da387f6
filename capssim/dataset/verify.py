"""``capssim dataset --verify OUT``: check every sample against the manifest.

For every sample listed in ``manifest.jsonl``: its folder exists; every file the manifest lists
exists with the listed size and sha256; ``meta.json`` is a valid capture description of that
sample (its ``dataset.index``). Also reported: samples 0..N-1 with no manifest line (the dataset
is incomplete: rerun the generation), folders without a manifest line or temporary folders
(leftovers a rerun removes), invalid manifest lines, and files the manifest does not list
(``recon/`` results written later are expected there and are not an error).
"""

from __future__ import annotations

import json
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from capssim.captures.capture import read_meta
from capssim.dataset.manifest import (
    MANIFEST,
    SAMPLES_DIR,
    is_leftover_name,
    is_sample_name,
    read_dataset_json,
    read_manifest,
)
from capssim.errors import CaptureFormatError, InputError
from capssim.files.imageio import file_sha256

log = logging.getLogger(__name__)


@dataclass
class VerifyReport:
    out: Path
    total: int
    checked: int = 0
    corrupt: dict[int, list[str]] = field(default_factory=dict)
    missing: list[int] = field(default_factory=list)
    leftovers: list[str] = field(default_factory=list)
    manifest_problems: list[str] = field(default_factory=list)
    extra_files: dict[int, list[str]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """No corruption and nothing missing."""
        return not self.corrupt and not self.missing and not self.manifest_problems

    def summary(self) -> str:
        lines = [f"{self.out}: {self.checked} samples checked, {len(self.corrupt)} corrupt, "
                 f"{len(self.missing)} of {self.total} missing"]
        for index, problems in sorted(self.corrupt.items()):
            for p in problems:
                lines.append(f"  CORRUPT sample {index}: {p}")
        if self.missing:
            shown = ", ".join(map(str, self.missing[:20])) + (" ..." if len(self.missing) > 20 else "")
            lines.append(f"  MISSING samples (no manifest line): {shown}. Rerun the generation to finish them.")
        for p in self.manifest_problems:
            lines.append(f"  MANIFEST: {p}")
        if self.leftovers:
            lines.append(f"  note: {len(self.leftovers)} leftover folders (no manifest line or temporary); "
                         "a rerun of the generation removes them")
        if self.extra_files:
            n = sum(len(v) for v in self.extra_files.values())
            lines.append(f"  note: {n} files not in the manifest (e.g. recon/ results) in {len(self.extra_files)} samples")
        lines.append("OK" if self.ok else "FAILED")
        return "\n".join(lines)


def _check_sample(samples_dir: Path, record: dict) -> tuple[list[str], list[str]]:
    """(problems, extra files) of one manifest record."""
    folder = samples_dir / record["name"]
    if not folder.is_dir():
        return [f"folder {folder} is missing"], []
    problems: list[str] = []
    listed = record["files"]
    for name, expected in sorted(listed.items()):
        path = folder / name
        if not path.is_file():
            problems.append(f"{name} is missing")
            continue
        size = path.stat().st_size
        if size != expected.get("bytes"):
            problems.append(f"{name} has {size} bytes; the manifest says {expected.get('bytes')}")
            continue
        digest = file_sha256(path)
        if digest != expected.get("sha256"):
            problems.append(f"{name} sha256 {digest[:12]}... differs from the manifest's {str(expected.get('sha256'))[:12]}...")
    if not problems:
        try:
            meta = read_meta(folder)
            index = (meta.get("dataset") or {}).get("index")
            if index != record["index"]:
                problems.append(f"meta.json belongs to sample {index}, not {record['index']}")
        except (CaptureFormatError, InputError, json.JSONDecodeError) as exc:
            problems.append(f"meta.json: {exc}")
    extra = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                   if p.is_file() and p.relative_to(folder).as_posix() not in listed)
    return problems, extra


def verify_dataset(out, *, threads: int = 4, progress: Callable[[int, int], None] | None = None) -> VerifyReport:
    """Check the dataset in folder ``out`` against its manifest; see the module docstring."""
    out = Path(out)
    if not out.is_dir():
        raise InputError("dataset", str(out), "an existing dataset folder (made by 'capssim dataset CONFIG -o OUT')")
    info = read_dataset_json(out)
    if info is None:
        raise InputError("dataset", f"{str(out)!r} without dataset.json", "a dataset folder made by 'capssim dataset'")
    total = int(info["samples"])
    report = VerifyReport(out=out, total=total)
    contents = read_manifest(out / MANIFEST)
    if contents.bad_lines:
        report.manifest_problems.append(f"invalid lines {contents.bad_lines[:10]} in {MANIFEST}")
    if contents.torn_tail:
        report.leftovers.append(f"{MANIFEST}: torn last line")
    samples_dir = out / SAMPLES_DIR
    records = dict(sorted(contents.records.items()))
    report.missing = [i for i in range(total) if i not in records]
    listed_names = {r["name"] for r in records.values()}
    if samples_dir.is_dir():
        for entry in sorted(samples_dir.iterdir()):
            if is_leftover_name(entry.name) or (is_sample_name(entry.name) and entry.name not in listed_names):
                report.leftovers.append(entry.name)
    done = 0
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        for index, (problems, extra) in zip(records, pool.map(lambda r: _check_sample(samples_dir, r), records.values())):
            done += 1
            if problems:
                report.corrupt[index] = problems
            if extra:
                report.extra_files[index] = extra
            if progress is not None:
                progress(done, len(records))
    report.checked = done
    log.info("verified %s: %d checked, %d corrupt, %d missing", out, done, len(report.corrupt), len(report.missing))
    return report
