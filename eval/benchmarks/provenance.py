"""What a benchmark records next to its numbers: code fingerprints, the environment, peak memory.

* :func:`code_fingerprint`: sha256 of source files and shipped weights, the cache and resume keys of the
  suite runner (a changed renderer re-renders, a changed method re-runs its cases);
* :func:`option_file_hashes`: sha256 of the files a method's options name (a retrained ``weights`` file);
* :func:`environment`: versions, git revision, CPU and GPU, stored with every case;
* :class:`PeakMemory`: peak resident set size of this process while a block runs, sampled by a
  thread every 5 ms (and ``torch.cuda.max_memory_allocated`` on CUDA).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import importlib.metadata as md
import json
import os
import platform
import subprocess
import threading
from pathlib import Path

import numpy as np
import torch

from capssim.captures.capture import software_versions
from capssim.files.imageio import file_sha256

#: the repository: the folders capssim/, reconstruct/, eval/, scenes/
REPO_ROOT = Path(__file__).resolve().parents[2]


def shared_data_dir() -> Path:
    """``$CAPSSIM_SHARED_DATA`` or ``../shared/data`` next to the repository."""
    return Path(os.environ.get("CAPSSIM_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


def content_hash(obj) -> str:
    """sha256 hex digest of ``obj`` as sorted-key JSON (non-JSON values by ``str``)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


#: what a result depends on besides the source: the shipped weights and dictionaries (reconstruct/weights)
SHIPPED_MODEL_SUFFIXES = (".pt", ".npz")


def code_fingerprint(*parts: str) -> str:
    """sha256 (16 hex digits) of the source files and shipped model files under ``parts`` (paths relative to the
    repository), so that new weights rerun the cases they score, as a code change does.

    The command line, the plots' colour maps and the design calculator never change a result and
    are left out.
    """
    h = hashlib.sha256()
    for part in parts:
        base = REPO_ROOT / part
        files = [base] if base.is_file() else sorted(
            f for f in base.rglob("*") if f.suffix in (".py", *SHIPPED_MODEL_SUFFIXES) and f.is_file()
        ) if base.is_dir() else []
        for f in files:
            rel = f.relative_to(REPO_ROOT).as_posix()
            if rel.startswith("capssim/cli/") or rel in ("capssim/visualize.py", "capssim/camera/design.py"):
                continue
            h.update(rel.encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def option_file_hashes(options: dict | None) -> dict[str, str]:
    """``{option: sha256 of the file}`` for each option whose value names an existing file (a ``weights`` or a
    ``dictionary`` made by ``capssim train``), so that a file retrained in place reruns the cases that read it."""
    out = {}
    for key, value in sorted((options or {}).items()):
        path = Path(value) if isinstance(value, str) and value else None
        if path is not None and path.is_file():
            stat = path.stat()
            out[key] = _file_hash(str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    return out


@functools.lru_cache(maxsize=64)
def _file_hash(path: str, size: int, mtime_ns: int) -> str:
    """sha256 (16 hex digits) of a file's bytes, cached by path, size and modification time."""
    return file_sha256(path)[:16]


def json_default(o):
    """``json.dumps(default=...)`` for numpy scalars and arrays and paths."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def _git_revision() -> dict:
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, timeout=5)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO_ROOT,
                               capture_output=True, text=True, timeout=5)
        if rev.returncode == 0:
            return {"revision": rev.stdout.strip(), "dirty": bool(dirty.stdout.strip())}
    except (OSError, subprocess.SubprocessError):
        pass
    return {"revision": None, "dirty": None}


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment(device: str = "cpu") -> dict:
    """Versions, git revision, CPU/GPU: recorded with every case."""
    versions = software_versions()
    for pkg in ("scikit-image", "scipy", "opencv-contrib-python-headless"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    gpu = None
    if torch.cuda.is_available():
        gpu = torch.cuda.get_device_name(0)
    return {"versions": versions, "git": _git_revision(), "platform": platform.platform(), "cpu": _cpu_model(),
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(), "gpu": gpu, "device": device,
            "hostname": platform.node()}


def release_freed_memory() -> None:
    """Hand the C heap's freed pages back to the system (glibc ``malloc_trim``; a no-op elsewhere).

    Without it the RSS keeps what earlier work freed, a later block reuses it unseen, and its
    rise above the start (``peak_rss_delta_mb``) reads near 0 MB (dofp-bilinear after caps).
    """
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


class PeakMemory:
    """Peak RSS of this process while the block runs (sampled by a thread), in MB; freed heap released first."""

    def __init__(self, interval_s: float = 0.005, device: str = "cpu"):
        self.interval_s = interval_s
        self.device = device
        self.peak_mb = self.start_mb = float("nan")
        self.cuda_peak_mb = None

    def __enter__(self):
        import psutil

        self._proc = psutil.Process()
        release_freed_memory()
        self.start_mb = self.peak_mb = self._proc.memory_info().rss / 2**20
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        if self.device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        return self

    def _sample(self):
        while not self._stop.is_set():
            self.peak_mb = max(self.peak_mb, self._proc.memory_info().rss / 2**20)
            self._stop.wait(self.interval_s)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_mb = max(self.peak_mb, self._proc.memory_info().rss / 2**20)
        if self.device.startswith("cuda"):
            self.cuda_peak_mb = torch.cuda.max_memory_allocated() / 2**20
        return False
