"""Score reconstructions.

Two ways to the same numbers. In memory, `capssim.eval.metrics.score(estimate, gt)` returns
PSNR and SSIM per channel and their means, the DoLP PSNR, the AoP error and more (the guide
[Scoring](../guides/scoring.md) defines each one and its conventions). On disk, as
`capssim evaluate` does: write the capture and each method's result into a capture folder, then
`capssim.eval.evaluate.evaluate_capture(folder)` scores every ``recon/*.tiff`` and writes
``metrics.json``.

The methods here are the fast baselines, on a 64 px capture with white Gaussian noise
(sigma 0.01); ``true_warps=True`` gives the camera-array method the exact warps stored in the
capture, so no registration runs.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture, write_reconstruction
from capssim.conventions import CHANNEL_NAMES
from capssim.eval.evaluate import evaluate_capture
from capssim.eval.metrics import score
from capssim.eval.synthetic import texture_scene
from capssim.reconstruct import reconstruct
from capssim.simulate import simulate_capture

gt, _ = texture_scene(64, seed=2)
capture = simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=0)
methods = ["caps-naive", "dofp-bilinear", "dofp-eari"]

print(f"{'method':<14} {'PSNR (dB)':>9} {'SSIM':>6} {'DoLP PSNR':>9} {'AoP RMSE (deg)':>14}")
results = {}
for method in methods:
    output, record = reconstruct(capture, method, true_warps=True)
    s = score(output.image, capture.gt)
    results[method] = (output.image, record, s)
    print(f"{method:<14} {s['psnr_mean']:9.2f} {s['ssim_mean']:6.3f} {s['dolp_psnr']:9.2f} {s['aop_rmse_deg']:14.2f}")

with tempfile.TemporaryDirectory() as tmp:
    folder = write_capture(Path(tmp) / "capture", capture)
    for method, (image, record, _) in results.items():
        write_reconstruction(folder, method, image, record)    # recon/METHOD.tiff and recon/METHOD.json
    on_disk = evaluate_capture(folder)                         # also writes folder/metrics.json
    for method in methods:
        same = on_disk["methods"][method]["metrics"]["psnr_mean"]
        print(f"evaluate_capture: {method} PSNR {same:.2f} dB (in memory {results[method][2]['psnr_mean']:.2f})")

fig, ax = plt.subplots(figsize=(10, 3.5))
width = 0.8 / len(methods)
for i, method in enumerate(methods):
    psnrs = [results[method][2]["psnr"][name] for name in CHANNEL_NAMES]
    ax.bar(np.arange(12) + (i - 1) * width, psnrs, width, label=method)
ax.set_xticks(np.arange(12), CHANNEL_NAMES, rotation=45)
ax.set_ylabel("PSNR (dB)")
ax.set_ylim(bottom=15)
ax.set_title("PSNR of each of the 12 channels (polarizer angle - colour)")
ax.legend()
plt.show()
