"""Error bars for any reconstruction: a parametric bootstrap through the forward model, calibrated by split
conformal prediction on simulated development captures (docs: guides/reconstruction.md, "Error bars").

- :mod:`.maps`: the arrays and files (``recon/METHOD.std.tiff``, ``.interval90.tiff``, ``.stokes-uncertainty.tiff``);
- :mod:`.bootstrap`: the bootstrap itself, on any estimator and on a capture;
- :mod:`.conformal`: the calibration file and its scale factors.
"""
