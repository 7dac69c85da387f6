"""Design maps (``capssim bench map``): where a camera array beats a DoFP sensor, by how much, and why.

:mod:`.spec` (the YAML file and its checks), :mod:`.cells` (a cell's capture and cases), :mod:`.sweep` (the run, on
the suites' case runner), :mod:`.margins` (best array method minus best DoFP method per cell), :mod:`.theory` (the
conditioning of the apertures' stacked sampling, eq. 5-8), :mod:`.plots` and :mod:`.report` (``report.md``, heatmaps).
"""
