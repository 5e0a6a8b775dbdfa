"""The ``tofhil`` command line: one typer app, one module per command group.

This package is the only place that prints or draws progress; library code takes a
:class:`tofhil.progress.Progress` callable instead. Each command group registers its commands
on ``app`` when imported (``COMMAND_MODULES``). User errors (:class:`tofhil.errors.TofhilError`)
print one message and exit with code 2, no traceback; so do usage errors (a bad option value,
a missing argument) and files that cannot be written. User values (file names, device specs)
are printed literally: the consoles interpret no emoji codes and every user value goes
through :func:`lit` (rich markup such as ``[bold red]`` in a file name stays text).
Option values are coerced by the options' own parsers (:mod:`tofhil.cli.coercion`), not by
typer's pydantic adapters, which would cost every command ~0.15 CPU-s of imports.
"""

from __future__ import annotations

import errno
import importlib
import json
import os
import shutil
import signal
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator, Optional, TypeVar

import typer

from tofhil.cli import coercion
from tofhil.errors import Interrupted, TofhilError

if TYPE_CHECKING:
    from rich.console import Console


class _LazyConsole:
    """A rich ``Console`` made when first used (attributes and methods are the console's).
    Importing rich.console costs ~0.02 CPU-s, which a command that prints only JSON into a
    pipe (``tofhil ndt --json``, timed against PCL as a whole process) does not need."""

    def __init__(self, **kwargs: Any) -> None:
        object.__setattr__(self, "_kwargs", kwargs)
        object.__setattr__(self, "_console", None)

    def rich_console(self) -> "Console":
        """The console itself (for rich APIs that take one)."""
        made = object.__getattribute__(self, "_console")
        if made is None:
            from rich.console import Console

            made = Console(**object.__getattribute__(self, "_kwargs"))
            object.__setattr__(self, "_console", made)
        return made

    def __getattr__(self, name: str) -> Any:
        return getattr(self.rich_console(), name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self.rich_console(), name, value)


app = typer.Typer(name="tofhil", add_completion=False, no_args_is_help=True,
                  pretty_exceptions_enable=False,
                  help="Hardware-in-the-loop evaluation of ToF cameras with a simulator twin.")
console = _LazyConsole(stderr=True, emoji=False)
out = _LazyConsole(emoji=False)

T = TypeVar("T")

#: Modules that register further commands on ``app`` when imported.
COMMAND_MODULES: list[str] = ["tofhil.cli.core", "tofhil.cli.imports", "tofhil.cli.ndt", "tofhil.cli.evaluate",
                              "tofhil.cli.simulate", "tofhil.cli.devices", "tofhil.cli.diagnose",
                              "tofhil.cli.sweep", "tofhil.cli.calibrate", "tofhil.cli.scene_from_capture",
                              "tofhil.cli.model", "tofhil.cli.view", "tofhil.cli.bench"]


def lit(value: object) -> str:
    """A user value (file name, spec, scene name) as rich markup that prints it literally."""
    from rich.markup import escape

    return escape(str(value))


def print_json(data: object) -> None:
    """``data`` as JSON on stdout, indented by 2: highlighted by rich on a terminal; into a
    pipe or file the same text without rich (its import is most of a short command's
    output cost), as a program reading it wants it."""
    if sys.stdout.isatty():
        out.print_json(json.dumps(data))
    else:  # what rich's print_json writes there: its dumps, soft-wrapped (never folded), a newline
        sys.stdout.write(json.dumps(data, indent=2, ensure_ascii=False) + "\n")


#: Set by the CLI's SIGINT handler. Python raises KeyboardInterrupt wherever the main thread
#: is; when that is a weakref callback or a ``__del__`` (h5py releases its objects there) the
#: exception is printed as "ignored" and lost, and a long simulate went on for its million
#: frames. The long loops (every :func:`progress` step) raise it again from this flag.
_INTERRUPT = {"requested": False}


def on_interrupt_signal(signum: int, frame: object) -> None:
    """Ctrl-C or SIGTERM: raise KeyboardInterrupt now, and remember it for :func:`check_interrupt`."""
    _INTERRUPT["requested"] = True
    raise KeyboardInterrupt


def _unraisable(report: "sys.UnraisableHookArgs") -> None:
    # A KeyboardInterrupt raised inside a weakref callback or __del__ is not lost any more
    # (the flag re-raises it): do not print it as an ignored exception.
    if not isinstance(report.exc_value, KeyboardInterrupt):
        sys.__unraisablehook__(report)


def check_interrupt() -> None:
    """Raise KeyboardInterrupt if Ctrl-C was pressed, even if its first raise was lost."""
    if _INTERRUPT["requested"]:
        raise KeyboardInterrupt


def progress(items: Iterable[T], total: int, description: str) -> Iterator[T]:
    """Iterate with a progress bar on stderr (hidden when stderr is not a terminal); each
    step is a place where an interrupt is honoured (:func:`check_interrupt`)."""
    # imported here: ~0.02 CPU-s that a command without a progress bar does not need
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(TextColumn("{task.description}", markup=False), BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), console=console.rich_console(), transient=False,
                  disable=not console.is_terminal) as bar:
        task = bar.add_task(description, total=total)
        for item in items:
            check_interrupt()
            yield item
            check_interrupt()
            bar.advance(task)


@contextmanager
def new_output_dir(path: Path) -> Iterator[Path]:
    """Run a command writing into ``path``: if the directory did not exist and the command
    fails (or is interrupted), the directory it created is removed, so that a rerun is not
    blocked by an empty or half-written folder. An existing directory is left as it is."""
    existed = path.exists()
    try:
        yield path
    except BaseException:
        if not existed and path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        raise


def _version_callback(value: bool) -> None:
    if value:
        from tofhil import __version__  # here: importlib.metadata costs every other command ~0.03 CPU-s

        out.print(f"tofhil {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: Optional[bool] = typer.Option(None, "--version", callback=_version_callback,
                                                 is_eager=True, help="Show the version and exit.")) -> None:
    """tofhil: capture, simulate, compare and diagnose ToF cameras."""
    from tofhil.app.emulators import connect_emulators

    connect_emulators()  # emulator[:SCENE] and depthai-sim[:SCENE] render through the twin


#: Commands that run with their own module alone: every other command module costs imports
#: (~0.07 CPU-s together) that a short command such as ``tofhil ndt`` (timed against PCL as a
#: whole process) does not need. Help and every other command register all modules.
_COMMAND_HOME: dict[str, str] = {"ndt": "tofhil.cli.ndt"}


def _register_command_modules(args: list[str] | None = None) -> None:
    home = _COMMAND_HOME.get(args[0]) if args else None
    for name in [home] if home else COMMAND_MODULES:
        importlib.import_module(name)


def _click_exceptions():  # typer >= 0.20 vendors click as typer._click
    try:
        from typer._click import exceptions
    except ImportError:  # pragma: no cover - older typer on click
        from click import exceptions
    return exceptions


def error_line(message: str) -> None:
    """Print ``error: MESSAGE`` as one line on stderr, the message taken literally."""
    from rich.text import Text

    text = " ".join(str(message).split())  # one line, whatever the message held
    console.print(Text("error: ", style="red") + Text(text), soft_wrap=True, highlight=False)


def _usage_message(exc: Exception) -> str:
    msg = exc.format_message()
    msg = msg.replace("Value error, ", "")  # pydantic's prefix, where typer's own coercion ran a parser
    ctx = getattr(exc, "ctx", None)
    command = getattr(ctx, "command_path", "") if ctx is not None else ""
    return f"{command}: {msg}" if command and command != "tofhil" else msg


def main(argv: list[str] | None = None) -> None:
    """Entry point: run the CLI.

    User errors, usage errors and unwritable outputs exit 2 with one line on stderr; an
    interrupt exits 130 saying what was kept.
    """
    args = sys.argv[1:] if argv is None else list(argv)
    _register_command_modules(args)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not when started ignoring it (nohup)
        signal.signal(signal.SIGINT, on_interrupt_signal)
        sys.unraisablehook = _unraisable
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        # SIGTERM (kill, a cluster's scheduler, systemd) ends every command as Ctrl-C does: a
        # writer keeps its completed frames or removes its partial file, instead of dying silently
        # and leaving .OUT.PID.partial behind
        signal.signal(signal.SIGTERM, on_interrupt_signal)
        sys.unraisablehook = _unraisable
    ex = _click_exceptions()
    command = typer.main.get_command(app)
    coercion.install(command)  # the options' parsers without typer's pydantic adapters (~0.15 CPU-s)
    if not args:
        args = ["--help"]
    try:
        with command.make_context("tofhil", args) as ctx:
            command.invoke(ctx)
        sys.exit(0)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except ex.UsageError as exc:
        error_line(_usage_message(exc))
        _exit(2)
    except ex.ClickException as exc:
        error_line(exc.format_message())
        _exit(2)
    except typer.Abort:
        error_line("aborted")
        _exit(1)
    except TofhilError as exc:
        error_line(str(exc))
        _exit(2)
    except Interrupted as exc:
        from rich.text import Text

        console.print(Text(str(exc)), soft_wrap=True, highlight=False)
        _exit(130)
    except KeyboardInterrupt:
        console.print("interrupted (nothing was written)", highlight=False)
        _exit(130)
    except OSError as exc:
        if exc.errno == errno.EPIPE:  # output piped into head: not an error
            _exit(0)
        if exc.errno in _USER_OS_ERRORS:
            # No file name: a library's own file (e.g. numba's compiled-kernel cache) on the same disk.
            where = exc.filename if exc.filename else "a file being written (disk or file-size limit)"
            error_line(f"{where}: {exc.strerror or exc}")
            _exit(2)
        raise


def _exit(code: int) -> None:
    """Exit with ``code``. After a failed HDF5 write (disk full) exit at once: outputs are
    already cleaned up, and the interpreter's shutdown would make HDF5 retry the write."""
    from tofhil import session

    if session.BROKEN_FILES:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass
        os._exit(code)
    sys.exit(code)


#: OS errors caused by the user's paths or disk, not by a bug: one line, exit 2.
_USER_OS_ERRORS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EFBIG, errno.EDQUOT,
                   errno.ENOENT, errno.EISDIR, errno.ENOTDIR, errno.EEXIST, errno.ENAMETOOLONG, errno.EIO}
