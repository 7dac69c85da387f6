"""Benchmark of the DoFP demosaicking baselines against published-style numbers (``capssim bench dofp``).

Protocol (the one of published colour-polarization demosaicking tables, e.g. Morimatsu et al.
ICIP 2020): the full 1024x1024 ground truth, a noise-free DoFP mosaic sampled directly from it
(no optical blur: the published comparisons sample the mosaic from the ground-truth images
without a PSF, so any blur would make the numbers incomparable), Sony layout
``[[90, 45], [135, 0]]``. The mosaic is the capture's ``dofp_raw`` of ``capssim simulate --noise
none --psf-sigma-hr-px 0``, built here in memory by the same code.

Scores: the Tokyo Tech / EARI columns of :func:`capssim.eval.metrics.tokyotech_scores` (their
MATLAB border crop), with the wall time of each method (minimum over ``repeats``).
"""

from __future__ import annotations

import time
from pathlib import Path

from capssim.camera.psf import PSF
from capssim.camera.sensor import make_sensor
from capssim.captures.capture import Capture
from capssim.conventions import DEFAULT_DOFP_LAYOUT
from capssim.errors import InputError
from capssim.files.imageio import read_gt_scene
from capssim.reconstruct.registry import reconstruct
from capssim.simulate import prepare_ground_truth, simulate_capture

from ..metrics import tokyotech_scores
from .provenance import shared_data_dir

DEFAULT_SCENES = ("qiu-kettle", "qiu-cellphonecases")
DEFAULT_METHODS = ("dofp-bilinear", "dofp-eari")

#: dofp-eari's numerical choices, scored with ``eari_variants``: label -> method options
EARI_VARIANTS = {
    "default (float32, eps 1e-10, weight floor 0.01/255^2)": {},
    "float64, eps 1e-32 (reference code's eps)": {"precision": "float64", "eps": 1e-32},
    "weight floor 0.01 (reference code on [0, 1] data)": {"weight_floor": 0.01},
}

#: table columns: (row key, header, format)
COLUMNS = [("scene", "scene", "{}"), ("method", "method", "{}"), ("psnr_0", "0", "{:.2f}"),
           ("psnr_45", "45", "{:.2f}"), ("psnr_90", "90", "{:.2f}"), ("psnr_135", "135", "{:.2f}"),
           ("psnr_s0", "S0", "{:.2f}"), ("psnr_s1", "S1", "{:.2f}"), ("psnr_s2", "S2", "{:.2f}"),
           ("psnr_dolp", "DoLP", "{:.2f}"), ("aop_rmse_deg", "AoP RMSE", "{:.2f}"),
           ("aop_mae_deg", "AoP MAE", "{:.2f}"), ("time_s", "time s", "{:.2f}")]


def default_gt_root() -> Path:
    """The folder holding the ground-truth scene folders: ``SHARED_DATA/gt``."""
    return shared_data_dir() / "gt"


#: the Gaussian PSF std (HR px) of the published DoFP protocol (Tokyo Tech, EARI): no optical blur, unlike the
#: camera set-up's default (:data:`capssim.camera.psf.DEFAULT_SIGMA_HR_PX`)
PUBLISHED_PSF_SIGMA_HR_PX = 0.0


def make_capture(gt_dir: Path, *, layout: str = DEFAULT_DOFP_LAYOUT, psf_sigma_hr_px: float = PUBLISHED_PSF_SIGMA_HR_PX) -> Capture:
    """Noise-free DoFP (and CAPS) capture of a ground-truth folder, as ``capssim simulate`` makes it."""
    image, source = read_gt_scene(gt_dir)
    image, info = prepare_ground_truth(image)
    source.update(info)
    return simulate_capture(image, make_sensor("none"), seed=0, psf=PSF.gaussian(psf_sigma_hr_px), dofp_layout=layout,
                            source=source)


def run_one(capture: Capture, method: str, *, device: str, repeats: int, options: dict | None = None):
    """Reconstruct ``repeats`` times; return the last ``(12, H, W)`` image, the minimum wall time (s) and its record."""
    best, out, record = float("inf"), None, None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out, record = reconstruct(capture, method, device=device, **(options or {}))
        best = min(best, time.perf_counter() - t0)
    return out.image, best, record


def run_dofp_benchmark(scenes=DEFAULT_SCENES, methods=DEFAULT_METHODS, *, gt_root: Path | None = None,
                       layout: str = DEFAULT_DOFP_LAYOUT, psf_sigma_hr_px: float = PUBLISHED_PSF_SIGMA_HR_PX, border: int | None = None, device: str = "cpu",
                       repeats: int = 1, eari_variants: bool = False) -> list[dict]:
    """One row per (scene, method): the Tokyo Tech columns and ``time_s``.

    ``border``: the metrics' crop (default: the Tokyo Tech 15 px); ``eari_variants``: score
    ``dofp-eari`` under each of :data:`EARI_VARIANTS` instead of ``methods``.
    """
    root = Path(gt_root) if gt_root is not None else default_gt_root()
    rows = []
    for scene in scenes:
        gt_dir = root / scene
        if not gt_dir.is_dir():
            raise InputError("scene", str(gt_dir), "a ground-truth scene folder", "Give the folder holding it: capssim bench dofp GT_ROOT.")
        capture = make_capture(gt_dir, layout=layout, psf_sigma_hr_px=psf_sigma_hr_px)
        runs = [(m, m, {}) for m in methods]
        if eari_variants:
            runs = [("dofp-eari", f"dofp-eari {label}", opts) for label, opts in EARI_VARIANTS.items()]
        for method, label, opts in runs:
            image, seconds, _ = run_one(capture, method, device=device, repeats=repeats, options=opts)
            scores = tokyotech_scores(image, capture.gt, border=border)
            rows.append({"scene": scene, "method": label, **scores, "time_s": seconds})
    return rows


def format_table(rows: list[dict]) -> str:
    """Aligned text table of :func:`run_dofp_benchmark`'s rows (``-`` for an undefined value)."""
    head = [h for _, h, _ in COLUMNS]
    cells = [["-" if r[k] is None else fmt.format(r[k]) for k, _, fmt in COLUMNS] for r in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(head)]

    def line(vals):
        return "  ".join(v.rjust(w) if i > 1 else v.ljust(w) for i, (v, w) in enumerate(zip(vals, widths)))

    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(c) for c in cells])
