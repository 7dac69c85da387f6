"""Parameter distributions of a dataset config, and their deterministic per-sample draws.

A config value is either a constant (any YAML scalar or list) or a one-key mapping:

==============================================  ==============================================
``{const: VALUE}``                              VALUE (use it for a constant mapping)
``{choice: [a, b, c]}``                         one of the values, uniformly
``{choice: [a, b], weights: [3, 1]}``           one of the values, with these relative weights
``{uniform: [lo, hi]}``                         real number, uniform on [lo, hi)
``{log_uniform: [lo, hi]}``                     real number, log-uniform on [lo, hi), 0 < lo
``{int_uniform: [lo, hi]}``                     integer, uniform on lo..hi (both included)
``{normal: [mean, std], clip: [lo, hi]}``       real number, Gaussian, clipped (clip optional
                                                only where the key accepts any real)
==============================================  ==============================================

Every value a distribution can draw is checked against the key's own rule when the config is
read, so a draw never fails later. A distribution that can draw nothing (``choice: []``,
``uniform: [2, 1]``, all weights 0) is an error naming the key.

Determinism: the draw for key path ``K`` of sample ``i`` uses its own generator
``numpy.random.default_rng(SeedSequence(master_seed, spawn_key=(i, crc32(K))))``
(:func:`key_rng`). It depends on nothing else: not on the worker, the order of samples, the
order of keys in the YAML file, or which other keys exist.
"""

from __future__ import annotations

import copy
import math
import zlib
from dataclasses import dataclass, field

import numpy as np

from capssim.files.schema import ConfigError, Integer, Nullable, Number, Spec, join, show

DISTRIBUTION_KINDS = ("const", "choice", "uniform", "log_uniform", "int_uniform", "normal")
_MODIFIERS = {"choice": ("weights",), "normal": ("clip",)}


def key_rng(master_seed: int, index: int, key_path: str) -> np.random.Generator:
    """The generator of key ``key_path`` for sample ``index`` (see the module docstring)."""
    spawn_key = (int(index), zlib.crc32(key_path.encode("utf-8")))
    return np.random.default_rng(np.random.SeedSequence(int(master_seed), spawn_key=spawn_key))


def _py(value):
    """numpy scalars -> Python scalars (JSON-able, repr-stable)."""
    if isinstance(value, np.generic):
        return value.item()
    return value


class Dist:
    """Base class of a parsed distribution."""

    def draw(self, rng: np.random.Generator):  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> str:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def is_constant(self) -> bool:
        return False


@dataclass
class Const(Dist):
    value: object

    def draw(self, rng):
        return copy.deepcopy(self.value)

    def describe(self):
        return show(self.value)

    @property
    def is_constant(self):
        return True


@dataclass
class Choice(Dist):
    values: list
    weights: list[float] | None = None
    _p: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        if self.weights is not None:
            w = np.asarray(self.weights, dtype=np.float64)
            self._p = w / w.sum()

    def draw(self, rng):
        k = int(rng.choice(len(self.values), p=self._p))
        return copy.deepcopy(self.values[k])

    def describe(self):
        text = f"choice {show(self.values)}"
        return text + (f" weights {self.weights}" if self.weights else "")


@dataclass
class Uniform(Dist):
    low: float
    high: float

    def draw(self, rng):
        return float(rng.uniform(self.low, self.high))

    def describe(self):
        return f"uniform [{self.low}, {self.high})"


@dataclass
class LogUniform(Dist):
    low: float
    high: float

    def draw(self, rng):
        return float(math.exp(rng.uniform(math.log(self.low), math.log(self.high))))

    def describe(self):
        return f"log-uniform [{self.low}, {self.high})"


@dataclass
class IntUniform(Dist):
    low: int
    high: int

    def draw(self, rng):
        return int(rng.integers(self.low, self.high + 1))

    def describe(self):
        return f"integer uniform {self.low}..{self.high}"


@dataclass
class Normal(Dist):
    mean: float
    std: float
    clip: tuple[float, float] | None = None

    def draw(self, rng):
        v = float(rng.normal(self.mean, self.std))
        if self.clip is not None:
            v = float(min(max(v, self.clip[0]), self.clip[1]))
        return v

    def describe(self):
        return f"normal(mean {self.mean}, std {self.std})" + (f" clipped to {list(self.clip)}" if self.clip else "")


def _bare(inner: Spec) -> Spec:
    return inner.inner if isinstance(inner, Nullable) else inner


def _pair(value, path: str, what: str) -> tuple:
    if not isinstance(value, list) or len(value) != 2:
        raise ConfigError(path, show(value), f"a list of two numbers [{what}]")
    return tuple(value)


def _finite_number(value, path):
    return Number().check(value, path)


def _bounded(inner: Spec) -> bool:
    bare = _bare(inner)
    return isinstance(bare, (Number, Integer)) and (bare.minimum is not None or bare.maximum is not None)


def parse_distribution(value, inner: Spec, path: str) -> Dist:
    """Parse the config value at ``path`` into a :class:`Dist` whose draws all satisfy ``inner``."""
    if not isinstance(value, dict):
        return Const(inner.check(value, path))
    kinds = [k for k in value if k in DISTRIBUTION_KINDS]
    if len(kinds) != 1:
        raise ConfigError(path, show(value),
                          f"{inner.description}, or a distribution: a mapping with exactly one of "
                          f"{', '.join(DISTRIBUTION_KINDS)}",
                          "Write a constant mapping as {const: {...}}." if not kinds else None)
    kind = kinds[0]
    allowed = (kind, *_MODIFIERS.get(kind, ()))
    for key in value:
        if key not in allowed:
            raise ConfigError(join(path, str(key)), "an unknown key",
                              f"one of {', '.join(allowed)} in a {kind} distribution")
    if kind == "const":
        return Const(inner.check(value[kind], join(path, kind)))
    if kind == "choice":
        return _parse_choice(value, inner, path)
    if kind in ("uniform", "log_uniform", "int_uniform"):
        return _parse_range(value, kind, inner, path)
    return _parse_normal(value, inner, path)


def _parse_choice(value: dict, inner: Spec, path: str) -> Choice:
    """``{choice: [values], weights: [w]}``: values each of ``inner``, weights >= 0 with a positive sum."""
    arg, kpath = value["choice"], join(path, "choice")
    if not isinstance(arg, list):
        raise ConfigError(kpath, show(arg), "a list of values to choose from")
    if not arg:
        raise ConfigError(kpath, "an empty list", "at least one value to draw from",
                          "A distribution with no values cannot draw any sample.")
    values = [inner.check(v, join(kpath, i)) for i, v in enumerate(arg)]
    weights = value.get("weights")
    if weights is not None:
        wpath = join(path, "weights")
        if not isinstance(weights, list) or len(weights) != len(values):
            raise ConfigError(wpath, show(weights), f"a list of {len(values)} weights, one per choice")
        weights = [Number(minimum=0).check(w, join(wpath, i)) for i, w in enumerate(weights)]
        if sum(weights) <= 0:
            raise ConfigError(wpath, show(weights), "weights with a positive sum",
                              "A distribution whose weights are all 0 cannot draw any sample.")
    return Choice(values, weights)


def _parse_range(value: dict, kind: str, inner: Spec, path: str) -> Dist:
    """``{uniform | log_uniform | int_uniform: [low, high]}`` whose every draw satisfies ``inner``."""
    arg, kpath, bare = value[kind], join(path, kind), _bare(inner)
    low, high = _pair(arg, kpath, "low, high")
    if kind == "int_uniform":
        low, high = Integer().check(low, join(kpath, 0)), Integer().check(high, join(kpath, 1))
    else:
        low, high = _finite_number(low, join(kpath, 0)), _finite_number(high, join(kpath, 1))
    if low > high:
        raise ConfigError(kpath, show(arg), "low <= high",
                          "An empty range is a distribution with no samples; swap the bounds.")
    if kind == "log_uniform" and low <= 0:
        raise ConfigError(kpath, show(arg), "0 < low <= high for a log-uniform distribution")
    if isinstance(bare, Integer):
        if kind != "int_uniform":
            raise ConfigError(kpath, show(arg), f"{bare.description}; a real-valued {kind} draws non-integers",
                              "Use int_uniform or choice.")
        if bare.multiple_of and bare.multiple_of > 1 and low != high:
            raise ConfigError(kpath, show(arg), f"{bare.description}; int_uniform would draw other integers",
                              "Use choice: [..] with the sizes you want.")
    # every value in [low, high] is allowed iff both ends are (the rules are intervals)
    inner.check(low, join(kpath, 0))
    inner.check(high, join(kpath, 1))
    return {"uniform": Uniform, "log_uniform": LogUniform, "int_uniform": IntUniform}[kind](low, high)


def _parse_normal(value: dict, inner: Spec, path: str) -> Normal:
    """``{normal: [mean, std] | {mean, std}, clip: [low, high]}``; a bounded ``inner`` needs the clip."""
    arg, kpath, bare = value["normal"], join(path, "normal"), _bare(inner)
    if isinstance(arg, dict):
        unknown = set(arg) - {"mean", "std"}
        if unknown or len(arg) != 2:
            raise ConfigError(kpath, show(arg), "[mean, std] or {mean: M, std: S}")
        mean, std = arg["mean"], arg["std"]
    else:
        mean, std = _pair(arg, kpath, "mean, std")
    mean, std = _finite_number(mean, join(kpath, 0)), Number(minimum=0).check(std, join(kpath, 1))
    if isinstance(bare, Integer):
        raise ConfigError(kpath, show(arg), f"{bare.description}; a normal distribution draws non-integers",
                          "Use int_uniform or choice.")
    clip = value.get("clip")
    if clip is not None:
        cpath = join(path, "clip")
        lo, hi = _pair(clip, cpath, "low, high")
        lo, hi = _finite_number(lo, join(cpath, 0)), _finite_number(hi, join(cpath, 1))
        if lo > hi:
            raise ConfigError(cpath, show(clip), "low <= high",
                              "An empty clip range is a distribution with no samples.")
        inner.check(lo, join(cpath, 0))
        inner.check(hi, join(cpath, 1))
        clip = (lo, hi)
    elif _bounded(inner):
        raise ConfigError(kpath, show(arg), f"a distribution that only draws {bare.description}",
                          "A normal distribution is unbounded: add clip: [low, high].")
    return Normal(mean, std, clip)


class Distribution(Spec):
    """Schema spec (:mod:`capssim.files.schema`): a constant value of ``inner`` or a distribution over such values."""

    def __init__(self, inner: Spec):
        self.inner = inner
        self.description = f"{inner.description}, or a distribution over such values"

    def check(self, value, path):
        return parse_distribution(value, self.inner, path)


def draw_tree(tree, master_seed: int, index: int, path: str):
    """Draw every :class:`Dist` in a nested dict/list ``tree`` for sample ``index``."""
    if isinstance(tree, Dist):
        return _py(tree.draw(key_rng(master_seed, index, path)))
    if isinstance(tree, dict):
        return {k: draw_tree(v, master_seed, index, join(path, k)) for k, v in tree.items()}
    if isinstance(tree, list):
        return [draw_tree(v, master_seed, index, join(path, i)) for i, v in enumerate(tree)]
    return tree
