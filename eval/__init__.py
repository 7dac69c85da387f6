"""Scoring of capssim results: metrics, Siemens-star MTF, benchmark runner and reports."""

if __name__ != "capssim.eval":
    # The folder eval/ is installed as capssim.eval; a bare `import eval` would shadow other packages.
    raise ImportError(f"{__name__!r} is not an import name of capssim: the folder eval/ is the package "
                      "capssim.eval; write `import capssim.eval` (after `pip install -e .`)")
