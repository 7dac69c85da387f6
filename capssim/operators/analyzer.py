"""Channel-mixing operators: the polarization analyzer of each aperture (paper eq. 9, P_n).

A linear polarizer at angle ``a`` with extinction ratio ``ER = T_max / T_min`` reads

    I_meas(a) = (ER * I(a) + I(a + 90)) / (ER + 1)

from the 12-channel image, which for ``ER = inf`` is the channel ``I(a)`` itself and for
unpolarized light gives ``S0/2`` whatever ``ER`` is (transmission loss is folded into the
exposure).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from capssim.conventions import N_CHANNELS, POLARIZER_ANGLES_DEG, channel_index
from capssim.errors import InputError
from capssim.operators.base import LinearOperator


class ChannelMix(LinearOperator):
    """``y[o, h, w] = sum_i M[o, i] x[i, h, w]``; input ``(Cin, H, W)``, output ``(*out_lead, H, W)``.

    ``out_lead`` reshapes the ``Cout`` output channels (for example ``(4, 3)`` for four
    apertures of three colours). The adjoint applies ``M^T``.
    """

    name = "channel_mix"

    def __init__(self, matrix, height: int, width: int, *, out_lead: Sequence[int] | None = None):
        m = torch.as_tensor(np.asarray(matrix, dtype=np.float64))
        if m.ndim != 2:
            raise InputError("matrix", f"shape {tuple(m.shape)}", "a 2-D (Cout, Cin) matrix")
        lead = tuple(out_lead) if out_lead is not None else (m.shape[0],)
        if int(np.prod(lead)) != m.shape[0]:
            raise InputError("out_lead", lead, f"a shape with {m.shape[0]} elements")
        super().__init__((m.shape[1], height, width), (*lead, height, width))
        self.matrix = m

    def _forward(self, x):
        m = self._const("m", self.matrix, x)
        return torch.einsum("oi,ihw->ohw", m, x).reshape(self.output_shape)

    def _adjoint(self, y):
        m = self._const("m", self.matrix, y)
        yy = y.reshape(m.shape[0], *self.input_shape[1:])
        return torch.einsum("oi,ohw->ihw", m, yy)


def analyzer_matrix(angles_deg: Sequence[float] = POLARIZER_ANGLES_DEG, *,
                    extinction_ratio: float | None = None) -> np.ndarray:
    """``(3*len(angles), 12)`` matrix: RGB seen through each polarizer angle.

    Angles must be among (0, 45, 90, 135) deg, the angles the 12-channel image holds.
    ``extinction_ratio=None`` (or inf) is an ideal polarizer.
    """
    if extinction_ratio is not None and not (extinction_ratio >= 1.0):
        raise InputError("extinction_ratio", extinction_ratio, "a number >= 1 (T_max/T_min), or None for ideal",
                         "Typical wire-grid polarizers have 100-1000.")
    ideal = extinction_ratio is None or np.isinf(extinction_ratio)
    t_par = 1.0 if ideal else extinction_ratio / (extinction_ratio + 1.0)
    t_perp = 0.0 if ideal else 1.0 / (extinction_ratio + 1.0)
    rows = []
    for a in angles_deg:
        a = int(round(a)) % 180
        if a not in POLARIZER_ANGLES_DEG:
            raise InputError("angles_deg", a, f"angles among {POLARIZER_ANGLES_DEG} degrees")
        for k in range(3):
            row = np.zeros(N_CHANNELS)
            row[channel_index(a, k)] += t_par
            row[channel_index((a + 90) % 180, k)] += t_perp
            rows.append(row)
    return np.stack(rows)


class Analyzer(ChannelMix):
    """12-channel image ``(12, H, W)`` -> RGB per aperture ``(N, 3, H, W)`` (paper P_n)."""

    name = "analyzer"

    def __init__(self, height: int, width: int, *, angles_deg: Sequence[float] = POLARIZER_ANGLES_DEG,
                 extinction_ratio: float | None = None):
        matrix = analyzer_matrix(angles_deg, extinction_ratio=extinction_ratio)
        super().__init__(matrix, height, width, out_lead=(len(angles_deg), 3))
        self.angles_deg = tuple(angles_deg)
        self.extinction_ratio = extinction_ratio


class ChannelSelect(LinearOperator):
    """``y[m] = x[channels[m]]``: picks (and may repeat) channels; adjoint sums back."""

    name = "channel_select"

    def __init__(self, channels: Sequence[int], n_channels: int, height: int, width: int):
        idx = [int(c) for c in channels]
        if min(idx) < 0 or max(idx) >= n_channels:
            raise InputError("channels", idx, f"indices in [0, {n_channels})")
        super().__init__((n_channels, height, width), (len(idx), height, width))
        self.index = torch.as_tensor(idx, dtype=torch.int64)

    def _forward(self, x):
        return x.index_select(0, self._const("i", self.index, x))

    def _adjoint(self, y):
        out = y.new_zeros(self.input_shape)
        return out.index_add_(0, self._const("i", self.index, y), y)
