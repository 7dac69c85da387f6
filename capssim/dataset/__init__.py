"""Synthetic benchmark datasets at scale: deterministic, resumable, on Dask.

* :mod:`capssim.dataset.config`: the YAML config, validated (errors name the key path), and the
  parameters of each sample, drawn deterministically from the master seed and the sample index.
* :mod:`capssim.dataset.generate`: :func:`generate_dataset` on a local or existing Dask cluster.
* :mod:`capssim.dataset.manifest`: the dataset folder, its JSONL manifest and lock.
* :mod:`capssim.dataset.verify`: :func:`verify_dataset` checks every sample against the manifest.
* :mod:`capssim.dataset.torch`: :class:`CaptureDataset`, a PyTorch ``Dataset`` with aligned crops.

The CLI is ``capssim dataset CONFIG -o OUT`` (README "Datasets").
"""

from capssim.dataset.config import DatasetConfig, load_config, parse_config
from capssim.dataset.schema import ConfigError

__all__ = ["ConfigError", "DatasetConfig", "generate_dataset", "load_config", "parse_config", "verify_dataset"]


def __getattr__(name):  # keep `import capssim.dataset` light: Dask and torch load on use
    if name == "generate_dataset":
        from capssim.dataset.generate import generate_dataset

        return generate_dataset
    if name == "verify_dataset":
        from capssim.dataset.verify import verify_dataset

        return verify_dataset
    raise AttributeError(name)
