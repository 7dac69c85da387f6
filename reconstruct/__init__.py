"""Reconstruction methods of capssim: the paper's CAPS algorithm, its ablations and baselines.

Use :func:`reconstruct` (the dispatcher) or :func:`run_method` (reads and writes a capture
folder). Methods register themselves in :mod:`reconstruct.registry`.
"""

from reconstruct.registry import (MethodOutput, RunContext, available_methods, get_method, reconstruct,
                                  register_method, resolve_device, run_method)

__all__ = ["MethodOutput", "RunContext", "available_methods", "get_method", "reconstruct", "register_method",
           "resolve_device", "run_method"]
