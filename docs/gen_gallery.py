"""Build the example gallery at docs build time: run every ``examples/gallery/*.py``, one page each.

mkdocs-gen-files runs this script on every build (mkdocs.yml). For each example, in file-name
order, it runs the script in this process (``runpy``, as ``__main__``) with the working folder set
to a fresh temporary folder and matplotlib on its non-interactive ``Agg`` backend, captures what
the script prints, saves every matplotlib figure still open when it ends as a PNG, and writes
``gallery/NAME.md``: the script's docstring, its code, its output and its figures. It also writes
``gallery/index.md`` (one card per example, with its first figure) and ``gallery/SUMMARY.md``
(the section's navigation, for mkdocs-literate-nav).

An exception in an example stops the build (its message names the example), so the strict
build that CI runs fails on a broken example. No result is stored in the repository: every
output on the site is the output of this build.

An example is a plain script: a module docstring whose first line is the title, then code.
``plt.show()`` is a no-op here (figures are collected at the end), so the same script opens
windows when run by hand: ``.venv/bin/python examples/gallery/NAME.py``.
"""

from __future__ import annotations

import ast
import contextlib
import io
import logging
import os
import runpy
import sys
import tempfile
import time
from pathlib import Path

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples" / "gallery"
PAGES = Path("gallery")
#: an example slower than this (seconds) is marked in the build log; the whole gallery should stay well under 2 min
SLOW_S = 20.0

log = logging.getLogger("mkdocs.plugins.capssim_gallery")


def split_docstring(source: str) -> tuple[str, str, str]:
    """(title, description, code) of an example: its docstring's first line, the rest of it, the code after it."""
    module = ast.parse(source)
    doc = ast.get_docstring(module)
    if not doc or not module.body or not isinstance(module.body[0], ast.Expr):
        raise ValueError("an example starts with a module docstring whose first line is its title")
    title, _, description = doc.partition("\n")
    code = "\n".join(source.splitlines()[module.body[0].end_lineno:]).strip("\n")
    return title.strip().rstrip("."), description.strip(), code


def run_example(path: Path) -> tuple[str, list[bytes], float]:
    """Run one example; return its printed output, its open figures as PNG bytes and its wall time (s)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    plt.close("all")
    stdout = io.StringIO()
    show, argv, cwd = plt.show, sys.argv, os.getcwd()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="capssim-gallery-") as work:
        try:
            plt.show = lambda *args, **kwargs: None
            sys.argv = [str(path)]
            os.chdir(work)
            with contextlib.redirect_stdout(stdout):
                runpy.run_path(str(path), run_name="__main__")
        except BaseException as exc:  # SystemExit included: an example that exits has failed
            raise RuntimeError(f"gallery example {path.relative_to(ROOT)} failed: {type(exc).__name__}: {exc}\n"
                               f"Run it alone to see the traceback: .venv/bin/python {path.relative_to(ROOT)}") from exc
        finally:
            plt.show, sys.argv = show, argv
            os.chdir(cwd)
        figures = []
        for number in plt.get_fignums():
            buffer = io.BytesIO()
            plt.figure(number).savefig(buffer, format="png", dpi=80, bbox_inches="tight")
            figures.append(buffer.getvalue())
        plt.close("all")
    return stdout.getvalue(), figures, time.perf_counter() - t0


def example_page(path: Path, title: str, description: str, code: str, output: str, figures: list[str],
                 seconds: float) -> str:
    """The Markdown page of one example."""
    rel = path.relative_to(ROOT).as_posix()
    lines = [f"# {title}", "", description, "",
             f"Source: `{rel}`; run it with `.venv/bin/python {rel}` (it writes only to a temporary folder).", "",
             "```python", code, "```", ""]
    if output.strip():
        lines += ["## Output", "", "```text", output.rstrip(), "```", ""]
    if figures:
        lines += ["## Figures", ""]
        lines += [f"![{title}, figure {i + 1}]({name})" + "{ loading=lazy }\n" for i, name in enumerate(figures)]
    lines += [f"*This page ran the example while the documentation was built ({seconds:.1f} s).*", ""]
    return "\n".join(lines)


def index_page(entries: list[tuple[str, str, str, list[str]]]) -> str:
    """The gallery's front page: one section per example, with its summary and first figure."""
    lines = ["# Example gallery", "",
             "Short Python scripts that use capssim's API, from a simulated capture to a calibrated rig. "
             "The documentation build runs every one of them: the output and figures on their pages are "
             "what this version of the code printed and drew. Each one takes a few seconds on a laptop "
             "CPU, needs neither the shared data nor a GPU, and writes only to a temporary folder.", "",
             "Run one yourself: `.venv/bin/python examples/gallery/NAME.py`. "
             "To add one, put a script with a docstring (title on the first line) into `examples/gallery/`.", ""]
    for stem, title, description, figures in entries:
        summary = description.split("\n\n")[0].replace("\n", " ")
        lines += [f"## [{title}]({stem}.md)", "", summary, ""]
        if figures:
            lines += [f"[![{title}]({figures[0]}){{ width=\"360\" loading=lazy }}]({stem}.md)", ""]
    return "\n".join(lines)


def main() -> None:
    scripts = sorted(EXAMPLES.glob("*.py"))
    if not scripts:
        raise RuntimeError(f"the example gallery is empty: no *.py in {EXAMPLES}")
    entries, total = [], 0.0
    for path in scripts:
        title, description, code = split_docstring(path.read_text())
        output, pngs, seconds = run_example(path)
        total += seconds
        log.info(f"gallery: {path.name} ran in {seconds:.1f} s" + (" (slow: keep examples small)" if seconds > SLOW_S else ""))
        names = []
        for i, png in enumerate(pngs):
            names.append(f"{path.stem}-{i + 1}.png")
            with mkdocs_gen_files.open(PAGES / names[-1], "wb") as out:
                out.write(png)
        with mkdocs_gen_files.open(PAGES / f"{path.stem}.md", "w") as out:
            out.write(example_page(path, title, description, code, output, names, seconds))
        mkdocs_gen_files.set_edit_path(PAGES / f"{path.stem}.md", path.relative_to(ROOT))
        entries.append((path.stem, title, description, names))
    log.info(f"gallery: {len(scripts)} examples in {total:.1f} s")
    with mkdocs_gen_files.open(PAGES / "index.md", "w") as out:
        out.write(index_page(entries))
    with mkdocs_gen_files.open(PAGES / "SUMMARY.md", "w") as out:
        out.write("* [Example gallery](index.md)\n" + "".join(f"* [{t}]({s}.md)\n" for s, t, _, _ in entries))


main()
