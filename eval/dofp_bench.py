"""Benchmark of the DoFP demosaicking baselines against published-style numbers.

Run::

    python -m eval.dofp_bench                       # both Qiu scenes, dofp-bilinear and dofp-eari
    python -m eval.dofp_bench --methods dofp-bilinear dofp-eari dofp-igri2 --repeats 3
    python -m eval.dofp_bench --eari-variants       # cost of EARI's numerical choices

Protocol (the one of published colour-polarization demosaicking tables, e.g. Morimatsu et al.
ICIP 2020): the full 1024x1024 ground truth, a noise-free DoFP mosaic sampled directly from it
(no optical blur: ``psf none``; the published comparisons sample the mosaic from the ground-truth
images without a PSF, so any blur would make the numbers incomparable), Sony layout
``[[90, 45], [135, 0]]``. The mosaic is the capture's ``dofp_raw`` of ``capssim simulate --noise
none --psf-sigma 0``, built here in memory by the same code.

Scores: the Tokyo Tech / EARI definitions (:func:`tokyotech_scores`), printed as a table with
the wall time of each method (minimum over ``--repeats``).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
DEFAULT_GT_ROOT = REPO.parent / "shared" / "data" / "gt"
DEFAULT_SCENES = ("qiu-kettle", "qiu-cellphonecases")
DEFAULT_METHODS = ("dofp-bilinear", "dofp-eari")


# -- Tokyo Tech / EARI metric definitions --------------------------------------------------------
def _crop(x: np.ndarray, border: int) -> np.ndarray:
    return x[..., border:x.shape[-2] - border, border:x.shape[-1] - border] if border else x


def _psnr(estimate: np.ndarray, reference: np.ndarray, *, peak: float = 1.0) -> float:
    mse = float(np.mean((np.asarray(estimate, np.float64) - np.asarray(reference, np.float64)) ** 2))
    return float(10 * np.log10(peak * peak / max(mse, 1e-32)))


def _stokes_tokyotech(image12: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per colour ``(3, H, W)``: S0 as the mean of the four angles, S1 = I0 - I90, S2 = I45 - I135."""
    i = np.asarray(image12, np.float64).reshape(4, 3, *image12.shape[-2:])
    return i.mean(axis=0), i[0] - i[2], i[1] - i[3]


def tokyotech_scores(estimate: np.ndarray, gt: np.ndarray, *, border: int = 15) -> dict[str, float]:
    """Scores of a ``(12, H, W)`` estimate against ``gt`` as in the EARI / Tokyo Tech evaluation.

    * a ``border``-pixel frame is removed on every side;
    * ``psnr_<angle>``: CPSNR over R, G, B of each polarizer image, peak 1;
    * ``psnr_s0``: CPSNR of ``S0 = (I0 + I45 + I90 + I135) / 4`` per colour (the mean, i.e. half
      of capssim's ``S0``), peak 1;
    * ``psnr_s1``, ``psnr_s2``: CPSNR of ``(S + 1) / 2``;
    * ``psnr_dolp``: CPSNR of the per-colour DoLP ``sqrt(S1^2 + S2^2) / (I0 + I45 + I90 + I135) * 2``
      (capssim's DoLP), clipped to [0, 1], 0 where the intensity sum is <= 1e-12;
    * ``aop_rmse_deg``: RMSE over all pixels and colours of the per-colour AoP difference in
      degrees, wrapped to [-90, 90).
    """
    est = _crop(np.asarray(estimate, np.float64), border)
    ref = _crop(np.asarray(gt, np.float64), border)
    out: dict[str, float] = {}
    for p, angle in enumerate((0, 45, 90, 135)):
        out[f"psnr_{angle}"] = _psnr(est[3 * p:3 * p + 3], ref[3 * p:3 * p + 3])
    se, sr = _stokes_tokyotech(est), _stokes_tokyotech(ref)
    out["psnr_s0"] = _psnr(se[0], sr[0])
    out["psnr_s1"] = _psnr((se[1] + 1) / 2, (sr[1] + 1) / 2)
    out["psnr_s2"] = _psnr((se[2] + 1) / 2, (sr[2] + 1) / 2)

    def dolp(s):
        total = 4 * s[0]
        mag = np.sqrt(s[1] ** 2 + s[2] ** 2)
        return np.where(total > 1e-12, np.clip(2 * mag / np.where(total > 1e-12, total, 1.0), 0, 1), 0.0)

    def aop(s):
        return 0.5 * np.degrees(np.arctan2(s[2], s[1]))

    out["psnr_dolp"] = _psnr(dolp(se), dolp(sr))
    diff = (aop(se) - aop(sr) + 90.0) % 180.0 - 90.0
    out["aop_rmse_deg"] = float(np.sqrt(np.mean(diff ** 2)))
    return out


# -- running --------------------------------------------------------------------------------------
def make_capture(gt_dir: Path, *, layout: str = "sony", psf_sigma: float = 0.0):
    """Noise-free DoFP (and CAPS) capture of a ground-truth folder, as ``capssim simulate`` makes it."""
    from capssim.imageio import read_gt_scene
    from capssim.sensor import make_sensor
    from capssim.simulate import prepare_ground_truth, simulate_capture

    image, source = read_gt_scene(gt_dir)
    image, info = prepare_ground_truth(image)
    source.update(info)
    psf = {"type": "gaussian", "sigma_hr_px": psf_sigma} if psf_sigma > 0 else {"type": "none"}
    return simulate_capture(image, make_sensor("none"), seed=0, psf=psf, dofp_layout=layout, source=source)


def run_one(capture, method: str, *, device: str, repeats: int, options: dict | None = None):
    """Reconstruct ``repeats`` times; return the last output and the minimum wall time (s)."""
    from capssim.reconstruct.registry import reconstruct

    best, out, record = float("inf"), None, None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out, record = reconstruct(capture, method, device=device, **(options or {}))
        best = min(best, time.perf_counter() - t0)
    return out.image, best, record


def _format_table(rows: list[dict]) -> str:
    cols = [("scene", "{}"), ("method", "{}"), ("psnr_0", "{:.2f}"), ("psnr_45", "{:.2f}"), ("psnr_90", "{:.2f}"),
            ("psnr_135", "{:.2f}"), ("psnr_s0", "{:.2f}"), ("psnr_s1", "{:.2f}"), ("psnr_s2", "{:.2f}"),
            ("psnr_dolp", "{:.2f}"), ("aop_rmse_deg", "{:.2f}"), ("time_s", "{:.2f}")]
    head = ["scene", "method", "0", "45", "90", "135", "S0", "S1", "S2", "DoLP", "AoP RMSE", "time s"]
    cells = [[fmt.format(r[k]) for k, fmt in cols] for r in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(head)]
    def line(vals):
        return "  ".join(v.rjust(w) if i > 1 else v.ljust(w) for i, (v, w) in enumerate(zip(vals, widths)))
    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(c) for c in cells])


EARI_VARIANTS = {
    "default (float32, eps 1e-10, weight floor 0.01/255^2)": {},
    "float64, eps 1e-32 (reference code's eps)": {"precision": "float64", "eps": 1e-32},
    "weight floor 0.01 (reference code on [0, 1] data)": {"weight_floor": 0.01},
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m eval.dofp_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--gt-root", type=Path, default=DEFAULT_GT_ROOT, help="folder holding the scene folders")
    parser.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES))
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    parser.add_argument("--layout", default="sony", help="DoFP 2x2 polarizer cell")
    parser.add_argument("--psf-sigma", type=float, default=0.0, help="Gaussian PSF std, HR px (0: none, as published)")
    parser.add_argument("--border", type=int, default=15, help="border crop of the metrics")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=1, help="runs per method; the minimum time is reported")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--eari-variants", action="store_true", help="score dofp-eari under its numerical variants")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows to this JSON file")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import torch

    if args.threads is not None:
        torch.set_num_threads(args.threads)

    rows = []
    for scene in args.scenes:
        gt_dir = args.gt_root / scene
        if not gt_dir.is_dir():
            parser.error(f"scene folder {gt_dir} not found (see --gt-root)")
        capture = make_capture(gt_dir, layout=args.layout, psf_sigma=args.psf_sigma)
        runs = [(m, m, {}) for m in args.methods]
        if args.eari_variants:
            runs = [("dofp-eari", f"dofp-eari {label}", opts) for label, opts in EARI_VARIANTS.items()]
        for method, label, opts in runs:
            image, seconds, _ = run_one(capture, method, device=args.device, repeats=args.repeats, options=opts)
            scores = tokyotech_scores(image, capture.gt, border=args.border)
            rows.append({"scene": scene, "method": label, **scores, "time_s": seconds})
    print(f"DoFP demosaicking, noise-free, layout {args.layout}, PSF sigma {args.psf_sigma} HR px, "
          f"border crop {args.border} px; PSNR in dB (peak 1), AoP RMSE in degrees; "
          f"time: min of {args.repeats} run(s) on {args.device}, {torch.get_num_threads()} CPU thread(s)")
    print(_format_table(rows))
    if args.json is not None:
        from capssim.imageio import atomic_write_json

        atomic_write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
