"""``tofhil import``: real captures from other tools -> tofhil sessions."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from tofhil.cli import app, console, lit, out
from tofhil.cli import options as opt


@app.command("import")
def import_(file: Path = typer.Argument(..., parser=opt.existing_file,
                                        help="The capture: ADI .bin (interleaved or *_depth*.bin "
                                                  "with its *_ir*.bin), Azure Kinect .mkv, or a tofhil session."),
            out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="The session file to write (.h5)."),
            camera: Optional[str] = typer.Option(None, "--camera", help="Camera preset name or YAML file "
                                                 "(default: the file's own calibration, or an assumed preset)."),
            fmt: Optional[str] = typer.Option(None, "--format", help="Force the format: adi-interleaved | "
                                              "adi-pair | k4a-mkv | session (default: detected)."),
            salvage: bool = typer.Option(False, "--salvage", help="Import the complete frames of a "
                                         "truncated recording instead of refusing it."),
            adi_max_confidence: Optional[int] = typer.Option(None, "--adi-max-confidence", parser=opt.count(0, 255),
                                                             help="ADI: mark "
                                                             "pixels whose confidence byte exceeds N invalid."),
            force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists.")) -> None:
    """Turn a real capture into a session: radial depth (m), amplitude, validity, camera model."""
    from tofhil.drivers.importers.dispatch import import_file

    def on_frame(i: int, n: int) -> None:
        if console.is_terminal and (i == n or i % 10 == 0):
            console.print(f"imported {i}/{n} frames", end="\r")

    result = import_file(file, out_path, camera=camera, force=force, fmt=fmt, salvage=salvage,
                         adi_max_confidence=adi_max_confidence, on_frame=on_frame)
    cam = result.camera
    out.print(f"wrote {result.n_frames} frame(s) from {lit(file)} ({lit(result.format)}) to {lit(result.out)}")
    out.print(f"camera {lit(cam.name or '-')} {cam.width}x{cam.height} fx={cam.fx:.2f} fy={cam.fy:.2f} "
              f"cx={cam.cx:.2f} cy={cam.cy:.2f} {cam.distortion_model} dist={[round(v, 6) for v in cam.dist]}")
    for note in result.notes:
        out.print(f"note: {lit(note)}")
