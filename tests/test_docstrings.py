"""The public API that the manual uses has numpy-style docstrings (issue 33, item 4).

The names are collected, not listed by hand: every ``capssim`` name imported (or a class's attribute
used) in the Python code blocks of README.md, docs/index.md and docs/guides/*.md and in the gallery
scripts (examples/gallery/*.py), every ``capssim.x.y`` name the guides and the gallery's text name in
backticks, and :data:`RETURNED_OBJECTS`, methods that the examples call on what the API returns.
Each callable among them needs a ``Parameters`` section (when it takes parameters) that names only
real parameters and all of them, and a function needs a ``Returns`` section (unless it returns None).
"""

from __future__ import annotations

import ast
import importlib
import inspect
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"```(?:python|py)\n(.*?)```", re.S)
DOTTED = re.compile(r"`(capssim(?:\.[A-Za-z_]\w*)+)")
SECTION = re.compile(r"^(\w[\w ]*)\n-{3,}\n(.*?)(?=^\w[\w ]*\n-{3,}\n|\Z)", re.M | re.S)

#: methods the guides and the gallery call on objects the API returns (``capture.lr_images()``, ...)
RETURNED_OBJECTS = (
    "capssim.captures.capture.Capture",
    "capssim.captures.capture.Capture.lr_images",
    "capssim.camera.rig.RigModel.flat_field",
    "capssim.render.render_capture",
    "capssim.reconstruct.registration.parameters.RegistrationParameters.replace",
)


def _sources() -> list[tuple[Path, str, str]]:
    """``(file, code, prose)``: the Python code and the text around it of every manual page and example."""
    pages = sorted((REPO / "docs" / "guides").glob("*.md")) + [REPO / "docs" / "index.md", REPO / "README.md"]
    out = [(page, "\n".join(FENCE.findall(page.read_text())), page.read_text()) for page in pages]
    for script in sorted((REPO / "examples" / "gallery").glob("*.py")):
        text = script.read_text()
        comments = "\n".join(re.findall(r"#.*", text))
        out.append((script, text, (ast.get_docstring(ast.parse(text)) or "") + "\n" + comments))
    return out


def _names_in(code: str) -> set[str]:
    """``capssim`` names imported by ``code``, and ``Name.attribute`` for the imported names."""
    tree = ast.parse(code)
    imported = {alias.asname or alias.name: f"{node.module}.{alias.name}"
                for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                and (node.module or "").split(".")[0] == "capssim" for alias in node.names}
    attributes = {f"{imported[node.value.id]}.{node.attr}" for node in ast.walk(tree)
                  if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in imported}
    return set(imported.values()) | attributes


def manual_names() -> dict[str, str]:
    """``{dotted name: where the manual uses it}``."""
    names: dict[str, str] = {name: "tests/test_docstrings.py RETURNED_OBJECTS" for name in RETURNED_OBJECTS}
    for path, code, prose in _sources():
        where = str(path.relative_to(REPO))
        for name in _names_in(code) | set(DOTTED.findall(prose)):
            names.setdefault(name, where)
    return names


def resolve(name: str):
    """The object a dotted name refers to: the longest importable module prefix, then attributes."""
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for part in parts[cut:]:
            obj = getattr(obj, part)
        return obj
    raise ImportError(name)


def sections(doc: str) -> dict[str, str]:
    """numpy-style sections of a docstring: ``{"Parameters": body, ...}``."""
    return {m.group(1): m.group(2) for m in SECTION.finditer(doc)}


def documented_parameters(body: str) -> set[str]:
    """Names of a Parameters section's entries (``a, b : type`` at the section's indentation)."""
    names = set()
    for line in body.splitlines():
        if line and not line[0].isspace():
            names.update(n.strip().lstrip("*") for n in line.split(" : ")[0].split(","))
    return names - {""}


def _signature_parameters(obj) -> set[str]:
    try:
        signature = inspect.signature(obj)
    except (TypeError, ValueError):
        return set()
    return {p for p in signature.parameters if p not in ("self", "cls")}


def _callables() -> list[tuple[str, str]]:
    found = []
    for name, where in sorted(manual_names().items()):
        try:
            obj = resolve(name)
        except (ImportError, AttributeError):
            continue  # test_every_name_the_manual_uses_exists reports it
        if callable(obj) and not inspect.ismodule(obj):
            found.append((name, where))
    return found


CALLABLES = _callables()


def test_the_manual_uses_the_api():
    """The collection finds the entry points that the README and the gallery show."""
    names = set(manual_names())
    for expected in ("capssim.simulate.simulate_capture", "capssim.reconstruct.reconstruct",
                     "capssim.eval.metrics.score", "capssim.camera.sensor.make_sensor"):
        assert expected in names
    assert len(CALLABLES) >= 30


def test_every_name_the_manual_uses_exists():
    missing = []
    for name, where in sorted(manual_names().items()):
        try:
            resolve(name)
        except (ImportError, AttributeError) as exc:
            missing.append(f"{name} (used in {where}): {type(exc).__name__}: {exc}")
    assert not missing, "the manual names what capssim lacks (moved? renamed?):\n" + "\n".join(missing)


@pytest.mark.parametrize("name, where", CALLABLES, ids=[name for name, _ in CALLABLES])
def test_public_api_docstring_has_numpy_sections(name, where):
    obj = resolve(name)
    doc = inspect.getdoc(obj) or ""
    found = sections(doc)
    parameters = _signature_parameters(obj)
    problems = []
    if parameters:
        if "Parameters" not in found:
            problems.append("no 'Parameters' section")
        else:
            documented = documented_parameters(found["Parameters"])
            if documented - parameters:
                problems.append(f"Parameters names {sorted(documented - parameters)}, not in the signature")
            if parameters - documented:
                problems.append(f"Parameters leaves out {sorted(parameters - documented)}")
    returns = inspect.signature(obj).return_annotation if not inspect.isclass(obj) else None
    if not inspect.isclass(obj) and returns not in (None, "None") and "Returns" not in found:
        problems.append("no 'Returns' section")
    assert not problems, (f"{name} (used in {where}): " + "; ".join(problems)
                          + ". Write a numpy-style docstring: Parameters / Returns with units, shapes and the "
                            "paper's equation where relevant.")


def test_section_parser_reads_numpy_docstrings():
    doc = "Summary.\n\nParameters\n----------\nx, y : int\n    Pixels.\n**options\n    More.\n\nReturns\n-------\nint\n"
    found = sections(doc)
    assert set(found) == {"Parameters", "Returns"}
    assert documented_parameters(found["Parameters"]) == {"x", "y", "options"}
    assert sections("Summary only.\n\n``x``: pixels.") == {}
