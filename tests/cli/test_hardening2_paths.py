"""Issue 34, class 5: output paths resolved before any work, and file-system errors as one line.

Every row names its class. A refused output exits 2 with exactly one ``error:`` line and no traceback,
before the command's work starts (the work function is replaced by one that fails the test); a link
that resolves to a usable place is followed; a write that fails (full disk, read-only file system, name
too long, ...) names the output and the error, and leaves no half-written output and no hidden
``.NAME.tmp-*`` temporary behind.
"""

from __future__ import annotations

import errno
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from support.fuzz import one_error_line, run_cli

from capssim.errors import InputError
from capssim.files.output_paths import check_files_in, follow_links, resolve_output, write_error


@dataclass(frozen=True)
class Row:
    cls: int
    name: str
    args: Callable[[Path], list]  #: the command line, given the test's folder (which holds gt/, cap/, loop, dangling)
    fragments: tuple = ()  #: words the one error line holds
    forbid: str = ""  #: "module:function" of the command's work: it must not run
    setup: Callable[[Path], None] = field(default=lambda root: None)






def leftovers(folder: Path) -> list[str]:
    """Hidden temporaries of the atomic writers anywhere under ``folder``."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(".*") if ".tmp-" in p.name or ".old-" in p.name)


@pytest.fixture(scope="module")
def template(tmp_path_factory, write_gt_folder) -> Path:
    """``gt/`` (64 px PNGs), ``cap/`` (its 32 px capture) and ``raw.png`` (a 32 px mosaic), built once."""
    from capssim.camera.sensor import make_sensor
    from capssim.captures.capture import write_capture
    from capssim.files.imageio import read_gt_scene
    from capssim.simulate import prepare_ground_truth, simulate_capture

    folder = tmp_path_factory.mktemp("paths")
    write_gt_folder(folder / "gt", size=64, seed=1)
    image, _ = prepare_ground_truth(read_gt_scene(folder / "gt")[0], crop=32)
    write_capture(folder / "cap", simulate_capture(image, make_sensor("none"), seed=0))
    import cv2

    cv2.imwrite(str(folder / "raw.png"), (np.arange(32 * 32).reshape(32, 32) % 251).astype(np.uint8))
    return folder


@pytest.fixture
def root(tmp_path, template) -> Path:
    """A copy of :func:`template`, with a link loop ``loop`` and a dangling link ``dangling -> elsewhere/out``."""
    shutil.copytree(template, tmp_path, dirs_exist_ok=True)
    (tmp_path / "loop").symlink_to("loop")
    (tmp_path / "dangling").symlink_to(tmp_path / "elsewhere" / "out")
    return tmp_path


def _mkdir(*parts: str) -> Callable[[Path], None]:
    return lambda root: root.joinpath(*parts).mkdir(parents=True)


def _touch(*parts: str) -> Callable[[Path], None]:
    return lambda root: root.joinpath(*parts).write_text("in the way")


SIMULATE = "capssim.simulate:simulate_capture"
EVALUATE = "capssim.eval.evaluate:evaluate_capture"
RECONSTRUCT = "capssim.reconstruct.tiles.frames:reconstruct_frame"
DEMOSAIC = "capssim.cli.demosaic:read_image"
LOOP = ("-o/--output", "'", "loop", "symbolic link that loops")

REFUSED = [
    # -o pointing at a symbolic-link loop, with and without --overwrite
    Row(5, "simulate -o loop", lambda r: ["simulate", r / "gt", "-o", r / "loop", "--crop", 32], LOOP, SIMULATE),
    Row(5, "simulate -o loop --overwrite",
        lambda r: ["simulate", r / "gt", "-o", r / "loop", "--crop", 32, "--overwrite"], LOOP, SIMULATE),
    Row(5, "demosaic -o loop", lambda r: ["demosaic", r / "raw.png", "-o", r / "loop"], LOOP, DEMOSAIC),
    Row(5, "demosaic -o loop --overwrite", lambda r: ["demosaic", r / "raw.png", "-o", r / "loop", "--overwrite"],
        LOOP, DEMOSAIC),
    Row(5, "render -o loop", lambda r: ["render", "siemens-star", "-o", r / "loop", "--size", 16, "--spp", 1], LOOP),
    Row(5, "render --preview loop",
        lambda r: ["render", "siemens-star", "-o", r / "new", "--size", 16, "--spp", 1, "--preview", r / "loop"],
        ("--preview", "loops")),
    Row(5, "dataset -o loop", lambda r: ["dataset", r / "missing.yaml", "-o", r / "loop"], LOOP),
    Row(5, "train -o loop", lambda r: ["train", r / "missing.yaml", "-o", r / "loop"], LOOP),
    Row(5, "calibrate -o loop", lambda r: ["calibrate", r / "cap", r / "cap", r / "cap", "-o", r / "loop"], LOOP),
    Row(5, "calibrate --report loop",
        lambda r: ["calibrate", r / "cap", r / "cap", r / "cap", "-o", r / "rig.json", "--report", r / "loop"],
        ("--report", "loops")),
    Row(5, "calibration-captures -o loop", lambda r: ["calibration-captures", "-o", r / "loop", "--size", 32],
        ("OUTPUT", "loops")),
    Row(5, "gt-check --write-aligned loop.tiff",
        lambda r: ["gt-check", r / "gt", "--write-aligned", r / "loop.tiff"], ("--write-aligned", "loops"),
        setup=lambda r: (r / "loop.tiff").symlink_to("loop.tiff")),
    Row(5, "bench suite -o loop", lambda r: ["bench", "suite", "quick", "-o", r / "loop"], ("-o", "loop")),
    Row(5, "bench budget -o loop", lambda r: ["bench", "budget", "quick", "-o", r / "loop"], LOOP),
    Row(5, "bench dataset --keep loop", lambda r: ["bench", "dataset", r / "missing.yaml", "--keep", r / "loop"],
        ("--keep", "loops")),
    # a dangling link the bench refuses (its output folder holds a lock: it must exist as a folder)
    Row(5, "bench suite -o dangling", lambda r: ["bench", "suite", "quick", "-o", r / "dangling"],
        ("-o", "does not exist")),
    # a file or folder in the way, reported before the work
    Row(5, "evaluate: metrics.json is a folder", lambda r: ["evaluate", r / "cap"],
        ("CAPTURE", "metrics.json", "an existing folder", "Remove or rename"), EVALUATE, _mkdir("cap", "metrics.json")),
    Row(5, "reconstruct -m caps: recon/caps.tiff is a folder", lambda r: ["reconstruct", r / "cap", "-m", "caps"],
        ("CAPTURE", "recon/caps.tiff", "an existing folder"), RECONSTRUCT, _mkdir("cap", "recon", "caps.tiff")),
    Row(5, "reconstruct -m dofp-bilinear: recon/dofp-bilinear.json is a folder",
        lambda r: ["reconstruct", r / "cap", "-m", "dofp-bilinear"], ("recon/dofp-bilinear.json", "an existing folder"),
        RECONSTRUCT, _mkdir("cap", "recon", "dofp-bilinear.json")),
    Row(5, "reconstruct: recon is a file", lambda r: ["reconstruct", r / "cap", "-m", "dofp-bilinear"],
        ("CAPTURE", "recon", "an existing file"), RECONSTRUCT, _touch("cap", "recon")),
    Row(5, "simulate -o FILE --overwrite", lambda r: ["simulate", r / "gt", "-o", r / "raw.png", "--overwrite"],
        ("-o/--output", "raw.png", "an existing file", "a folder path"), SIMULATE),
    Row(5, "demosaic -o FILE --overwrite", lambda r: ["demosaic", r / "raw.png", "-o", r / "gt" / "0.png",
                                                      "--overwrite"], ("-o/--output", "0.png", "an existing file"),
        DEMOSAIC),
    Row(5, "demosaic -o link to a file --overwrite", lambda r: ["demosaic", r / "raw.png", "-o", r / "flink",
                                                                "--overwrite"], ("a link to", "an existing file"),
        DEMOSAIC, lambda r: (r / "flink").symlink_to(r / "raw.png")),
    Row(5, "render --preview FOLDER",
        lambda r: ["render", "siemens-star", "-o", r / "new", "--size", 16, "--spp", 1, "--preview", r / "gt"],
        ("--preview", "an existing folder")),
    Row(5, "calibrate -o FOLDER --overwrite",
        lambda r: ["calibrate", r / "cap", r / "cap", r / "cap", "-o", r / "gt", "--overwrite"],
        ("-o/--output", "an existing folder")),
    Row(5, "calibrate --report FILE",
        lambda r: ["calibrate", r / "cap", r / "cap", r / "cap", "-o", r / "rig.json", "--report", r / "raw.png"],
        ("--report", "an existing file")),
    Row(5, "gt-check --write-aligned FOLDER.tiff --overwrite",
        lambda r: ["gt-check", r / "gt", "--write-aligned", r / "x.tiff", "--overwrite"],
        ("--write-aligned", "an existing folder"), "capssim.eval.gt_check:check_ground_truth", _mkdir("x.tiff")),
    Row(5, "train -o FILE", lambda r: ["train", r / "missing.yaml", "-o", r / "raw.png"],
        ("-o/--output", "an existing file")),
    Row(5, "dataset -o FILE", lambda r: ["dataset", r / "missing.yaml", "-o", r / "raw.png"],
        ("-o/--output", "an existing file")),
    Row(5, "bench budget -o FILE", lambda r: ["bench", "budget", "quick", "-o", r / "raw.png"],
        ("-o/--output", "an existing file")),
    Row(5, "bench budget --results-page FOLDER",
        lambda r: ["bench", "budget", "quick", "-o", r / "b", "--results-page", r / "gt"],
        ("--results-page", "an existing folder")),
    Row(5, "bench suite --results-page FOLDER",
        lambda r: ["bench", "suite", "quick", "-o", r / "b", "--results-page", r / "gt"],
        ("--results-page", "an existing folder")),
    Row(5, "bench dataset --keep FILE", lambda r: ["bench", "dataset", r / "missing.yaml", "--keep", r / "raw.png"],
        ("--keep", "an existing file")),
    # a name the file system cannot hold: refused while probing or creating, one line naming the error
    Row(5, "reconstruct -m dofp-bilinear: recon/dofp-bilinear.tiff is a folder",
        lambda r: ["reconstruct", r / "cap", "-m", "dofp-bilinear"],
        ("CAPTURE", "recon/dofp-bilinear.tiff", "an existing folder", "Remove or rename"), RECONSTRUCT,
        _mkdir("cap", "recon", "dofp-bilinear.tiff")),
    # a loop inside the path, a dangling link to a place no folder can be made, a link to a folder without --overwrite
    Row(5, "simulate -o loop/out", lambda r: ["simulate", r / "gt", "-o", r / "loop" / "out", "--crop", 32],
        ("-o/--output", "loops back"), SIMULATE),
    Row(5, "demosaic -o loop/out --overwrite", lambda r: ["demosaic", r / "raw.png", "-o", r / "loop" / "out",
                                                          "--overwrite"], ("-o/--output", "loops back"), DEMOSAIC),
    Row(5, "simulate -o dangling link under a file", lambda r: ["simulate", r / "gt", "-o", r / "dfile", "--crop", 32],
        ("-o/--output", "dfile", "under the existing file", "raw.png"), SIMULATE,
        lambda r: (r / "dfile").symlink_to(r / "raw.png" / "out")),
    Row(5, "demosaic -o dangling link under a file --overwrite",
        lambda r: ["demosaic", r / "raw.png", "-o", r / "dfile", "--overwrite"],
        ("-o/--output", "under the existing file"), DEMOSAIC, lambda r: (r / "dfile").symlink_to(r / "raw.png" / "o")),
    Row(5, "demosaic -o link to a folder, no --overwrite", lambda r: ["demosaic", r / "raw.png", "-o", r / "dlink"],
        ("-o/--output", "a link to", "pass --overwrite"), DEMOSAIC,
        lambda r: (r / "dlink").symlink_to(r / "gt")),
    Row(5, "simulate -o NAME too long", lambda r: ["simulate", r / "gt", "-o", r / ("x" * 300), "--crop", 32],
        ("-o/--output", "File name too long, ENAMETOOLONG", "shorter name"), SIMULATE),
]


@pytest.mark.parametrize("row", REFUSED, ids=[f"class{r.cls}-{r.name}" for r in REFUSED])
def test_refused_outputs_are_one_line_before_any_work(row, root, capsys, monkeypatch):
    assert row.cls == 5
    row.setup(root)
    if row.forbid:
        module, name = row.forbid.split(":")

        def work_started(*args, **kwargs):
            raise AssertionError(f"{row.name}: the work started before the output was checked")

        monkeypatch.setattr(f"{module}.{name}", work_started)
    before = sorted(p.name for p in root.iterdir())
    one_error_line(*run_cli(row.args(root), capsys, monkeypatch, quiet=True), *row.fragments)
    assert sorted(p.name for p in root.iterdir()) == before, "a refused command left something behind"
    assert leftovers(root) == []


FOLLOWED = [
    Row(5, "simulate -o dangling link: written where it points",
        lambda r: ["simulate", r / "gt", "-o", r / "dangling", "--crop", 32], setup=lambda r: None),
    Row(5, "demosaic -o dangling link: written where it points",
        lambda r: ["demosaic", r / "raw.png", "-o", r / "dangling"]),
    Row(5, "simulate -o dangling link --overwrite: written where it points",
        lambda r: ["simulate", r / "gt", "-o", r / "dangling", "--crop", 32, "--overwrite"]),
    Row(5, "demosaic -o dangling link --overwrite: written where it points",
        lambda r: ["demosaic", r / "raw.png", "-o", r / "dangling", "--overwrite"]),
    Row(5, "simulate -o link to a folder --overwrite: replaced where it points",
        lambda r: ["simulate", r / "gt", "-o", r / "dangling", "--crop", 32, "--overwrite"],
        setup=lambda r: (r / "elsewhere" / "out").mkdir(parents=True)),
    Row(5, "demosaic -o link to a folder --overwrite: replaced where it points",
        lambda r: ["demosaic", r / "raw.png", "-o", r / "dangling", "--overwrite"],
        setup=lambda r: (r / "elsewhere" / "out").mkdir(parents=True)),
]


@pytest.mark.parametrize("row", FOLLOWED, ids=[f"class{r.cls}-{r.name}" for r in FOLLOWED])
def test_links_to_a_usable_place_are_followed(row, root, capsys, monkeypatch):
    assert row.cls == 5
    row.setup(root)
    status, err = run_cli(row.args(root), capsys, monkeypatch, quiet=True)
    assert status == 0, err
    assert (root / "dangling").is_symlink() and (root / "elsewhere" / "out").is_dir()
    assert any((root / "elsewhere" / "out").iterdir())
    assert leftovers(root) == []


# -- an OSError while writing: one line naming the output and the error, nothing half-written ------------------
def _fail_tiff(code: int):
    def imwrite(path, *args, **kwargs):
        Path(path).write_bytes(b"half")  # as a real writer would, before the disk filled up
        raise OSError(code, os.strerror(code))

    return "tifffile.imwrite", imwrite


def _fail_fsync(code: int):
    def fsync(fd):
        raise OSError(code, os.strerror(code))

    return "os.fsync", fsync


def _fail_rename(code: int):
    """The last step fails: the complete temporary folder cannot be renamed into place."""
    real_replace = os.replace

    def replace(src, dst, **kwargs):
        if ".tmp-" in Path(src).name and Path(src).is_dir():
            raise OSError(code, os.strerror(code), str(src), None, str(dst))
        return real_replace(src, dst, **kwargs)

    return "os.replace", replace


FAILING = {"tiff": _fail_tiff, "fsync": _fail_fsync, "rename": _fail_rename}

WRITE_FAILS = [
    Row(5, "simulate --overwrite, final rename fails: the old capture stays",
        lambda r: ["simulate", r / "gt", "-o", r / "cap", "--crop", 32, "--overwrite", "--seed", 3],
        ("-o/--output", "cap", "No space left on device, ENOSPC"), "rename:28"),
    Row(5, "demosaic, final rename fails (EIO)", lambda r: ["demosaic", r / "raw.png", "-o", r / "new"],
        ("-o/--output", "new", f"{os.strerror(errno.EIO)}, EIO"), "rename:5"),
    Row(5, "demosaic, disk full while writing JSON", lambda r: ["demosaic", r / "raw.png", "-o", r / "new"],
        ("-o/--output", "new", "ENOSPC"), "fsync:28"),
    Row(5, "simulate, disk full (ENOSPC)", lambda r: ["simulate", r / "gt", "-o", r / "new", "--crop", 32],
        ("-o/--output", "new", "No space left on device, ENOSPC", "Free some disk space"), "tiff:28"),
    Row(5, "simulate, read-only file system (EROFS)", lambda r: ["simulate", r / "gt", "-o", r / "new", "--crop", 32],
        ("-o/--output", "Read-only file system, EROFS"), "tiff:30"),
    Row(5, "simulate, permission denied (EACCES)", lambda r: ["simulate", r / "gt", "-o", r / "new", "--crop", 32],
        ("-o/--output", "Permission denied, EACCES"), "tiff:13"),
    Row(5, "simulate --overwrite, disk full: the old capture stays",
        lambda r: ["simulate", r / "gt", "-o", r / "cap", "--crop", 32, "--overwrite", "--seed", 3],
        ("cap", "ENOSPC"), "tiff:28"),
    Row(5, "demosaic, disk full", lambda r: ["demosaic", r / "raw.png", "-o", r / "new"], ("new", "ENOSPC"), "tiff:28"),
    Row(5, "reconstruct, disk full", lambda r: ["reconstruct", r / "cap", "-m", "dofp-bilinear", "--no-progress"],
        ("recon", "dofp-bilinear.tiff", "ENOSPC"), "tiff:28"),
    Row(5, "evaluate, disk full", lambda r: ["evaluate", r / "cap"], ("metrics.json", "ENOSPC"), "fsync:28"),
    Row(5, "evaluate, quota exceeded (EDQUOT)", lambda r: ["evaluate", r / "cap"], ("metrics.json", "EDQUOT"),
        "fsync:122"),
]


@pytest.mark.parametrize("row", WRITE_FAILS, ids=[f"class{r.cls}-{r.name}" for r in WRITE_FAILS])
def test_a_failed_write_is_one_line_and_leaves_nothing_half_written(row, root, capsys, monkeypatch):
    assert row.cls == 5
    if "evaluate" in row.name:  # a reconstruction to score
        status, err = run_cli(["reconstruct", root / "cap", "-m", "dofp-bilinear", "--no-progress"], capsys,
                              monkeypatch, quiet=True)
        assert status == 0, err
    snapshot = {p: p.read_bytes() for p in (root / "cap").rglob("*") if p.is_file()}
    writer, code = row.forbid.split(":")
    monkeypatch.setattr(*FAILING[writer](int(code)))
    line = one_error_line(*run_cli(row.args(root), capsys, monkeypatch, quiet=True), *row.fragments)
    assert ".tmp-" not in line  # the message names the output, not a temporary
    assert not (root / "new").exists()
    assert {p: p.read_bytes() for p in (root / "cap").rglob("*") if p.is_file()} == snapshot
    assert leftovers(root) == []


def test_an_os_error_no_writer_named_is_still_one_line(root, capsys, monkeypatch):
    """The entry point's last resort: an OSError from anywhere is one line, exit 2 (class 5)."""
    def broken(*args, **kwargs):
        raise OSError(errno.EIO, os.strerror(errno.EIO), str(root / "somewhere"))

    monkeypatch.setattr("capssim.simulate.simulate_capture", broken)
    one_error_line(*run_cli(["simulate", root / "gt", "-o", root / "new", "--crop", 32], capsys, monkeypatch,
                            quiet=True), "somewhere", "Input/output error, EIO")


# -- the helper itself ------------------------------------------------------------------------------------------
def test_resolve_output_follows_links_and_refuses_what_is_in_the_way(tmp_path):
    (tmp_path / "folder").mkdir()
    (tmp_path / "file").write_text("x")
    (tmp_path / "to-folder").symlink_to(tmp_path / "folder")
    (tmp_path / "to-missing").symlink_to(tmp_path / "new" / "out")
    assert resolve_output(tmp_path / "to-folder", overwrite=True) == tmp_path / "folder"
    assert resolve_output(tmp_path / "to-missing") == tmp_path / "new" / "out"
    assert resolve_output(tmp_path / "to-missing", kind="file") == tmp_path / "new" / "out"
    assert resolve_output("relative/out") == Path("relative/out")  # no link: as given
    for path, kind, overwrite, fragment in [
        (tmp_path / "folder", "folder", False, "pass --overwrite"),
        (tmp_path / "file", "folder", True, "an existing file"),
        (tmp_path / "folder", "file", True, "an existing folder"),
        (tmp_path / "file", "file", False, "does not exist yet"),
        (tmp_path / "file" / "below", "folder", False, "under the existing file"),
    ]:
        with pytest.raises(InputError, match=fragment):
            resolve_output(path, kind=kind, overwrite=overwrite)
    (tmp_path / "a").symlink_to("b")
    (tmp_path / "b").symlink_to("a")
    with pytest.raises(InputError, match="loops back"):
        follow_links(tmp_path / "a" / "out")
    with pytest.raises(ValueError):
        resolve_output(tmp_path / "x", kind="archive")


def test_check_files_in_refuses_folders_in_the_way_and_ignores_a_missing_folder(tmp_path):
    check_files_in(tmp_path / "missing", ["metrics.json"], argument="CAPTURE")  # left to the command's own check
    (tmp_path / "recon" / "m.json").mkdir(parents=True)
    check_files_in(tmp_path, ["metrics.json", "recon/m.tiff"], argument="CAPTURE")
    with pytest.raises(InputError, match=r"CAPTURE: got '.*recon/m.json', an existing folder"):
        check_files_in(tmp_path, ["recon/m.json"], argument="CAPTURE")


@pytest.mark.parametrize("code, words", [(errno.ENOSPC, "Free some disk space"), (errno.EROFS, "read-only"),
                                         (errno.ENAMETOOLONG, "shorter name"), (errno.EIO, "Choose another path")])
def test_write_error_names_the_path_the_errno_and_a_fix(code, words):
    error = write_error("out/x.tiff", OSError(code, os.strerror(code)), argument="-o/--output")
    message = str(error)
    assert "\n" not in message and "'out/x.tiff'" in message and errno.errorcode[code] in message
    assert os.strerror(code) in message and words in message
    assert error.os_error.errno == code and error.path == Path("out/x.tiff")
