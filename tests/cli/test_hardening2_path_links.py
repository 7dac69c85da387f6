"""Issue 34, class 5: a FILE output that is a symbolic link is written through the link, never replaced.

(Folders through links: tests/cli/test_hardening2_paths.py.) The atomic writers write next to the link's
target and rename there, so the link stays a link and the file appears where it points; a link loop is
one line, exit 2, and nothing is written.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from support.fuzz import run_cli

from capssim.errors import InputError
from capssim.files.imageio import atomic_write_text, read_tiff, write_png, write_tiff


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    args: Callable[[Path], list]  #: the command line, given the test's folder (gt/, link -> target/out.EXT)
    ext: str  #: the extension of the file the link points at




def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob(".*") if ".tmp-" in p.name)


CLI_ROWS = [
    Row(5, "render --preview dangling link",
        lambda r: ["render", "siemens-star", "-o", r / "cap", "--size", 16, "--spp", 1, "--preview", r / "link"], ".png"),
    Row(5, "render --preview link to a file (replaced)",
        lambda r: ["render", "siemens-star", "-o", r / "cap", "--size", 16, "--spp", 1, "--preview", r / "link"],
        ".png+old"),
    Row(5, "gt-check --write-aligned dangling link",
        lambda r: ["gt-check", r / "gt", "--write-aligned", r / "link.tiff"], ".tiff"),
    Row(5, "gt-check --write-aligned link to a file --overwrite",
        lambda r: ["gt-check", r / "gt", "--write-aligned", r / "link.tiff", "--overwrite"], ".tiff+old"),
]


@pytest.mark.parametrize("row", CLI_ROWS, ids=[f"class{r.cls}-{r.name}" for r in CLI_ROWS])
def test_a_file_output_through_a_link_lands_where_the_link_points(row, tmp_path, write_gt_folder, capsys, monkeypatch):
    assert row.cls == 5
    write_gt_folder(tmp_path / "gt", size=32, seed=1)
    ext, _, old = row.ext.partition("+")
    target = tmp_path / "target" / f"out{ext}"
    target.parent.mkdir()
    if old:
        target.write_bytes(b"the old file")
    link = tmp_path / ("link.tiff" if ext == ".tiff" else "link")
    link.symlink_to(target)
    status, err = run_cli(row.args(tmp_path), capsys, monkeypatch, quiet=True)
    assert status == 0, err
    assert link.is_symlink() and link.resolve() == target, "the link was replaced by a file"
    assert target.is_file() and target.read_bytes() != b"the old file"
    assert _hidden(tmp_path) == []


def test_the_atomic_writers_write_through_links_and_refuse_loops(tmp_path):
    """class 5, the writers themselves: TIFF, PNG and text through a link to a missing or existing file."""
    array = np.arange(2 * 4 * 4, dtype=np.float32).reshape(2, 4, 4)
    for name, write, check in [
        ("a.tiff", lambda p: write_tiff(p, array), lambda p: np.array_equal(read_tiff(p), array)),
        ("b.png", lambda p: write_png(p, np.zeros((4, 4, 3))), lambda p: p.read_bytes()[:4] == b"\x89PNG"),
        ("c.json", lambda p: atomic_write_text(p, "{}"), lambda p: p.read_text() == "{}"),
    ]:
        for existing in (False, True):
            target = tmp_path / f"{existing}" / name
            target.parent.mkdir(exist_ok=True)
            if existing:
                target.write_text("old")
            link = tmp_path / f"link-{existing}-{name}"
            link.symlink_to(target)
            write(link)
            assert link.is_symlink() and check(target), (name, existing)
    (tmp_path / "loop.tiff").symlink_to("loop.tiff")
    with pytest.raises(InputError, match="loops back on itself"):
        write_tiff(tmp_path / "loop.tiff", array)
    assert _hidden(tmp_path) == []
