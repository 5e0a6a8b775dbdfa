"""The ``tofhil`` command line: one typer app, one module per command group.

This package is the only place that prints or draws progress; library code takes a
:class:`tofhil.progress.Progress` callable instead. Each command group registers its commands
on ``app`` when imported (``COMMAND_MODULES``). User errors (:class:`tofhil.errors.TofhilError`)
print one message and exit with code 2, no traceback.
"""

from __future__ import annotations

import importlib
import sys
from typing import Iterable, Iterator, Optional, TypeVar

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from tofhil import __version__
from tofhil.errors import TofhilError

app = typer.Typer(name="tofhil", add_completion=False, no_args_is_help=True,
                  pretty_exceptions_enable=False,
                  help="Hardware-in-the-loop evaluation of ToF cameras with a simulator twin.")
console = Console(stderr=True)
out = Console()

T = TypeVar("T")

#: Modules that register further commands on ``app`` when imported.
COMMAND_MODULES: list[str] = ["tofhil.cli.core", "tofhil.cli.imports", "tofhil.cli.ndt", "tofhil.cli.evaluate",
                              "tofhil.cli.simulate", "tofhil.cli.devices", "tofhil.cli.diagnose"]


def progress(items: Iterable[T], total: int, description: str) -> Iterator[T]:
    """Iterate with a progress bar on stderr (hidden when stderr is not a terminal)."""
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), console=console, transient=False,
                  disable=not console.is_terminal) as bar:
        task = bar.add_task(description, total=total)
        for item in items:
            yield item
            bar.advance(task)


def _version_callback(value: bool) -> None:
    if value:
        out.print(f"tofhil {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: Optional[bool] = typer.Option(None, "--version", callback=_version_callback,
                                                 is_eager=True, help="Show the version and exit.")) -> None:
    """tofhil: capture, simulate, compare and diagnose ToF cameras."""


def _register_command_modules() -> None:
    for name in COMMAND_MODULES:
        importlib.import_module(name)


def main(argv: list[str] | None = None) -> None:
    """Entry point: run the CLI; user errors exit 2 with one line on stderr."""
    _register_command_modules()
    try:
        app(args=argv, prog_name="tofhil")
    except TofhilError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        console.print("interrupted")
        sys.exit(130)
