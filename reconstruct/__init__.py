"""Reconstruction methods of capssim: the paper's CAPS algorithm, its ablations and baselines.

Use :func:`reconstruct` (the dispatcher) or :func:`run_method` (reads and writes a capture
folder). Methods register themselves in :mod:`capssim.reconstruct.registry`.
"""

if __name__ != "capssim.reconstruct":
    # The folder reconstruct/ is installed as capssim.reconstruct; a bare `import reconstruct` would shadow other packages.
    raise ImportError(f"{__name__!r} is not an import name of capssim: the folder reconstruct/ is the package "
                      "capssim.reconstruct; write `import capssim.reconstruct` (after `pip install -e .`)")

from .registry import (
    MethodOutput,
    RunContext,
    available_methods,
    get_method,
    reconstruct,
    register_method,
    resolve_device,
    run_method,
)

__all__ = ["MethodOutput", "RunContext", "available_methods", "get_method", "reconstruct", "register_method",
           "resolve_device", "run_method"]
