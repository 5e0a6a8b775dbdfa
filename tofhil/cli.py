"""The ``tofhil`` command line.

Core commands live here; the drivers, the simulator twin and evaluation add theirs from
their own ``cli`` modules (listed in ``COMMAND_MODULES``). User errors
(:class:`tofhil.errors.TofhilError`) print one message and exit with code 2, no traceback.
"""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path
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
COMMAND_MODULES: list[str] = ["tofhil.drivers.import_cli", "tofhil.eval.ndt_cli", "tofhil.eval.cli", "tofhil.sim.cli", "tofhil.drivers.cli",
                              "tofhil.eval.diagnose_cli"]


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


@app.command()
def info(session: Path = typer.Argument(..., help="A session file (.h5)."),
         as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table.")) -> None:
    """Show a session's device, camera, frames, frequencies and datasets."""
    from tofhil.session import open_session

    with open_session(session) as s:
        summary = s.summary()
    if as_json:
        out.print_json(json.dumps(summary))
        return
    cam = summary["camera"]
    out.print(f"[bold]{summary['path']}[/bold]  (format v{summary['format_version']}, "
              f"{summary['software_version']}, created {summary['created_utc']})")
    out.print(f"device    {json.dumps(summary['device'])}")
    out.print(f"camera    {cam.get('name') or '-'} {cam['width']}x{cam['height']}  fx={cam['fx']:.2f} "
              f"fy={cam['fy']:.2f} cx={cam['cx']:.2f} cy={cam['cy']:.2f} dist={cam['dist']}")
    out.print(f"frames    {summary['n_frames']}   raw={summary['has_raw']} depth={summary['has_depth']} "
              f"scene={'embedded' if summary['scene'] else 'none'}")
    if summary["has_raw"]:
        out.print(f"freq_hz   {summary['freq_hz']}   theta_deg {summary['theta_deg']}   "
                  f"integration {summary['integration_time_s'] * 1e6:.1f} us")
    for name, shape in summary["datasets"].items():
        out.print(f"  {name:24s} {shape}")


@app.command()
def depth(session: Path = typer.Argument(..., help="A session with raw taps."),
          out_path: Path = typer.Option(..., "--out", help="The session to write (raw + depth)."),
          min_amplitude: float = typer.Option(0.0, help="Pixels with lower amplitude are invalid."),
          margin: float = typer.Option(0.5, help="Unwrapping conflict margin (0..1 of the decision spacing)."),
          force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists.")) -> None:
    """Demodulate and unwrap raw taps into radial distance, amplitude and validity."""
    from tofhil.depth import depth_from_raw
    from tofhil.session import SessionWriter, open_session

    if out_path.resolve() == session.resolve():
        raise TofhilError("the output must differ from the input", file=out_path)
    with open_session(session) as s:
        if not s.has_raw:
            raise TofhilError("has no raw taps to demodulate", file=session, field="raw/taps")
        with SessionWriter(out_path, s.camera, device=s.device, scene_text=s.scene_text, force=force) as w:
            for raw in progress(s.raw_frames(), s.n_frames, "demodulating"):
                w.append(raw, depth_from_raw(raw, min_amplitude=min_amplitude, margin=margin))
            n = w.n_frames
    out.print(f"wrote {n} frames with depth to {out_path}")


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


if __name__ == "__main__":
    # Run as ``python -m tofhil.cli``: this module is ``__main__``, while command modules
    # register on ``tofhil.cli.app``; call the canonical module so they are all there.
    from tofhil.cli import main as _main

    _main()
