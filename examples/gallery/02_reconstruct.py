"""Reconstruct a capture.

`capssim.reconstruct.reconstruct(capture, METHOD, ...)` runs one registered method on a capture
in memory and returns its output (``output.image``: ``(12, 2H, 2W)`` float32) and the record
that `capssim reconstruct` writes to ``recon/METHOD.json`` (options, parameters, wall time of
each stage). Here: the paper's method ``caps`` (with 5 ADMM iterations instead of the paper's
25, to keep the example fast), its camera-array baseline ``caps-naive`` and a DoFP baseline,
``dofp-eari``. The warps between the apertures are estimated from the data, as with a real
camera; ``true_warps=True`` would use the ones stored in the capture. Every method is listed,
with its reference, in the guide [Methods and baselines](../guides/methods.md).
"""

import matplotlib.pyplot as plt

from capssim.camera.sensor import make_sensor
from capssim.eval.synthetic import texture_scene
from capssim.reconstruct import available_methods, reconstruct
from capssim.simulate import simulate_capture
from capssim.visualize import display_white, intensity_image

gt, _ = texture_scene(64, seed=1)
capture = simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=0)
print("registered methods:", ", ".join(available_methods()))

outputs = {}
for method, options in [("caps", {"iterations": 5}), ("caps-naive", {}), ("dofp-eari", {})]:
    output, record = reconstruct(capture, method, **options)
    outputs[method] = output.image
    stages = ", ".join(f"{name} {t:.2f} s" for name, t in record["stages_s"].items())
    print(f"\n{method}: {output.image.shape} {output.image.dtype} in {record['wall_time_s']:.2f} s")
    print(f"  stages: {stages}")

white = display_white(gt)                                       # one display scale for every panel
fig, axes = plt.subplots(1, 4, figsize=(12, 3.4))
for ax, (name, image) in zip(axes, {"ground truth": gt, **outputs}.items()):
    ax.imshow(intensity_image(image, white=white))
    ax.set_title(name)
    ax.set_axis_off()
fig.suptitle("Unpolarized intensity S0/2 (sRGB display), 64 x 64 HR pixels from 4 x 32 x 32 raw pixels")
plt.show()
