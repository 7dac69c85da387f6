"""The house: one import namespace, floors that import only downwards, no import circles.

Floors (docs/architecture.md, "The floors"), lowest first; a module may import its own floor and the ones
below. Within a floor, the import graph must still have no circle.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: installed package name -> folder of the repository (pyproject.toml [tool.setuptools] package-dir)
ROOTS = {"capssim": "capssim", "capssim.reconstruct": "reconstruct", "capssim.eval": "eval",
         "capssim.scenes": "scenes"}

#: capssim's rooms (sub-packages) and root modules on the physics floor (docs/architecture.md, "The rooms of
#: capssim/"), lowest first; test_capssim_rooms_import_only_downwards pins their order
CAPSSIM_ROOMS = (
    ("capssim", "capssim.errors", "capssim.conventions"),
    ("capssim.runtime",),
    ("capssim.files",),
    ("capssim.stokes",),
    ("capssim.camera",),
    ("capssim.operators",),
    ("capssim.captures",),
    ("capssim.visualize",),
)
PHYSICS = tuple(name for room in CAPSSIM_ROOMS for name in room)
#: (floor name, module prefixes), lowest floor first
FLOORS = (
    ("physics", PHYSICS),
    ("simulation and rendering", ("capssim.simulate", "capssim.render")),
    ("scenes", ("capssim.scenes",)),
    ("datasets", ("capssim.dataset",)),
    ("reconstruction", ("capssim.reconstruct",)),
    ("evaluation", ("capssim.eval",)),
    ("command line", ("capssim.cli", "capssim.__main__")),
)
#: floors whose functions may import project modules lazily (start-up time of the command line)
LAZY_IMPORT_FLOORS = ("command line",)


def _modules() -> dict[str, Path]:
    found = {}
    for package, folder in ROOTS.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = path.relative_to(REPO / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([package, *parts])
            if package == "capssim" and any(name == r or name.startswith(r + ".") for r in ROOTS if r != "capssim"):
                continue
            found[name] = path
    return found


MODULES = _modules()


def floor_of(module: str) -> int:
    # a module at capssim/'s root (capssim/*.py) is physics unless a higher floor names it (capssim.simulate)
    best = 0 if module.startswith("capssim.") and module.count(".") == 1 else None
    for rank, (_, prefixes) in enumerate(FLOORS):
        for prefix in prefixes:
            if module == prefix or (prefix != "capssim" and module.startswith(prefix + ".")):
                best = rank
    if best is None:
        raise AssertionError(f"{module} is on no floor: add it to FLOORS in {Path(__file__).name}")
    return best


def _absolute(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module name of ``from <node.module> import ...`` in ``module`` (relative imports resolved)."""
    if not node.level:
        return node.module
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    parts = package.split(".")
    base = parts[:len(parts) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(path: Path, module: str = "") -> list[tuple[str, bool, int]]:
    """``(imported project module, inside a function?, line)`` for each project import of a file
    (relative imports resolved against ``module``, the file's own module name)."""
    tree = ast.parse(path.read_text())
    top_level = {id(node) for node in tree.body}
    for node in ast.walk(tree):  # imports under module-level if/try count as top level
        if isinstance(node, (ast.If, ast.Try)) and id(node) in top_level:
            top_level.update(id(child) for child in ast.walk(node))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and (node.module or node.level):
            source = _absolute(module, path, node)
            # ``from package import submodule`` depends on the submodule; other names on the module itself
            names = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in MODULES else source
                     for alias in node.names]
        else:
            continue
        for name in names:
            if name in MODULES:
                out.append((name, id(node) not in top_level, node.lineno))
    return out


GRAPH = {module: _imports(path, module) for module, path in MODULES.items()}


def test_every_module_is_on_a_floor():
    assert len(MODULES) > 50
    for module in MODULES:
        floor_of(module)


@pytest.mark.parametrize("floor", [name for name, _ in FLOORS])
def test_floor_imports_only_downwards(floor):
    rank = [name for name, _ in FLOORS].index(floor)
    upward = []
    for module, imports in GRAPH.items():
        if floor_of(module) != rank:
            continue
        for target, _, line in imports:
            if floor_of(target) > rank:
                upward.append(f"{MODULES[module].relative_to(REPO)}:{line} imports {target} "
                              f"({FLOORS[floor_of(target)][0]} floor)")
    assert not upward, "imports that run up a floor:\n" + "\n".join(upward)


#: the rooms of capssim.reconstruct (its sub-packages, and its root modules by name), lowest first: a module
#: imports modules of its own room and of the rooms below it, never of one above
RECONSTRUCT_ROOMS = (
    ("filters", "calibration_model", "run_context"),
    ("dofp",),
    ("registration",),
    ("calibration",),  # the rig estimated from calibration captures (flat field, geometry, Malus, PSF)
    ("model",),
    ("kernel_regression",),  # array-kr's merge of raw samples (below the solvers; needs no solver)
    ("solvers",),
    ("networks",),  # the learned networks: below the priors, which may hold one (nlstr-denoiser)
    ("priors",),
    ("pipeline",),
    ("selection",),  # a method's data-driven choices, made once per frame before its solve
    ("registry", "option_probe"),  # option_probe: a method run up to its options, before any work
    ("uncertainty",),  # error bars: a bootstrap that runs any registered method again (above the registry)
    ("methods", "plugins"),  # plug-in methods and priors from other packages, registered beside the built-ins
    ("training",),
    ("tiles",),  # full frames in tiles: runs any registered method per tile
    ("",),  # the package's face, capssim.reconstruct itself
)


def reconstruct_room(module: str) -> int:
    rest = module.removeprefix("capssim.reconstruct").lstrip(".")
    head = rest.split(".", 1)[0]
    for rank, names in enumerate(RECONSTRUCT_ROOMS):
        if head in names:
            return rank
    raise AssertionError(f"{module} is in no room: add it to RECONSTRUCT_ROOMS in {Path(__file__).name}")


def test_reconstruct_rooms_import_only_downwards():
    inside = [m for m in MODULES if m == "capssim.reconstruct" or m.startswith("capssim.reconstruct.")]
    root_modules = [m for m in inside if m.count(".") == 2 and MODULES[m].name != "__init__.py"]
    assert len(root_modules) + 1 <= 8, f"reconstruct/ holds {len(root_modules) + 1} modules at its root (at most 8)"
    upward = [f"{MODULES[m].relative_to(REPO)}:{line} imports {t}" for m in inside for t, _, line in GRAPH[m]
              if t.startswith("capssim.reconstruct") and reconstruct_room(t) > reconstruct_room(m)]
    assert not upward, "imports that run up a room of reconstruct/:\n" + "\n".join(upward)


def capssim_room(module: str) -> int:
    for rank, names in enumerate(CAPSSIM_ROOMS):
        if any(module == name or (name != "capssim" and module.startswith(name + ".")) for name in names):
            return rank
    raise AssertionError(f"{module} is in no room: add it to CAPSSIM_ROOMS in {Path(__file__).name}")


def test_capssim_rooms_import_only_downwards():
    inside = [m for m in MODULES if floor_of(m) == 0]
    root_modules = [m for m in MODULES if m.count(".") == 1 and MODULES[m].name != "__init__.py"
                    and m != "capssim.__main__"]
    assert len(root_modules) <= 12, f"capssim/ holds {len(root_modules)} modules at its root (at most 12)"
    upward = [f"{MODULES[m].relative_to(REPO)}:{line} imports {t}" for m in inside for t, _, line in GRAPH[m]
              if floor_of(t) == 0 and capssim_room(t) > capssim_room(m)]
    assert not upward, "imports that run up a room of capssim/:\n" + "\n".join(upward)


def test_renderer_never_imports_the_scenes():
    offenders = [f"{module} -> {target}" for module, imports in GRAPH.items() if module.startswith("capssim.render")
                 for target, _, _ in imports if target.startswith("capssim.scenes")]
    assert not offenders


def test_scenes_register_through_their_entry_point_alone():
    """The scene library registers through one call (pyproject's entry point), not through imports for side effects."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert config["entry-points"]["capssim.scenes"] == {"library": "capssim.scenes:register_library"}
    importers = [f"{MODULES[m].relative_to(REPO)}:{line}" for m, imports in GRAPH.items()
                 if not m.startswith("capssim.scenes") for t, _, line in imports if t.startswith("capssim.scenes")]
    assert not importers, "these import the scene library; look scenes up with capssim.render.get_scene:\n" + \
        "\n".join(importers)
    code = ("import sys; from capssim.render import list_scenes; from capssim.scenes import LIBRARY; "
            "assert sorted(list_scenes()) == sorted(c().info.name for c in LIBRARY), sorted(list_scenes())")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_no_import_circles():
    edges = {m: sorted({t for t, _, _ in imports if t != m}) for m, imports in GRAPH.items()}
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in edges:
        if v not in index:
            visit(v)
    assert not circles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in circles)


def test_project_imports_inside_functions_only_where_start_up_time_needs_them():
    lazy_ok = {[name for name, _ in FLOORS].index(f) for f in LAZY_IMPORT_FLOORS}
    lazy = [f"{MODULES[m].relative_to(REPO)}:{line} imports {t} inside a function"
            for m, imports in GRAPH.items() if floor_of(m) not in lazy_ok
            for t, inside, line in imports if inside]
    assert not lazy, "move these imports to the top of their modules:\n" + "\n".join(lazy)


def test_pyproject_installs_one_namespace_covering_every_package_folder():
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert config["package-dir"] == ROOTS
    listed = set(config["packages"])
    assert all(name == "capssim" or name.startswith("capssim.") for name in listed)
    folders = {m for m, p in MODULES.items() if p.name == "__init__.py"}
    assert listed == folders, f"not listed: {sorted(folders - listed)}; listed but absent: {sorted(listed - folders)}"


@pytest.mark.parametrize("name", ["eval", "reconstruct", "scenes"])
def test_bare_folder_names_do_not_import(name, tmp_path):
    for cwd in (REPO, tmp_path):  # the clone's root (folder on sys.path) and anywhere else
        result = subprocess.run([sys.executable, "-c", f"import {name}"], cwd=cwd, capture_output=True, text=True)
        assert result.returncode != 0
        assert "ImportError" in result.stderr or "ModuleNotFoundError" in result.stderr
    result = subprocess.run([sys.executable, "-c", f"import capssim.{name}"], cwd=tmp_path, capture_output=True,
                            text=True)
    assert result.returncode == 0, result.stderr


MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 80


def test_modules_and_functions_stay_small():
    too_long = []
    for module, path in MODULES.items():
        text = path.read_text()
        lines = text.count("\n") + 1
        if lines > MAX_MODULE_LINES:
            too_long.append(f"{path.relative_to(REPO)}: {lines} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    too_long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name}: {length} lines "
                                    f"(at most {MAX_FUNCTION_LINES})")
    assert not too_long, "split these:\n" + "\n".join(too_long)


def test_installed_distribution_has_one_top_level_name():
    from importlib import metadata

    dists = list(metadata.distributions(name="capssim"))
    if not dists:
        pytest.skip("capssim is not installed (pip install -e .)")
    finders = 0
    for dist in dists:
        assert (dist.read_text("top_level.txt") or "capssim").split() == ["capssim"]
        for file in dist.files or []:  # an editable install maps only capssim.* names to the folders
            if file.name.startswith("__editable__") and file.name.endswith("finder.py"):
                finders += 1
                mapping = ast.literal_eval(next(line.split("=", 1)[1] for line in file.read_text().splitlines()
                                                if line.startswith("MAPPING")))
                assert sorted(mapping) == sorted(ROOTS)
    assert finders <= 1
