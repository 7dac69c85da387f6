"""Synthetic benchmark datasets at scale: deterministic, resumable, on Dask.

* :mod:`capssim.dataset.config`: the YAML config, validated (errors name the key path), and the
  parameters of each sample, drawn deterministically from the master seed and the sample index.
* :mod:`capssim.dataset.generate`: :func:`generate_dataset` on a local or existing Dask cluster.
* :mod:`capssim.dataset.manifest`: the dataset folder, its JSONL manifest and lock.
* :mod:`capssim.dataset.verify`: :func:`verify_dataset` checks every sample against the manifest.
* :mod:`capssim.dataset.torch`: :class:`CaptureDataset`, a PyTorch ``Dataset`` with aligned crops.

The CLI is ``capssim dataset CONFIG -o OUT`` (docs: guides/datasets.md).
"""

from capssim.dataset.config import DatasetConfig, load_config, parse_config
from capssim.dataset.generate import generate_dataset
from capssim.dataset.verify import verify_dataset
from capssim.files.schema import ConfigError

__all__ = ["ConfigError", "DatasetConfig", "generate_dataset", "load_config", "parse_config", "verify_dataset"]
