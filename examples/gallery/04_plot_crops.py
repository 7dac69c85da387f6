"""Plot intensity, DoLP and AoP crops.

The three views that the benchmark reports draw for every method (the paper's fig. 7 style),
built here with `capssim.visualize`: the unpolarized intensity ``S0/2`` (sRGB display, one
white level for every panel), the DoLP of R, G and B as an RGB image, and the AoP as a hue
(0-180 deg round the colour circle) whose saturation is the DoLP. The scene is a polarization
Siemens star (`capssim.eval.synthetic.star_scene`): constant intensity, a DoLP of 0.8 and an AoP
that turns with the angle round the centre, so all of its detail is in the polarization. The
array method ``caps`` (5 ADMM iterations, exact warps) is set against the DoFP camera's
``dofp-eari``; both see the same scene with the same noise and pixel count.
"""

import matplotlib.pyplot as plt

from capssim.camera.sensor import make_sensor
from capssim.eval.synthetic import star_scene
from capssim.reconstruct import reconstruct
from capssim.simulate import simulate_capture
from capssim.visualize import aop_image, aop_legend, display_white, dolp_image, intensity_image

gt, info = star_scene(64, cycles=12, polarization=True)
capture = simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=0)
images = {"ground truth": gt}
for method, options in [("caps", {"iterations": 5}), ("dofp-eari", {})]:
    output, record = reconstruct(capture, method, true_warps=True, **options)
    images[method] = output.image
    print(f"{method}: {record['wall_time_s']:.2f} s")

white = display_white(gt)
views = [("intensity S0/2", lambda im: intensity_image(im, white=white)),
         ("DoLP (R, G, B)", lambda im: dolp_image(im, dolp_max=1.0)),
         ("AoP (hue), DoLP (saturation)", lambda im: aop_image(im, dolp_max=1.0))]
fig, axes = plt.subplots(len(views), len(images) + 1, figsize=(10, 7.5),
                         gridspec_kw={"width_ratios": [1] * len(images) + [0.45]})
for row, (view, draw) in enumerate(views):
    for col, (name, image) in enumerate(images.items()):
        axes[row, col].imshow(draw(image), interpolation="nearest")
        axes[row, col].set_title(name if row == 0 else "")
        axes[row, col].set_ylabel(view)
        axes[row, col].set_xticks([])
        axes[row, col].set_yticks([])
    axes[row, -1].set_axis_off()
axes[2, -1].imshow(aop_legend(64, dolp_max=1.0))
axes[2, -1].set_title("AoP key", fontsize=9)
fig.suptitle("A 64 px polarization star: what the array and a DoFP camera resolve")
plt.tight_layout()
plt.show()
