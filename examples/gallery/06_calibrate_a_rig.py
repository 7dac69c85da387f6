"""Calibrate an imperfect rig.

A real array's polarizers sit a little off their nominal angles, with a finite extinction
ratio, and its cameras differ in gain and vignetting. This example simulates the calibration
captures of such a rig (`capssim.dataset.calibration_captures.make_calibration_captures`: a
flat field, a polarizer sweep, a geometry target and a Siemens star), measures the rig from them
with `capssim.reconstruct.calibration.calibrate_captures` (which writes a ``capssim-rig`` file) and
compares the measurement with the truth. The guide
[Real rigs and calibration](../guides/calibration.md) describes the procedure with a real rig and
each estimator. Sizes here are small (64 px, 8 sweep angles) to keep the example fast; the
guide's accuracy figures are for 256 px.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from capssim.camera.rig import RigModel
from capssim.camera.sensor import make_sensor
from capssim.conventions import POLARIZER_ANGLES_DEG
from capssim.dataset.calibration_captures import make_calibration_captures
from capssim.reconstruct.calibration import calibrate_captures

truth = RigModel.preset("realistic", seed=3)                   # angle offsets, extinction, gains, vignetting

with tempfile.TemporaryDirectory() as tmp:
    index = make_calibration_captures(Path(tmp) / "cal", rig=truth, size=64, polarizer_angles=8, seed=0,
                                      sensor=make_sensor("gaussian", sigma=0.01))
    print("calibration captures:", ", ".join(c["folder"] for c in index["captures"]))
    measured = calibrate_captures([Path(tmp) / "cal"], Path(tmp) / "calibration.json")
    print("measured:", ", ".join(measured.calibrated))

est = measured.rig
print(f"\n{'aperture':<9} {'angle true':>10} {'measured':>9} {'ER (G) true':>11} {'measured':>9} "
      f"{'gain true':>9} {'measured':>9}")
for n, nominal in enumerate(POLARIZER_ANGLES_DEG):
    print(f"{n:<9} {nominal + truth.angle_offsets_deg[n]:10.3f} {nominal + est.angle_offsets_deg[n]:9.3f} "
          f"{truth.extinction_ratio[n][1]:11.1f} {est.extinction_ratio[n][1]:9.1f} "
          f"{truth.gain[n]:9.4f} {est.gain[n]:9.4f}")
error = np.max(np.abs(est.angle_offsets_deg - truth.angle_offsets_deg))
print(f"\nlargest polarizer angle error: {error:.3f} deg")

fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
x = np.arange(4)
axes[0].bar(x - 0.2, truth.angle_offsets_deg, 0.4, label="true")
axes[0].bar(x + 0.2, est.angle_offsets_deg, 0.4, label="measured")
axes[0].set_xticks(x, [f"{a} deg" for a in POLARIZER_ANGLES_DEG])
axes[0].set_ylabel("polarizer angle offset (deg)")
axes[0].legend()
flat_true, flat_est = truth.flat_field((32, 32)), est.flat_field((32, 32))
axes[1].plot(flat_true[0, 16], label="aperture 0, true")
axes[1].plot(flat_est[0, 16], "--", label="aperture 0, measured")
axes[1].set_xlabel("column (raw pixels), middle row")
axes[1].set_ylabel("relative response (gain x vignetting)")
axes[1].legend()
fig.suptitle("A 'realistic' rig: truth against calibration")
plt.tight_layout()
plt.show()
