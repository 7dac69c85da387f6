"""Benchmark your own method.

A method is any function that takes a capture (the object `capssim.reconstruct.reconstruct` takes) and
keyword options, and returns the `(12, 2H, 2W)` image (numpy or torch) or a `MethodOutput`. The decorator
`capssim.reconstruct.plugins.method` says what input it reads (`"caps"`, the camera array, or `"dofp"`) and
what to list; `capssim.reconstruct.plugins.add_method` registers it in this process, without installing
anything, and from then on it runs like a built-in method: in `reconstruct`, in suites, in the error budget
and in the regression check, its records marked `plugin`.

This one is `caps-naive` followed by an unsharp mask of the intensity (a strength option `amount`), scored
against `caps-naive` on a small synthetic suite. To ship it, put the function in a package and declare it
in that package's `pyproject.toml`; capssim finds it by itself, also in `capssim reconstruct --list` and
on Dask workers:

```toml
[project.entry-points."capssim.methods"]
naive-sharp = "my_package.methods:naive_sharp"
```

The [Methods guide](../guides/methods.md#bring-your-own-method-plug-ins) has the contract.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from scipy.ndimage import gaussian_filter

from capssim.eval.benchmarks.suite import load_suite, run_suite
from capssim.reconstruct import plugins, reconstruct


@plugins.method(input_kind="caps", description="caps-naive, then an unsharp mask of the intensity")
def naive_sharp(capture, *, amount=0.5):
    out, _ = reconstruct(capture, "caps-naive")              # the public API: any method is a building block
    image = out.image                                          # (12, 2H, 2W) float32, channel c = 3 p + k
    mean = image.reshape(4, 3, *image.shape[1:]).mean(axis=0)  # (3, 2H, 2W): the four analyzers' mean, per colour
    detail = mean - gaussian_filter(mean, sigma=(0, 1.0, 1.0))
    return np.clip(image + float(amount) * np.tile(detail, (4, 1, 1)), 0.0, 1.0)


plugins.add_method("naive-sharp", naive_sharp)                 # this process only; or the entry point above

SUITE = """
name: own-method
seeds: [0]
noise:
  - {name: gauss-0.01, noise: gaussian, sigma: 0.01}
methods:
  - caps-naive
  - naive-sharp
  - {name: naive-sharp, label: naive-sharp-1, options: {amount: 1.0}}
scenes:
  - {name: texture, source: synthetic, generator: texture, size: 48}
"""

with tempfile.TemporaryDirectory() as tmp:
    suite_file = Path(tmp) / "own.yaml"
    suite_file.write_text(SUITE)
    run = run_suite(load_suite(suite_file), Path(tmp) / "out", threads=1)
    for rec in run.records:
        print(f"{rec['method']:<14} {rec['status']:<3} PSNR {rec['metrics']['psnr_mean']:6.2f} dB  "
              f"SSIM {rec['metrics']['ssim_mean']:.4f}  plug-in: {rec.get('plugin', {}).get('entry_point', '-')}")

fig, ax = plt.subplots(figsize=(5, 3.2))
ax.bar([r["method"] for r in run.records], [r["metrics"]["psnr_mean"] for r in run.records], color="tab:blue")
ax.set_ylim(min(r["metrics"]["psnr_mean"] for r in run.records) - 1, None)
ax.set_ylabel("mean PSNR (dB)")
ax.set_title("A plug-in method against caps-naive")
fig.tight_layout()
plt.show()
