"""A small schema validator for the files users write by hand: every error names the file and the key path.

Used by the dataset config, suite files, baselines, ``meta.json``, rig and calibration files and
training configs (one schema each, checked on load, before any work).

A schema is a tree of small spec objects (:class:`Integer`, :class:`Number`, :class:`String`,
:class:`Mapping`, :class:`Sequence`, ...). ``spec.check(value, path)`` returns the normalised
value or raises :class:`ConfigError` naming ``path`` (e.g. ``sources[1].size``), what it got,
what is valid and, where it helps, how to fix it.

Distributions are values too: a key whose spec is ``Distribution(Number(minimum=0))``
(:class:`capssim.dataset.distributions.Distribution`, built on these specs) accepts a constant
``0.01`` or ``{uniform: [0.001, 0.02]}``, and the validator checks that every value the
distribution can draw satisfies the inner spec.
"""

from __future__ import annotations

import difflib
import math
from typing import Any, Callable

from capssim.errors import InputError


class ConfigError(InputError):
    """A hand-written file is unreadable or invalid; ``key_path`` names the offending key.

    ``config_file`` is the file's path; ``kind`` says what the file is ("config", "suite",
    "baseline", "meta.json", ...) and is written before it in the message.
    """

    def __init__(self, key_path: str, received: object, valid: str, fix: str | None = None, *,
                 config_file: str | None = None, kind: str = "config"):
        self.key_path = key_path
        self.config_file = config_file
        self.kind = kind
        where = f"{kind} {config_file}" if config_file else kind
        argument = f"{where}, key {key_path!r}" if key_path else where  # repr: one line, whatever the key
        super().__init__(argument, received, valid, fix)


def join(path: str, key: str | int) -> str:
    """``join('a', 'b') == 'a.b'``, ``join('a', 3) == 'a[3]'``, ``join('', 'b') == 'b'``."""
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


def show(value: Any) -> str:
    """A short printable form of a config value for error messages."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


class Spec:
    """Base class: ``check(value, path)`` returns the normalised value or raises ConfigError."""

    description = "a value"

    def check(self, value, path: str):  # pragma: no cover - abstract
        raise NotImplementedError


class Anything(Spec):
    """Any YAML scalar or list (scene parameters are checked by the scene itself)."""

    description = "a YAML scalar or list"

    def check(self, value, path):
        if isinstance(value, dict):
            raise ConfigError(path, show(value), self.description,
                              "Write a constant mapping as {const: {...}}.")
        return value


class AnyMapping(Spec):
    """Any mapping (checked in detail later)."""

    def __init__(self, what: str = "a mapping"):
        self.description = what

    def check(self, value, path):
        if not isinstance(value, dict):
            raise ConfigError(path, show(value), f"{self.description} (key: value pairs)")
        return value


class Boolean(Spec):
    description = "true or false"

    def check(self, value, path):
        if not isinstance(value, bool):
            raise ConfigError(path, show(value), self.description)
        return value


class Number(Spec):
    """A finite real number, optionally bounded (``exclusive_minimum`` for > instead of >=)."""

    def __init__(self, *, minimum: float | None = None, maximum: float | None = None,
                 exclusive_minimum: bool = False):
        self.minimum, self.maximum, self.exclusive_minimum = minimum, maximum, exclusive_minimum
        parts = ["a finite number"]
        if minimum is not None:
            parts.append(f"{'>' if exclusive_minimum else '>='} {minimum}")
        if maximum is not None:
            parts.append(f"<= {maximum}")
        self.description = " ".join(parts)

    def check(self, value, path):
        if isinstance(value, str):  # PyYAML reads 1e-3 (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                raise ConfigError(path, show(value), self.description) from None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(path, show(value), self.description)
        value = float(value)
        low_bad = self.minimum is not None and (value <= self.minimum if self.exclusive_minimum else value < self.minimum)
        if low_bad or (self.maximum is not None and value > self.maximum):
            raise ConfigError(path, show(value), self.description)
        return value


class Integer(Spec):
    """An integer, optionally bounded and a multiple of ``multiple_of``."""

    def __init__(self, *, minimum: int | None = None, maximum: int | None = None, multiple_of: int | None = None):
        self.minimum, self.maximum, self.multiple_of = minimum, maximum, multiple_of
        parts = ["an integer"]
        if multiple_of:
            parts.append(f"multiple of {multiple_of}")
        if minimum is not None:
            parts.append(f">= {minimum}")
        if maximum is not None:
            parts.append(f"<= {maximum}")
        self.description = " ".join(parts[:1]) + (" " + ", ".join(parts[1:]) if parts[1:] else "")

    def check(self, value, path):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, show(value), self.description)
        if (self.minimum is not None and value < self.minimum) or (self.maximum is not None and value > self.maximum) \
                or (self.multiple_of and value % self.multiple_of):
            fix = None
            if self.multiple_of and value > 0 and value % self.multiple_of:
                fix = f"Try {max(self.minimum or 0, value - value % self.multiple_of)}."
            raise ConfigError(path, show(value), self.description, fix)
        return value


class String(Spec):
    """A string, optionally one of ``choices`` (a callable returning them is allowed)."""

    def __init__(self, *, choices: list[str] | Callable[[], list[str]] | None = None, kind: str = "name"):
        self.choices = choices
        self.kind = kind
        self.description = "a string"

    def _choices(self):
        return self.choices() if callable(self.choices) else self.choices

    def check(self, value, path):
        if not isinstance(value, str) or not value:
            raise ConfigError(path, show(value), "a non-empty string")
        choices = self._choices()
        if choices is not None and value not in choices:
            close = difflib.get_close_matches(value, choices, n=1)
            raise ConfigError(path, show(value), f"one of {', '.join(map(str, choices))}",
                              f"Did you mean {close[0]!r}?" if close else None)
        return value


class Custom(Spec):
    """A value checked by ``func(value) -> normalised`` that raises InputError on bad input."""

    def __init__(self, func: Callable[[Any], Any], description: str):
        self.func, self.description = func, description

    def check(self, value, path):
        try:
            return self.func(value)
        except InputError as exc:
            raise ConfigError(path, show(value), exc.valid, exc.fix) from None


class Nullable(Spec):
    """``null`` or a value of ``inner``."""

    def __init__(self, inner: Spec):
        self.inner = inner
        self.description = f"null or {inner.description}"

    def check(self, value, path):
        return None if value is None else self.inner.check(value, path)


class Sequence(Spec):
    """A list of ``item`` values: at least ``min_length``, or exactly one of ``lengths`` when given;
    with ``bare`` (a spec), a value that is not a list is checked by ``bare`` instead."""

    def __init__(self, item: Spec, *, min_length: int = 0, what: str = "items",
                 lengths: tuple[int, ...] | None = None, bare: Spec | None = None):
        self.item, self.min_length, self.what, self.lengths, self.bare = item, min_length, what, lengths, bare
        counts = "" if lengths is None else " or ".join(map(str, lengths)) + " "
        self.description = f"a list of {counts}{what}" + (f", or {bare.description}" if bare is not None else "")

    def check(self, value, path):
        if self.bare is not None and not isinstance(value, list):
            return self.bare.check(value, path)
        if not isinstance(value, list):
            raise ConfigError(path, show(value), self.description)
        if len(value) < self.min_length:
            raise ConfigError(path, f"{len(value)} {self.what}", f"at least {self.min_length} {self.what}")
        if self.lengths is not None and len(value) not in self.lengths:
            raise ConfigError(path, f"{len(value)} {self.what}", self.description)
        return [self.item.check(v, join(path, i)) for i, v in enumerate(value)]


class Mapping(Spec):
    """A mapping with known ``fields``; ``required`` keys must be present; unknown keys are errors
    unless ``extra`` (a spec for the values of any other key) is given."""

    def __init__(self, fields: dict[str, Spec] | None = None, *, required: tuple[str, ...] = (),
                 extra: Spec | None = None, what: str = "a mapping"):
        self.fields = fields or {}
        self.required = required
        self.extra = extra
        self.description = what

    def check(self, value, path):
        if value is None and not self.required:
            value = {}
        if not isinstance(value, dict):
            raise ConfigError(path, show(value), f"{self.description} (key: value pairs)")
        if self.extra is None:  # unknown keys first: a typo explains a missing key
            for key in value:
                if key not in self.fields:
                    close = difflib.get_close_matches(str(key), list(self.fields), n=1)
                    raise ConfigError(join(path, str(key)), "an unknown key", f"one of {', '.join(self.fields)}",
                                      f"Did you mean {close[0]!r}?" if close else None)
        for key in self.required:
            if key not in value:
                raise ConfigError(join(path, key), "nothing (missing key)", f"a value ({self.fields[key].description})")
        out = {}
        for key, item in value.items():
            key_path = join(path, str(key))
            if not isinstance(key, str):
                raise ConfigError(key_path, f"key {show(key)}", "a string key")
            spec = self.fields.get(key, self.extra)
            if spec is None:
                close = difflib.get_close_matches(key, list(self.fields), n=1)
                raise ConfigError(key_path, "an unknown key", f"one of {', '.join(self.fields)}",
                                  f"Did you mean {close[0]!r}?" if close else None)
            out[key] = spec.check(item, key_path)
        return out


# -- reading hand-written files -------------------------------------------------------------------
MAX_NESTING = 64
"""Deepest nesting of lists and mappings accepted in a hand-written file (JSON's and YAML's parsers
recurse per level; a file nested 200,000 deep would otherwise end in a RecursionError)."""


def _depth_ok(text: str) -> bool:
    """Whether the brackets of ``text`` nest at most :data:`MAX_NESTING` deep (a cheap upper bound:
    brackets inside strings count too, which only matters for files far past any real one)."""
    depth = worst = 0
    for char in text:
        if char in "[{":
            depth += 1
            worst = max(worst, depth)
        elif char in "]}":
            depth -= 1
    return worst <= MAX_NESTING


def read_text_file(path, *, kind: str, example: str | None = None) -> str:
    """The UTF-8 text of a hand-written file, or a :class:`ConfigError` naming ``kind`` and the path."""
    from pathlib import Path

    path = Path(path)
    hint = f" See {example}." if example else ""
    if not path.is_file():
        what = "a folder" if path.is_dir() else "no file"
        raise ConfigError("", f"{what} at {str(path)!r}", f"a readable {kind} file", f"Check the path.{hint}",
                          kind=kind)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("", f"an unreadable file ({type(exc).__name__})", f"a UTF-8 {kind} file",
                          config_file=str(path), kind=kind) from None
    if not _depth_ok(text):
        raise ConfigError("", f"lists or mappings nested more than {MAX_NESTING} deep", f"a {kind} file",
                          "Flatten the file; no capssim file nests that deep.", config_file=str(path), kind=kind)
    return text


def load_json_file(path, *, kind: str, example: str | None = None):
    """Parse a hand-written JSON file (``meta.json``, baselines, rig and calibration files).

    Raises :class:`ConfigError` (exit 2, one line) for a missing, unreadable, too deeply nested or
    invalid file. The result is *not* validated: check it with the file's schema spec.
    """
    import json

    text = read_text_file(path, kind=kind, example=example)
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        where = f" at line {exc.lineno}, column {exc.colno}" if hasattr(exc, "lineno") else ""
        raise ConfigError("", f"text that is not valid JSON{where}", f"a JSON {kind} file",
                          "Fix the JSON syntax (quotes, commas, brackets).", config_file=str(path),
                          kind=kind) from None


def load_yaml_file(path, *, kind: str, example: str | None = None):
    """Parse a hand-written YAML file (suite files, dataset and training configs), safely.

    Raises :class:`ConfigError` as :func:`load_json_file` does.
    """
    import yaml

    text = read_text_file(path, kind=kind, example=example)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError("", f"text that is not valid YAML{where} ({problem})", f"a YAML {kind} file",
                          "Fix the YAML syntax (indentation, colons, brackets).", config_file=str(path),
                          kind=kind) from None
    except RecursionError:
        raise ConfigError("", "a file nested too deeply", f"a YAML {kind} file", config_file=str(path),
                          kind=kind) from None


def validate(spec: Spec, value, *, config_file=None, kind: str = "config"):
    """``spec.check(value, "")`` with the file's path and kind added to any :class:`ConfigError`."""
    try:
        return spec.check(value, "")
    except ConfigError as exc:
        raise ConfigError(exc.key_path, exc.received, exc.valid, exc.fix,
                          config_file=str(config_file) if config_file is not None else exc.config_file,
                          kind=kind) from None
