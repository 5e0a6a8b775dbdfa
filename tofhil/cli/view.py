"""``tofhil view``: a session replayed in the Rerun viewer, or written as an ``.rrd`` file."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from tofhil.cli import app, console, lit, out, progress
from tofhil.cli import options as opt
from tofhil.errors import TofhilError


@app.command("view")
def view(session: Path = typer.Argument(..., parser=opt.existing_file, help="A session file (.h5)."),
         scene: Optional[str] = typer.Option(None, "--scene", help="A scene file or bundled scene name: also show "
                                             "the twin's render of it for the session's camera and the residual "
                                             "depth (measured - twin) per frame."),
         save: Optional[Path] = typer.Option(None, "--save", parser=opt.new_file,
                                             help="Write the view to this .rrd file instead of spawning the viewer "
                                                  "(headless; open it later with `rerun FILE.rrd`)."),
         spawn: bool = typer.Option(False, "--spawn", help="With --save: spawn the viewer as well."),
         force: bool = typer.Option(False, "--force", help="Overwrite the --save file if it exists.")) -> None:
    """Replay a session in the Rerun viewer (pip install 'tofhil\\[view]'): depth, amplitude, the point
    cloud, and with --scene the twin's render and the residual, frame by frame."""
    from tofhil.app.view import check_display, check_view_output, require_rerun, view_session

    require_rerun()
    if spawn and save is None:
        raise TofhilError("--spawn only adds the viewer to --save", field="--spawn",
                          expected="--save VIEW.rrd --spawn, or neither (the viewer alone)")
    if save is None or spawn:
        check_display("--spawn" if spawn else None)
    check_view_output(save, force)
    summary = view_session(session, scene=scene, save=save, spawn=save is None or spawn, progress=progress)
    where = f" to {lit(summary.saved)}" if summary.saved is not None else " in the viewer"
    out.print(f"logged {summary.shown} frame(s) of {lit(session)}{where}")
    if summary.twin:
        out.print(f"twin: {lit(summary.twin)}")
    if summary.error:
        console.print(f"view: {summary.error}", highlight=False, markup=False, soft_wrap=True)
