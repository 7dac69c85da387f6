"""Error bars: which pixels of a reconstruction to trust.

``--uncertainty N`` (``uncertainty=N`` in Python) gives every reconstruction calibrated error bars: a parametric
bootstrap draws ``N`` new captures from the reconstruction through the camera's forward model and noise, reconstructs
each one (warm-started), and takes their spread; a scale fitted on development captures where the truth is known
(split conformal prediction, ``capssim bench uncertainty``) turns the spread into 90 % intervals. The intervals come
per channel and for S0, DoLP and AoP (guide: [Error bars](../guides/reconstruction.md#error-bars)).

How to read them: DoLP's interval widens where S0 is dark (a DoLP is a ratio over S0), and AoP is only worth
reading where its interval is narrow, so it is drawn there only. The bars cover the noise and, through the
calibration, the typical bias of the method on scenes like the development ones; they do not cover a model error
outside the simulator (parallax on a 3-D scene, an array the capture does not describe). The 90 % holds pooled
over development scenes; one scene may lie well off it (this dark-banded texture does: see the printed coverage,
and the per-scene range on the [results page](../results/uncertainty.md)).
"""

import matplotlib.pyplot as plt
import numpy as np

from capssim.camera.sensor import make_sensor
from capssim.eval.synthetic import texture_scene
from capssim.eval.uncertainty_scores import score_uncertainty
from capssim.reconstruct import reconstruct
from capssim.simulate import simulate_capture

gt, _ = texture_scene(64, seed=3)
gt[:, :, :16] *= 0.08                                             # a dark band on the left: S0 near 0
capture = simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=0)

out, record = reconstruct(capture, "dofp-igri2", uncertainty=8)   # a DoFP method: fast, and calibrated
maps = out.uncertainty                                            # std (12, H, W), interval90 (2, 12, H, W), stokes
print("calibration:", record["uncertainty"]["calibration"]["name"],
      f"({record['uncertainty']['replicates']} replicates, {record['uncertainty']['time_s']:.2f} s)")
scores = score_uncertainty(out.image, gt, maps)                   # against the truth, as capssim evaluate does
for group, score in scores.to_dict(with_curves=False)["groups"].items():
    print(f"{group:5s} 90 % interval covers {score['coverage']:.2f} of the scored pixels, "
          f"mean width {score['mean_width']:.3g} ({score['width_unit']})")

plane = dict(zip(record["uncertainty"]["stokes_layout"], maps.stokes))   # e.g. plane["DoLP lower G"]
green = out.image[1::3]                                           # I0, I45, I90, I135 of the green channel
s0, s1, s2 = green.sum(axis=0) / 2, green[0] - green[2], green[1] - green[3]
dolp = np.hypot(s1, s2) / np.maximum(s0, 1e-6)
aop_width = plane["AoP upper G"] - plane["AoP lower G"]
aop_shown = np.where(aop_width < 20.0, np.mod(plane["AoP lower G"] + aop_width / 2, 180), np.nan)
panels = [(s0, "S0 (green)", "gray", 0, None), (np.clip(dolp, 0, 1), "DoLP", "magma", 0, 1),
          (plane["DoLP upper G"] - plane["DoLP lower G"], "DoLP 90 % interval width", "viridis", 0, None),
          (aop_shown, "AoP where its interval < 20 deg", "hsv", 0, 180)]
fig, axes = plt.subplots(1, 4, figsize=(14, 3.6))
for ax, (image, title, cmap, vmin, vmax) in zip(axes, panels):
    ax.set_facecolor("0.5")                                       # grey: AoP not drawn
    shown = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax)
    ax.set_title(title, fontsize=10)
    ax.set_axis_off()
    fig.colorbar(shown, ax=ax, fraction=0.046)
fig.suptitle("dofp-igri2 with --uncertainty 8: the dark band (left) has wide DoLP bars and no AoP")
plt.show()
