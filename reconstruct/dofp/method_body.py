"""The registered-method body shared by the DoFP demosaicking baselines: options in, array function, record out."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from capssim.errors import InputError, UnknownNameError

from ..run_context import MethodOutput

#: the range ``(low, high]`` of each float option: the regularizers are on [0, 1] data; below 1e-30
#: ``1 / weight_floor`` overflows float32; ``bayer_sigma`` is a Gaussian std in pixels (below 0.01 its taps underflow)
PARAMETER_RANGES = {"eps": (0.0, 1.0), "weight_floor": (1e-30, 1.0), "edge_eps": (0.0, 1.0), "bayer_sigma": (0.01, 16.0)}


def reject_unknown_options(leftover: dict, known: Sequence[str]) -> None:
    """Raise :class:`~capssim.errors.UnknownNameError` when ``leftover`` holds an option not in ``known``."""

    for key in leftover:
        raise UnknownNameError("option", str(key), list(known) or ["(this method takes no options)"])


def run_dofp_method(capture, context, demosaic, defaults: dict):
    """The registered-method body shared by the residual-interpolation DoFP methods.

    Reads the options ``precision`` (``float32`` | ``float64``) and the float parameters named
    in ``defaults`` from ``context.options``, demosaicks ``capture.dofp_float()`` with
    ``demosaic(mosaic, *, layout, dtype, timer, **params)`` on ``context.device`` and returns
    the :class:`~capssim.reconstruct.registry.MethodOutput` with the parameters used.
    """

    opts = dict(context.options)
    precision = opts.pop("precision", "float32")
    if precision not in ("float32", "float64"):
        raise InputError("precision", precision, "float32 or float64")
    params = {}
    for key, default in defaults.items():
        raw = opts.pop(key, default)
        try:
            params[key] = float(raw)
        except (TypeError, ValueError):
            raise InputError(key, raw, "a number", f"Pass e.g. -p {key}={default}.") from None
        low, high = PARAMETER_RANGES.get(key, (-np.inf, np.inf))
        if not (np.isfinite(params[key]) and low < params[key] <= high):
            raise InputError(key, raw, f"a finite number in ({low:g}, {high:g}]", f"Pass e.g. -p {key}={default}.")
    reject_unknown_options(opts, ["precision", *defaults])
    with context.timer.stage("load"):
        mosaic = torch.from_numpy(capture.dofp_float()).to(context.device)
        n_saturated = int(capture.dofp_saturated().sum())
    image = demosaic(mosaic, layout=capture.dofp_layout, dtype=getattr(torch, precision), timer=context.timer,
                     **params)
    with context.timer.stage("to_host"):
        image = image.to("cpu", torch.float32).numpy()
    return MethodOutput(image=image, params={"layout": [list(r) for r in capture.dofp_layout], "precision": precision,
                                             **params},
                        extra={"n_saturated_pixels": n_saturated,
                               "saturation_handling": "none (interpolation uses saturated samples as they are)"})
