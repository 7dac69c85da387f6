"""Kernel-regression merge of the raw Bayer samples of the four apertures onto the HR grid (``array-kr``):
the gather of samples and their kernel sums (:mod:`.gather`), kernels steered by the structure tensor
(:mod:`.steering`) and the intensity-then-polarization merge (:mod:`.merge`). Reference: Wronski et al.,
"Handheld multi-frame super-resolution", ACM TOG 38(4) (SIGGRAPH 2019)."""
