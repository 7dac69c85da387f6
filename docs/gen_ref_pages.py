"""Generate the API reference at build time: one page per public module of the installed namespace.

mkdocs-gen-files runs this script on every build. The modules come from pyproject.toml (the
``packages`` list and the ``package-dir`` folder mapping), so a module that is added, split or
renamed appears without editing the docs. Modules whose name starts with ``_`` and ``__main__``
are left out. Each page holds one mkdocstrings directive (``::: capssim.x.y``);
``reference/SUMMARY.md`` is the section's navigation for mkdocs-literate-nav.
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import mkdocs_gen_files

sys.path.insert(0, str(Path(__file__).resolve().parent))
from griffe_namespace import ROOT, package_dirs  # noqa: E402


def package_folder(package: str, dirs: dict[str, Path]) -> Path:
    """The folder of an installed package: its own package-dir entry, or its nearest mapped parent's."""
    base = max((name for name in dirs if package == name or package.startswith(name + ".")), key=len)
    rest = package[len(base) + 1:]
    return dirs[base].joinpath(*rest.split(".")) if rest else dirs[base]


def public_modules() -> list[tuple[str, Path, bool]]:
    """(dotted name, source file, is a package) of every public module, sorted by name."""
    dirs = package_dirs()
    packages = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    modules = []
    for package in packages:
        folder = package_folder(package, dirs)
        modules.append((package, folder / "__init__.py", True))
        for source in sorted(folder.glob("*.py")):
            if not source.stem.startswith("_"):
                modules.append((f"{package}.{source.stem}", source, False))
    return sorted(modules)


def contents(package: str, modules: list[tuple[str, Path, bool]]) -> str:
    """A package page's list of its direct sub-modules and sub-packages, linked to their pages."""
    rows = []
    for name, _, is_package in modules:
        parent, _, leaf = name.rpartition(".")
        if parent == package:
            rows.append(f"- [`{name}`]({leaf}/index.md)" if is_package else f"- [`{name}`]({leaf}.md)")
    return "\n## Modules\n\n" + "\n".join(rows) + "\n" if rows else ""


def main() -> None:
    nav = mkdocs_gen_files.Nav()
    modules = public_modules()
    for name, source, is_package in modules:
        parts = name.split(".")
        page = Path(*parts, "index.md") if is_package else Path(*parts[:-1], parts[-1] + ".md")
        nav[tuple(parts)] = page.as_posix()
        with mkdocs_gen_files.open(Path("reference", page), "w") as out:
            out.write(f"# `{name}`\n\n::: {name}\n" + (contents(name, modules) if is_package else ""))
        mkdocs_gen_files.set_edit_path(Path("reference", page), source.relative_to(ROOT))
    with mkdocs_gen_files.open("reference/SUMMARY.md", "w") as summary:
        summary.writelines(nav.build_literate_nav())


main()
