"""Simulate a capture.

The paper's synthetic protocol (section 5.2) from a 12-channel ground truth: random sub-pixel
poses of apertures 1-3, PSF blur, 2x2 pixel integration, RGGB Bayer sampling and white Gaussian
sensor noise (paper eq. 9). The same scene is also seen by a DoFP colour-polarization camera
with the same pixel count. The capture is written to a folder (the format of the guide
[Captures and conventions](../guides/captures.md)) and read back.

The ground truth is `capssim.eval.synthetic.texture_scene`, a smooth random texture with
spatially varying DoLP and AoP (no data files needed): ``(12, 64, 64)`` float32, channel
``c = 3*p + k`` with ``p`` over the polarizer angles (0, 45, 90, 135) deg and ``k`` over (R, G, B).
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_capture, write_capture
from capssim.eval.synthetic import texture_scene
from capssim.simulate import simulate_capture

gt, info = texture_scene(64, seed=0)                           # (12, 2H, 2W) on [0, 1]
sensor = make_sensor("gaussian", sigma=0.01)                   # sigma: fraction of full scale
capture = simulate_capture(gt, sensor, seed=0)                 # poses and noise drawn from seed 0

print("ground truth  ", gt.shape, gt.dtype)
print("CAPS raw      ", capture.caps_raw.shape, "(4 apertures, RGGB, H x W)")
print("DoFP raw      ", capture.dofp_raw.shape, "(one colour-polarization mosaic, 2H x 2W)")
print("16 sub-images ", capture.lr_images()[0].shape, "(m = 4*n + q, n the aperture, q over R, G1, G2, B)")

with tempfile.TemporaryDirectory() as tmp:
    folder = write_capture(Path(tmp) / "texture", capture)
    print("files         ", sorted(p.name for p in folder.iterdir()))
    again = read_capture(folder)                               # validates meta.json and every TIFF
    print("HR shape      ", again.hr_shape, " raw shape", again.raw_shape)
    for n, pose in enumerate(again.meta["poses"]["apertures"]):
        dx, dy = pose["shift_xy_px"]
        print(f"aperture {n}: shift ({dx:+.3f}, {dy:+.3f}) HR px, rotation {pose['rotation_deg']:+.3f} deg, "
              f"scale {pose['scale']:.4f}")

fig, axes = plt.subplots(1, 5, figsize=(14, 3.4))
for n, ax in enumerate(axes[:4]):
    ax.imshow(capture.caps_float()[n], cmap="gray", vmin=0, vmax=1)
    ax.set_title(f"aperture {n}\npolarizer {45 * n} deg", fontsize=10)
axes[4].imshow(capture.dofp_float(), cmap="gray", vmin=0, vmax=1)
axes[4].set_title("DoFP mosaic\n(2x the pixels)", fontsize=10)
for ax in axes:
    ax.set_axis_off()
fig.suptitle("Raw frames of one simulated shot (RGGB mosaics, linear)")
plt.show()
