"""Issue 33, item 3: one command-line grammar, checked over EVERY command of the Typer app (walked by
click introspection, so a command added later is checked too), and the CLI guide (docs/guides/cli.md)
documents exactly the commands that ``capssim --help`` and ``capssim bench --help`` list.

The grammar (docs/guides/cli.md, "The grammar"):

1. inputs are positional: an option that takes a path is either ``-o/--output`` or one of the
   auxiliary paths of :data:`AUXILIARY_PATHS` (a secondary output or a helper file, never the
   command's input), and no option is named like an input (:data:`INPUT_NAMES`);
2. ``-o/--output`` is what the command makes: ``-o`` always goes with ``--output`` and is never
   "also" a copy of something else;
3. ``--json`` is a flag that prints JSON to stdout; no other option mentions JSON in its name;
4. one name per concept: a short flag means one long option everywhere, and none of the retired
   synonyms (:data:`RETIRED`) remains;
5. lists by repetition: an option whose help mentions commas, or a text option with a plural name,
   is repeatable, unless it is one value with a fixed number of components (:data:`VECTORS`); a
   repeatable option says so in its help ("repeat");
6. ``--threads`` and ``--device`` on every command, with the same choices and default;
7. no hidden commands or options.
"""

from __future__ import annotations

import re
import typing
from pathlib import Path

import click
import pytest
import typer.main
from typer.testing import CliRunner

from capssim.cli import app
from capssim.cli._options import DEFAULT_DEVICE, DEVICE_HELP, DEVICES
from capssim.errors import InputError

REPO = Path(__file__).resolve().parents[2]
GUIDE = REPO / "docs" / "guides" / "cli.md"

#: (command, option) -> why that option takes a path although inputs are positional
AUXILIARY_PATHS = {
    ("bench budget", "--results-page"): "a secondary output: the Markdown results page",
    ("bench reconstruct", "--plot"): "a secondary output: the PNG of time and memory against the pixel count",
    ("bench budget", "--cache"): "a cache folder of captures (default: OUTPUT/cache)",
    ("bench uncertainty", "--cache"): "a cache folder of captures (default: OUTPUT/cache)",
    ("bench suite", "--check"): "a baseline to compare the run with (a reference, not the input)",
    ("bench suite", "--update-baseline"): "a second output: the run's metrics as the new baseline",
    ("bench suite", "--results-page"): "a second output: the Markdown results page",
    ("bench suite", "--cache"): "a cache folder of captures (default: OUTPUT/cache)",
    ("bench map", "--cache"): "a cache folder of captures (default: OUTPUT/cache)",
    ("bench registration", "--content-alignment"): "a helper record (gt-check --json) of the captures' ground truth",
    ("bench dataset", "--keep"): "a second output: where the generated datasets are kept",
    ("calibrate", "--report"): "a second output: plots and a summary",
    ("evaluate", "--lpips-weights"): "network weights for one metric (never downloaded)",
    ("evaluate", "--plots"): "a second output: the error-bar plots (PNG) of reconstructions with uncertainty files",
    ("gt-check", "--write-aligned"): "a second output: the aligned ground truth",
    ("render", "--preview"): "a second output: a preview PNG of the ground truth",
}

#: option names that would smuggle an input past the positional arguments
INPUT_NAMES = {"--gt", "--input", "--in", "--capture", "--captures", "--config", "--image", "--raw", "--source"}

#: (command, option) -> a text option with a plural name or commas that is ONE value with fixed components
VECTORS = {
    ("reconstruct", "--options"): "one method name, whose options are listed (not a list)",
    ("*", "--angle-offsets"): "the 4 apertures' polarizer angle errors a,b,c,d",
    ("*", "--gains"): "the 4 cameras' gains a,b,c,d",
    ("*", "--aperture-psf-sigmas"): "the 4 apertures' PSF widths a,b,c,d",
    ("*", "--extinction-ratios"): "1, 3 (R,G,B) or 12 (aperture x colour) extinction ratios of one rig",
    ("mtf", "--center"): "one point ROW,COL",
    ("bench render", "--samplers"): "one scene name (the sampler comparison's scene)",
}

#: spellings retired in 0.2.0 (CHANGELOG.md): none may come back
RETIRED = {"--layout", "--mode", "--option", "-O", "--methods", "--scenes", "--compute-threads", "--gt",
           "--channels", "--gt-root"}

#: short flag -> the one long option it abbreviates, wherever it appears
SHORT_FLAGS = {"-o": "--output", "-m": "--method", "-p": "--param", "-w": "--workers", "-v": "--verbose",
               "-q": "--quiet"}


def _walk(command, path: str = ""):
    """``(path, command)`` for every command and group below ``command`` (itself included). Duck-typed:
    typer may build on click or on its own copy of click."""
    yield path, command
    for name, sub in getattr(command, "commands", {}).items():
        yield from _walk(sub, f"{path} {name}".strip())


ROOT = typer.main.get_command(app)
ALL = list(_walk(ROOT))
LEAVES = [(path, cmd) for path, cmd in ALL if not hasattr(cmd, "commands")]
OPTIONS = [(path, p) for path, cmd in LEAVES for p in cmd.params if p.param_type_name == "option"]


def _long(param) -> str:
    longs = [o for o in param.opts if o.startswith("--")]
    return longs[0] if longs else param.opts[0]


def _base_annotation(param):
    """The value type of ``param`` with ``Optional[...]`` and ``List[...]`` taken off."""
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is None:  # plain click (another typer): the click type says it
        return Path if isinstance(param.type, click.Path) else None
    annotation = descriptor.annotation
    while typing.get_origin(annotation) in (typing.Union, list, tuple) and typing.get_args(annotation):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        annotation = args[0]
    return annotation


def _is_path(param) -> bool:
    annotation = _base_annotation(param)
    return isinstance(annotation, type) and issubclass(annotation, Path)


def _listed(table: dict, path: str, name: str):
    return table.get((path, name), table.get(("*", name)))


def test_the_walk_sees_every_command():
    names = {path for path, _ in LEAVES}
    assert {"simulate", "render", "reconstruct", "evaluate", "bench suite", "bench dofp"} <= names
    assert len(LEAVES) >= 19 and len(OPTIONS) > 100


def test_no_hidden_commands_or_options():
    assert [path for path, cmd in ALL if cmd.hidden] == []
    assert [(path, p.name) for path, p in OPTIONS if p.hidden] == []


def test_o_is_the_output_and_only_the_output():
    for path, p in OPTIONS:
        assert ("-o" in p.opts) == ("--output" in p.opts), (path, p.opts)
        if "--output" in p.opts:
            assert not (p.help or "").lower().startswith("also"), (path, "-o is what the command makes", p.help)


def test_json_is_a_flag_that_prints_to_stdout():
    seen = 0
    for path, p in OPTIONS:
        if any("json" in o.lower() for o in p.opts):
            assert p.opts == ["--json"] and p.is_flag and p.default is False, (path, p.opts)
            assert "stdout" in (p.help or ""), (path, p.help)
            seen += 1
    assert seen >= 10


def test_one_name_per_concept():
    for path, p in OPTIONS:
        assert not set(p.opts) & RETIRED, (path, p.opts)
        for short in (o for o in p.opts if re.fullmatch(r"-[A-Za-z]", o)):
            assert SHORT_FLAGS.get(short) == _long(p), (path, short, p.opts)


def test_lists_are_given_by_repetition():
    for path, p in OPTIONS:
        if p.is_flag:
            continue
        name, text = _long(p), (p.help or "").lower()
        plural_text = name.rsplit("-", 1)[-1].endswith("s") and _base_annotation(p) is str
        if ("comma" in text or plural_text) and not p.multiple:
            assert _listed(VECTORS, path, name), (path, name, "a list: make it repeatable (multiple=True)")
        assert p.multiple == ("repeat" in text), (path, name, "a repeatable option says so in its help")


def test_vector_and_auxiliary_tables_name_existing_options():
    present = {(path, _long(p)) for path, p in OPTIONS}
    present_names = {name for _, name in present}
    for table in (AUXILIARY_PATHS, VECTORS):
        for path, name in table:
            assert ((path, name) in present) if path != "*" else (name in present_names), (path, name, "stale")


def test_inputs_are_positional():
    for path, p in OPTIONS:
        name = _long(p)
        assert name not in INPUT_NAMES, (path, name, "an input is a positional argument")
        if _is_path(p) and name != "--output":
            assert (path, name) in AUXILIARY_PATHS, (path, name, "a path option that is not -o/--output")


@pytest.mark.parametrize("path, command", LEAVES, ids=[path for path, _ in LEAVES])
def test_every_command_takes_threads_and_device_alike(path, command):
    params = {p.name: p for p in command.params if p.param_type_name == "option"}
    by_flag = {_long(p): p for p in params.values()}
    threads, device = by_flag.get("--threads"), by_flag.get("--device")
    assert threads is not None and device is not None, path
    assert threads.default is None and not threads.multiple and _base_annotation(threads) is int
    assert device.metavar == "|".join(DEVICES) and (device.help or "").startswith(DEVICE_HELP), path
    assert device.default == ([DEFAULT_DEVICE] if device.multiple else DEFAULT_DEVICE), path
    ctx = command.context_class(command)
    for choice in DEVICES:
        value = [choice.upper()] if device.multiple else choice.upper()
        assert device.process_value(ctx, value) == ([choice] if device.multiple else choice), path
    with pytest.raises(InputError, match="--device"):
        device.process_value(ctx, ["gpu"] if device.multiple else "gpu")
    with pytest.raises(InputError, match="--threads"):  # one line, not click's usage block
        threads.process_value(ctx, 0)
    assert threads.process_value(ctx, 1) == 1, path


def test_a_bad_device_is_one_line_naming_the_option():
    result = CliRunner().invoke(app, ["design", "--device", "gpu"])
    assert isinstance(result.exception, InputError)
    assert str(result.exception).count("\n") == 0
    assert "--device" in str(result.exception) and "auto | cpu | cuda" in str(result.exception)


def _help_commands(args: list[str]) -> set[str]:
    out = CliRunner().invoke(app, [*args, "--help"]).output
    section = out.split("Commands:", 1)[1]
    return {m.group(1) for m in re.finditer(r"^  ([a-z][a-z0-9-]*)", section, re.MULTILINE)}


def _guide_commands() -> set[str]:
    """The commands the CLI guide's "Commands" table documents: rows ``| `capssim NAME ...` |``."""
    text = GUIDE.read_text()
    table = text.split("## Commands", 1)[1].split("\n## ", 1)[0]
    return {m.group(1) for m in re.finditer(r"^\| `capssim ((?:bench )?[a-z][a-z0-9-]*)", table, re.MULTILINE)}


def test_help_and_the_cli_guide_list_the_same_commands():
    documented = _guide_commands()
    top = _help_commands([])
    bench = {f"bench {name}" for name in _help_commands(["bench"])}
    assert documented == (top - {"bench"}) | bench
    assert {path for path, _ in LEAVES} == documented
