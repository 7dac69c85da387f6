"""LPIPS (AlexNet variant), only with network weights the user supplies locally.

Reference: Zhang et al., "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric", CVPR 2018 (LPIPS v0.1). The paper's Table 1 scores the four polarizer RGB images
with it. capssim never downloads weights: pass ``--lpips-weights PATH`` where PATH is a
file, or a folder of files, holding together

* the AlexNet feature weights in torchvision's key layout (``features.0.weight`` ...
  ``features.10.bias``; e.g. torchvision's ``alexnet-owt-7be5be79.pth``), and
* the LPIPS linear heads (``lin0.model.1.weight`` ... ``lin4.model.1.weight``; e.g.
  ``weights/v0.1/alex.pth`` of the ``lpips`` package).

The network is re-implemented here in plain torch (no torchvision needed). Inputs are the
linear [0, 1] values as stored, clipped to [0, 1] and mapped to [-1, 1], then through
LPIPS's fixed scaling layer. Without reference weights in this environment, the numerical
agreement with the ``lpips`` package is not tested here (the architecture and the
normalization are; see tests/test_eval_lpips.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from capssim.errors import InputError

_SHIFT = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
_SCALE = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
#: AlexNet conv layers (index in torchvision's ``features``): out channels, kernel, stride, padding
_CONVS = {0: (3, 64, 11, 4, 2), 3: (64, 192, 5, 1, 2), 6: (192, 384, 3, 1, 1), 8: (384, 256, 3, 1, 1),
          10: (256, 256, 3, 1, 1)}
_TAP_CHANNELS = (64, 192, 384, 256, 256)


class LPIPS(nn.Module):
    """LPIPS-Alex distance; build with :meth:`from_path`."""

    def __init__(self):
        super().__init__()
        self.convs = nn.ModuleDict({str(i): nn.Conv2d(cin, cout, k, stride=s, padding=p)
                                    for i, (cin, cout, k, s, p) in _CONVS.items()})
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in _TAP_CHANNELS])

    @classmethod
    def from_path(cls, path: str | Path, *, device: str | torch.device = "cpu") -> "LPIPS":
        path = Path(path)
        files = sorted(path.glob("*.pth")) + sorted(path.glob("*.pt")) if path.is_dir() else [path]
        if not files or not all(f.is_file() for f in files):
            raise InputError("lpips-weights", str(path), "a .pth file or a folder of .pth files",
                             "capssim never downloads weights; see docs: guides/scoring.md, 'Metrics' (LPIPS).")
        state: dict[str, torch.Tensor] = {}
        for f in files:
            try:
                loaded = torch.load(f, map_location="cpu", weights_only=True)
            except Exception as exc:  # corrupt or not a torch file
                why = exc.strerror if isinstance(exc, OSError) and exc.strerror else "not a torch weights file"
                raise InputError("--lpips-weights", f"unreadable {f} ({why})", "a torch state dict (.pth) of LPIPS",
                                 "Copy the weights file again; see docs: guides/scoring.md, 'Metrics' (LPIPS).") from None
            if isinstance(loaded, dict) and "state_dict" in loaded:
                loaded = loaded["state_dict"]
            if not isinstance(loaded, dict):
                raise InputError("lpips-weights", f"{f} holding {type(loaded).__name__}", "a torch state dict")
            state.update({k.replace("module.", ""): v for k, v in loaded.items() if isinstance(v, torch.Tensor)})
        model = cls()
        mapped = {}
        missing = []
        for i in _CONVS:
            for part in ("weight", "bias"):
                key = f"features.{i}.{part}"
                if key in state:
                    mapped[f"convs.{i}.{part}"] = state[key]
                else:
                    missing.append(key)
        for k in range(5):
            key = f"lin{k}.model.1.weight"
            if key in state:
                mapped[f"lins.{k}.weight"] = state[key]
            else:
                missing.append(key)
        if missing:
            raise InputError("lpips-weights", f"{path} without {', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}",
                             "AlexNet features.* weights and LPIPS lin0..lin4 heads",
                             "Supply torchvision's alexnet checkpoint and lpips' v0.1 alex.pth (a folder with both).")
        try:
            model.load_state_dict(mapped)
        except RuntimeError as exc:
            raise InputError("lpips-weights", f"tensors of the wrong shape ({exc})", "AlexNet/LPIPS v0.1 weights") from exc
        return model.to(device).eval()

    def _features(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = []
        x = F.relu(self.convs["0"](x))
        taps.append(x)
        x = F.relu(self.convs["3"](F.max_pool2d(x, 3, 2)))
        taps.append(x)
        x = F.relu(self.convs["6"](F.max_pool2d(x, 3, 2)))
        taps.append(x)
        x = F.relu(self.convs["8"](x))
        taps.append(x)
        x = F.relu(self.convs["10"](x))
        taps.append(x)
        return taps

    @torch.no_grad()
    def distance(self, estimate_rgb, reference_rgb) -> float:
        """LPIPS between two ``(3, H, W)`` images on [0, 1] (H, W >= 32)."""
        dev = next(self.parameters()).device

        def prep(a):
            t = torch.as_tensor(np.asarray(a, dtype=np.float32), device=dev)
            if t.ndim != 3 or t.shape[0] != 3:
                raise InputError("image", f"shape {tuple(t.shape)}", "an RGB image (3, H, W)")
            if min(t.shape[1:]) < 32:
                raise InputError("image", f"size {t.shape[1]}x{t.shape[2]}", "at least 32x32 pixels for LPIPS")
            t = t.clamp(0, 1)[None] * 2 - 1
            return (t - _SHIFT.to(dev)) / _SCALE.to(dev)

        fa, fb = self._features(prep(estimate_rgb)), self._features(prep(reference_rgb))
        total = 0.0
        for lin, a, b in zip(self.lins, fa, fb):
            na = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total += float(lin((na - nb) ** 2).mean())
        return total
