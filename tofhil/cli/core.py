"""``tofhil info`` and ``tofhil depth``: the core commands."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from tofhil.cli import app, lit, out, print_json, progress
from tofhil.cli import options as opt
from tofhil.errors import TofhilError


@app.command()
def info(session: Path = typer.Argument(..., parser=opt.existing_file, help="A session file (.h5)."),
         as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table.")) -> None:
    """Show a session's device, camera, frames, frequencies and datasets."""
    from tofhil.session import open_session

    with open_session(session) as s:
        summary = s.summary()
    if as_json:
        print_json(summary)
        return
    cam = summary["camera"]
    out.print(f"[bold]{lit(summary['path'])}[/bold]  (format v{summary['format_version']}, "
              f"{lit(summary['software_version'])}, created {lit(summary['created_utc'])})")
    out.print(f"device    {lit(json.dumps(summary['device']))}")
    out.print(f"camera    {lit(cam.get('name') or '-')} {cam['width']}x{cam['height']}  fx={cam['fx']:.2f} "
              f"fy={cam['fy']:.2f} cx={cam['cx']:.2f} cy={cam['cy']:.2f} {cam.get('model', 'plumb_bob')} "
              f"dist={cam['dist']}")
    out.print(f"frames    {summary['n_frames']}   raw={summary['has_raw']} depth={summary['has_depth']} "
              f"scene={'embedded' if summary['scene'] else 'none'}")
    if summary["has_raw"]:
        out.print(f"freq_hz   {summary['freq_hz']}   theta_deg {summary['theta_deg']}   "
                  f"integration {summary['integration_time_s'] * 1e6:.1f} us")
    for name, shape in summary["datasets"].items():
        out.print(f"  {name:24s} {shape}", markup=False)


@app.command()
def depth(session: Path = typer.Argument(..., parser=opt.existing_file, help="A session with raw taps."),
          out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="The session to write (raw + depth)."),
          min_amplitude: float = typer.Option(0.0, parser=opt.finite(0.0, unit="DN"),
                                              help="Pixels with lower amplitude are invalid."),
          margin: float = typer.Option(0.5, parser=opt.finite(0.0, 1.0, lo_open=True),
                                       help="Unwrapping conflict margin (0..1 of the decision spacing)."),
          force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists.")) -> None:
    """Demodulate and unwrap raw taps into radial distance, amplitude and validity."""
    from tofhil.depth import depth_from_raw
    from tofhil.session import SessionWriter, open_session

    if out_path.resolve() == session.resolve():
        raise TofhilError("the output must differ from the input", file=out_path)
    with open_session(session, need_frames=True) as s:
        if not s.has_raw:
            raise TofhilError("has no raw taps to demodulate", file=session, field="raw/taps")
        with SessionWriter(out_path, s.camera, device=s.device, scene_text=s.scene_text, force=force,
                           derived=True, tap_dtype=s.integer_tap_dtype) as w:  # (taps copied as stored)
            for raw in progress(s.raw_frames(), s.n_frames, "demodulating"):
                w.append(raw, depth_from_raw(raw, min_amplitude=min_amplitude, margin=margin))
            n = w.n_frames
    out.print(f"wrote {n} frames with depth to {lit(out_path)}")
