"""Suite-like YAML spec files: a spec is a name shipped in a folder (``eval/suites``, ``eval/maps``) or a YAML path,
read once and validated whole, every mistake one :class:`~capssim.files.schema.ConfigError` line. Suites
(:mod:`.suite_schema`) and design maps (:mod:`capssim.eval.maps.spec`) load through it."""

from __future__ import annotations

import hashlib
from pathlib import Path

from capssim.errors import UnknownNameError
from capssim.files.schema import Spec, load_yaml_file, validate

__all__ = ["available_specs", "load_spec_file", "spec_path"]


def available_specs(folder: Path) -> list[str]:
    """The names of the YAML specs shipped in ``folder`` (suites in ``eval/suites``, design maps in ``eval/maps``)."""
    return sorted(p.stem for p in Path(folder).glob("*.yaml"))


def spec_path(name_or_path: str | Path, *, folder: Path, noun: str) -> Path:
    """The file of a spec name (``folder/NAME.yaml``) or YAML path; :class:`UnknownNameError` naming ``noun``
    otherwise."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") and path.is_file():
        return path
    names = available_specs(folder)
    if str(name_or_path) not in names:
        raise UnknownNameError(noun, str(name_or_path), names)
    return Path(folder) / f"{name_or_path}.yaml"


class _CheckedBy(Spec):
    """A whole spec file checked by one function ``check(value) -> spec``."""

    def __init__(self, check, description: str):
        self._check, self.description = check, description

    def check(self, value, path):
        return self._check(value)


def load_spec_file(name_or_path: str | Path, *, folder: Path, noun: str, kind: str, example: str, check,
                   description: str) -> dict:
    """Read a suite-like YAML spec and validate it with ``check`` (every mistake one :class:`ConfigError` line);
    the spec with ``name`` (default: the file's stem), ``path`` and ``sha256`` of the file."""
    path = spec_path(name_or_path, folder=folder, noun=noun)
    raw = load_yaml_file(path, kind=kind, example=example)
    spec = validate(_CheckedBy(check, description), raw, config_file=path, kind=kind)
    spec.setdefault("name", path.stem)
    spec["path"] = str(path)
    spec["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    return spec
