"""Linear operators with hand-written exact adjoints (deepinv style).

Every operator has a fixed ``input_shape`` and ``output_shape``, a ``forward`` and an
``adjoint``. Composition (``A @ B``) and stacking are operators too, and every one of
them passes :func:`adjointness_error` (the dot-product test) in float64.

Noise, clipping and quantization are never part of an operator: they live in
:mod:`capssim.camera.sensor` and are applied after it.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from capssim.errors import InputError


class LinearOperator:
    """Base class: ``y = A x`` with ``x.shape == input_shape``, ``y.shape == output_shape``.

    Subclasses implement ``_forward`` and ``_adjoint``. Tensors may live on any device
    and have any floating dtype; operator constants are cast lazily and cached.
    """

    input_shape: tuple[int, ...]
    output_shape: tuple[int, ...]
    name = "operator"

    def __init__(self, input_shape: Sequence[int], output_shape: Sequence[int]):
        self.input_shape = tuple(int(s) for s in input_shape)
        self.output_shape = tuple(int(s) for s in output_shape)
        self._cast_cache: dict = {}

    # -- public API -------------------------------------------------------------------
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _check_shape(self, "x", x, self.input_shape)
        return self._forward(x)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        _check_shape(self, "y", y, self.output_shape)
        return self._adjoint(y)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward(x)

    def __matmul__(self, other: "LinearOperator") -> "Composition":
        return Composition([other, self])

    @property
    def T(self) -> "Adjoint":
        return Adjoint(self)

    def describe(self) -> str:
        return f"{self.name}: {self.input_shape} -> {self.output_shape}"

    # -- helpers for subclasses --------------------------------------------------------
    def _const(self, key: str, tensor: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """``tensor`` on ``like``'s device, and in its dtype if floating; cached."""
        dtype = like.dtype if tensor.is_floating_point() else tensor.dtype
        cache_key = (key, dtype, like.device)
        cached = self._cast_cache.get(cache_key)
        if cached is None:
            cached = tensor.to(device=like.device, dtype=dtype)
            self._cast_cache[cache_key] = cached
        return cached

    def _forward(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def _adjoint(self, y: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError


def _check_shape(op: LinearOperator, arg: str, t: torch.Tensor, shape: tuple[int, ...]) -> None:
    if not isinstance(t, torch.Tensor):
        raise InputError(f"{op.name}.{arg}", type(t).__name__, "a torch.Tensor",
                         "Convert with torch.as_tensor(array).")
    if tuple(t.shape) != shape:
        raise InputError(f"{op.name}.{arg}", f"shape {tuple(t.shape)}", f"shape {shape}")
    if not t.is_floating_point():
        raise InputError(f"{op.name}.{arg}", f"dtype {t.dtype}", "a floating dtype (float32 or float64)",
                         "Convert with .float() or .double().")


class Adjoint(LinearOperator):
    """The adjoint ``A^T`` of an operator, as an operator."""

    def __init__(self, op: LinearOperator):
        super().__init__(op.output_shape, op.input_shape)
        self.op = op
        self.name = f"{op.name}^T"

    def _forward(self, x):
        return self.op._adjoint(x)

    def _adjoint(self, y):
        return self.op._forward(y)


class Composition(LinearOperator):
    """``ops[-1] @ ... @ ops[0]``: applies ``ops[0]`` first."""

    def __init__(self, ops: Sequence[LinearOperator], name: str = "composition"):
        flat: list[LinearOperator] = []
        for op in ops:
            flat.extend(op.ops if isinstance(op, Composition) else [op])
        for first, second in zip(flat[:-1], flat[1:]):
            if first.output_shape != second.input_shape:
                raise InputError(
                    "ops", f"{first.describe()} followed by {second.describe()}",
                    "each operator's output_shape equal to the next one's input_shape",
                )
        super().__init__(flat[0].input_shape, flat[-1].output_shape)
        self.ops = flat
        self.name = name

    def _forward(self, x):
        for op in self.ops:
            x = op._forward(x)
        return x

    def _adjoint(self, y):
        for op in reversed(self.ops):
            y = op._adjoint(y)
        return y

    def describe(self) -> str:
        inner = " -> ".join(op.name for op in self.ops)
        return f"{self.name} [{inner}]: {self.input_shape} -> {self.output_shape}"


class Stack(LinearOperator):
    """Vertical stack ``[A_1; ...; A_k]`` of operators sharing one input.

    The output is the flattened outputs concatenated, shape ``(sum of sizes,)``;
    :meth:`split` gives them back in their own shapes.
    """

    def __init__(self, ops: Sequence[LinearOperator], name: str = "stack"):
        shapes = {op.input_shape for op in ops}
        if len(shapes) != 1:
            raise InputError("ops", f"input shapes {sorted(shapes)}", "one common input_shape")
        self.ops = list(ops)
        self.sizes = [math.prod(op.output_shape) for op in ops]
        super().__init__(ops[0].input_shape, (sum(self.sizes),))
        self.name = name

    def split(self, y: torch.Tensor) -> list[torch.Tensor]:
        parts = torch.split(y, self.sizes)
        return [p.reshape(op.output_shape) for p, op in zip(parts, self.ops)]

    def _forward(self, x):
        return torch.cat([op._forward(x).reshape(-1) for op in self.ops])

    def _adjoint(self, y):
        out = None
        for part, op in zip(self.split(y), self.ops):
            contribution = op._adjoint(part)
            out = contribution if out is None else out + contribution
        return out


class Reshape(LinearOperator):
    """Reshape (a permutation-free relabelling); its adjoint is the inverse reshape."""

    name = "reshape"

    def __init__(self, input_shape: Sequence[int], output_shape: Sequence[int]):
        if math.prod(input_shape) != math.prod(output_shape):
            raise InputError("output_shape", tuple(output_shape), f"a shape with {math.prod(input_shape)} elements")
        super().__init__(input_shape, output_shape)

    def _forward(self, x):
        return x.reshape(self.output_shape)

    def _adjoint(self, y):
        return y.reshape(self.input_shape)


class Multiply(LinearOperator):
    """``y = w * x`` with fixed weights ``w`` of the operator's shape (diagonal, self-adjoint),
    e.g. a flat field (gain x vignetting) on the raw grid."""

    name = "multiply"

    def __init__(self, weights):
        w = torch.as_tensor(np.asarray(weights, dtype=np.float64))
        super().__init__(tuple(w.shape), tuple(w.shape))
        self.weights = w

    def _forward(self, x):
        return x * self._const("w", self.weights, x)

    def _adjoint(self, y):
        return y * self._const("w", self.weights, y)


def adjointness_error(op: LinearOperator, *, dtype=torch.float64, device=None, seed: int = 0) -> float:
    """Relative error of the dot-product test ``|<Ax, y> - <x, A^T y>| / (|A x| |y|)``.

    Exact adjoints give about 1e-15 in float64.
    """
    gen = torch.Generator(device="cpu").manual_seed(seed)
    x = torch.randn(op.input_shape, generator=gen, dtype=dtype).to(device or "cpu")
    y = torch.randn(op.output_shape, generator=gen, dtype=dtype).to(device or "cpu")
    ax = op.forward(x)
    aty = op.adjoint(y)
    lhs = torch.sum(ax * y)
    rhs = torch.sum(x * aty)
    scale = torch.linalg.vector_norm(ax) * torch.linalg.vector_norm(y)
    scale = max(float(scale), float(torch.linalg.vector_norm(x) * torch.linalg.vector_norm(aty)), 1e-300)
    return float(abs(lhs - rhs)) / scale


def operator_norm_estimate(op: LinearOperator, *, iterations: int = 30, dtype=torch.float64,
                           device=None, seed: int = 0) -> float:
    """Largest singular value of ``op`` by power iteration on ``A^T A``."""
    gen = torch.Generator(device="cpu").manual_seed(seed)
    x = torch.randn(op.input_shape, generator=gen, dtype=dtype).to(device or "cpu")
    x = x / torch.linalg.vector_norm(x)
    value = 0.0
    for _ in range(iterations):
        z = op.adjoint(op.forward(x))
        value = float(torch.linalg.vector_norm(z))
        if value == 0.0:
            return 0.0
        x = z / value
    return math.sqrt(value)
