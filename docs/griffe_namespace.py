"""Griffe extension for the API reference: one `capssim` namespace from four folders.

setuptools installs reconstruct/, eval/ and scenes/ as ``capssim.reconstruct``, ``capssim.eval``
and ``capssim.scenes`` (``[tool.setuptools] package-dir`` in pyproject.toml). Griffe's static
loader only finds sub-packages inside ``capssim/``, so once it has loaded ``capssim`` this
extension loads each mapped folder from source and attaches it under its installed name.
It also makes the docstrings' reST-ish markup Markdown: roles (``:func:`name```) become code spans,
the literal-block marker ``::`` goes, and the command line's click paragraphs (after a ``\\b``
line: print as written) become code blocks.

mkdocs.yml names it under ``plugins: mkdocstrings: handlers: python: options: extensions``.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import griffe

ROOT = Path(__file__).resolve().parent.parent
ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|data|attr|exc|obj|const|ref|term):`~?([^`]+)`")
LITERAL_MARK = re.compile(r"(\S)::$|\s+::$", re.MULTILINE)  # reST "text::" before an indented literal block


def package_dirs(pyproject: Path = ROOT / "pyproject.toml") -> dict[str, Path]:
    """Installed package name -> its folder, from pyproject's ``[tool.setuptools] package-dir``."""
    setuptools = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]
    return {name: ROOT / folder for name, folder in setuptools.get("package-dir", {}).items()}


def _click_paragraphs(text: str) -> str:
    """Each paragraph that click keeps as written (it follows a line ``\\b``) as a Markdown code block."""
    out, verbatim = [], False
    for line in text.splitlines():
        if line.strip() in ("\\b", "\b"):  # written \b in a docstring, it is a backspace character
            out.append("```text")
            verbatim = True
        elif verbatim and not line.strip():
            out += ["```", ""]
            verbatim = False
        else:
            out.append(line)
    return "\n".join(out + (["```"] if verbatim else []))


def _markdown_docstrings(obj: griffe.Object) -> None:
    if obj.docstring is not None:
        text = LITERAL_MARK.sub(lambda m: m.group(1) + ":" if m.group(1) else "", obj.docstring.value)
        obj.docstring.value = _click_paragraphs(ROLE.sub(r"`\1`", text))
    for member in obj.members.values():
        if not member.is_alias:
            _markdown_docstrings(member)


class NamespaceFolders(griffe.Extension):
    """Attach the folders mapped by package-dir to the loaded top-level package."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        mapped = sorted((name, folder) for name, folder in package_dirs().items() if name.startswith(pkg.name + "."))
        for name, folder in mapped:  # parents before children: sorted by dotted name
            parent_path, _, leaf = name.rpartition(".")
            parent = loader.modules_collection.get_member(parent_path)
            # _load_module is griffe's own loader step for a package folder (it recurses into submodules)
            module = loader._load_module(leaf, folder / "__init__.py", submodules=True, parent=parent)
            parent.set_member(leaf, module)
            loader.expand_exports(module)
        _markdown_docstrings(pkg)
