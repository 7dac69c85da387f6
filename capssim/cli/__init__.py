"""The ``capssim`` command line: one app, one module per group of subcommands.

Every module ``capssim.cli.<name>`` defines ``register(app)``; they are discovered
automatically. The command line is the top floor: nothing imports it, and it imports every
floor below it. Modules that pull torch (the capture format, the reconstruction, the
evaluation, the benchmarks) are imported inside the command functions, so start-up and
``--help`` stay fast.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import sys

import typer

from capssim.errors import CapssimError

app = typer.Typer(
    name="capssim",
    help="Camera-array colour-polarization super-resolution: simulate, render, reconstruct, score.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages."),
          quiet: bool = typer.Option(False, "--quiet", "-q", help="Log warnings and errors only.")) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", force=True)


def _register_all() -> None:
    modules = sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))
    for name in modules:
        module = importlib.import_module(f"{__name__}.{name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(app)


_register_all()


def main() -> None:
    """Console entry point: user errors print one clear line and exit with status 2."""
    try:
        app()
    except CapssimError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except OSError as exc:  # a file-system error no writer named (capssim.files.output_paths): still one line
        from capssim.files.output_paths import describe_os_error

        where = f" ({exc.filename})" if exc.filename else ""
        typer.echo(f"error: file system{where}: {describe_os_error(exc)}.", err=True)
        sys.exit(2)
