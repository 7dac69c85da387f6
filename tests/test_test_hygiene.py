"""The tests share helpers through fixtures, and every declared marker is used (issue 33, item 5)."""

from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
#: support modules a test may import: module-time helpers (Hypothesis strategies and settings)
IMPORTABLE_SUPPORT = {"support.fuzz"}


def _test_files() -> list[Path]:
    return sorted(TESTS.rglob("test_*.py"))


def test_tests_import_no_conftest_no_test_module_and_builders_only_as_fixtures():
    test_modules = {path.stem for path in _test_files()}
    bad = []
    for path in _test_files():
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                top = name.split(".")[0]
                if (top in ("conftest", "tests") or name.split(".")[-1] in test_modules
                        or (top == "support" and name not in IMPORTABLE_SUPPORT)):
                    bad.append(f"{path.relative_to(REPO)}:{node.lineno} imports {name}")
    assert not bad, ("ask for the helper as a fixture (tests/conftest.py) instead:\n" + "\n".join(bad))


def test_every_declared_marker_is_used():
    declared = [line.split(":")[0].strip() for line in
                tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["markers"]]
    text = "\n".join(path.read_text() for path in [*_test_files(), TESTS / "conftest.py"])
    unused = [m for m in declared if not re.search(rf"pytest\.mark\.{m}\b", text)]
    assert declared and not unused, f"markers declared in pyproject.toml and never used: {unused}"
