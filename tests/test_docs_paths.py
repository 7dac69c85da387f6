"""Every repository path and every internal link that README.md and docs/ name exists (issue 59 item 4).

A path is a word that starts with one of the repository's folders (``tests/evaluation/test_budget.py``,
``eval/suites/quick.yaml``, ``reconstruct/methods/``); words with a placeholder in capitals
(``eval/suites/NAME.yaml``) or a glob are patterns, not paths. A link is a Markdown link ``[text](target)``
that is not a web address: its file must exist (pages the documentation build generates, the gallery and
the API reference, are checked against their sources), and its ``#anchor`` must be a heading of the page.
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
PAGES = sorted([REPO / "README.md", *DOCS.rglob("*.md")])
FOLDERS = ("capssim", "reconstruct", "eval", "scenes", "tests", "examples", "scripts", "docs")
PATH = re.compile(r"(?<![\w./:-])(?:" + "|".join(FOLDERS) + r")/[\w./-]*")
LINK = re.compile(r"(?<!!)\[[^\]\n]*\]\(([^)\s]+)\)|!\[[^\]\n]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def _is_pattern(path: str) -> bool:
    return bool(re.search(r"[A-Z]{2,}|\*|\.\.\.|<|\{", path))


def repository_paths(text: str) -> set[str]:
    """The repository paths a page names (module docstring), trailing punctuation dropped."""
    found = set()
    for match in PATH.finditer(text):
        path = match.group(0).rstrip(".,;:)-")
        if not _is_pattern(path + text[match.end():match.end() + 1]):
            found.add(path)
    return found


def exists(path: str) -> bool:
    """A file or folder, or a module named without ``.py`` (``eval/metrics``, ``reconstruct/tiles/memory.plan``)."""
    return any((REPO / p).exists() for p in (path, f"{path}.py", f"{path.rsplit('.', 1)[0]}.py"))


def slug(heading: str) -> str:
    """The anchor MkDocs (Python-Markdown's toc) gives a heading."""
    text = re.sub(r"`|\*\*|\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")  # "512²" -> "5122"
    text = re.sub(r"[^\w\s-]", "", text)
    return re.sub(r"[-\s]+", "-", text).strip("-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6}\s+(.*?)\s*#*\s*$", text, re.M)}


def _generated(target: Path) -> bool:
    """Pages the documentation build writes: the gallery (from examples/gallery/*.py), the API reference,
    the sections' navigation."""
    rel = target.relative_to(DOCS) if target.is_relative_to(DOCS) else None
    if rel is None:
        return False
    if rel.parts[0] == "gallery":
        return rel.name == "index.md" or (REPO / "examples" / "gallery" / rel.with_suffix(".py").name).is_file()
    return rel.parts[0] == "reference"


def _shown(path: Path) -> str:
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def broken_links(page: Path) -> list[str]:
    text = FENCE.sub("", page.read_text())
    text = re.sub(r"`[^`\n]*`", "", text)
    broken = []
    for match in LINK.finditer(text):
        target = match.group(1) or match.group(2)
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        resolved = (page.parent / file).resolve() if file else page
        if _generated(resolved):
            continue
        if not resolved.exists():
            broken.append(f"{target} (no file {_shown(resolved)})")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target} (no heading #{anchor} in {_shown(resolved)})")
    return broken


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_repository_path_a_page_names_exists(page):
    missing = sorted(p for p in repository_paths(page.read_text()) if not exists(p))
    assert not missing, f"{page.relative_to(REPO)} names paths that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_internal_link_of_a_page_exists(page):
    broken = broken_links(page)
    assert not broken, f"{page.relative_to(REPO)} has broken links: {broken}"


def test_the_checks_find_a_missing_path_and_a_broken_link(tmp_path):
    text = "See tests/test_no_such_file.py, eval/suites/NAME.yaml, tests/*/test_fuzz_*.py and eval/suites/quick.yaml."
    assert repository_paths(text) == {"tests/test_no_such_file.py", "eval/suites/quick.yaml"}
    assert not exists("tests/test_no_such_file.py") and exists("eval/metrics") and exists("eval/metrics.score")
    assert slug("The `caps` method, step by step (paper sections 3-4, Fig. 3)") == \
        "the-caps-method-step-by-step-paper-sections-3-4-fig-3"
    (tmp_path / "other.md").write_text("# A heading\n\n## The paper's parameters\n")
    page = tmp_path / "page.md"
    page.write_text("[a](other.md#a-heading) [b](other.md#the-papers-parameters) [c](missing.md) [d](other.md#nope) "
                    "[e](https://example.org/x.md) `[f](not-a-link.md)`\n")
    assert [b.split()[0] for b in broken_links(page)] == ["missing.md", "other.md#nope"]
