"""``tofhil scene-from-capture``: a twin scene built from a capture."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from tofhil.cli import app, console, lit, out
from tofhil.cli import options as opt
from tofhil.errors import TofhilError


def _frequencies(text: Optional[str]) -> list[float] | None:
    if not text:
        return None
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise TofhilError(f"got {text!r}", field="--freq-hz",
                          expected="modulation frequencies in Hz, comma-separated (e.g. 100e6 or 200e6,180e6)") from None
    if not values or not all(v > 0 and v < 1e10 for v in values):
        raise TofhilError(f"got {text!r}", field="--freq-hz", expected="positive frequencies in Hz below 10 GHz")
    return values


@app.command("scene-from-capture")
def scene_from_capture(session: Path = typer.Argument(..., parser=opt.existing_file,
                                                      help="A session with depth (and amplitude), e.g. from tofhil import."),
                       out_path: Path = typer.Option(..., "--out", help="The scene file to write (.yaml)."),
                       frame: int = typer.Option(0, "--frame", parser=opt.count(0, 10**9), help="Frame to build the scene from."),
                       max_planes: int = typer.Option(4, "--max-planes", parser=opt.count(0, 50),
                                                      help="Most planar patches to segment."),
                       freq_hz: Optional[str] = typer.Option(None, "--freq-hz",
                                                             help="Modulation frequencies (Hz, comma-separated) when the session records none."),
                       wavelength_m: Optional[float] = typer.Option(None, "--wavelength-m", parser=opt.finite(1e-7, 1e-5),
                                                                    help="Emitter wavelength (m) when neither session nor camera preset gives it."),
                       no_mesh: bool = typer.Option(False, "--no-mesh", help="Leave out the non-planar rest (no mesh file)."),
                       target: Optional[str] = typer.Option(None, "--target",
                                                            help="A board the capture shows, e.g. checkerboard:9x6:0.03 "
                                                                 "or a YAML file: its pose from the amplitude image."),
                       force: bool = typer.Option(False, "--force", help="Overwrite the scene and its sidecar files.")) -> None:
    """Build a twin scene from one frame: camera, planes, the rest as a mesh, fitted radiometry."""
    from tofhil.sim.from_capture import scene_from_capture as build

    res = build(session, out_path, frame=frame, max_planes=max_planes, freq_hz=_frequencies(freq_hz),
                wavelength_m=wavelength_m, mesh=not no_mesh, force=force, target=target,
                progress=lambda m: console.print(f"[dim]{lit(m)}[/dim]", highlight=False))
    for w in res.warnings:
        console.print(f"[yellow]warning:[/yellow] {lit(w)}", highlight=False)
    out.print(f"scene: {lit(res.scene_path)} ({len(res.planes)} planes"
              + (f", mesh {lit(res.mesh_path.name)}" if res.mesh_path else "") + ")")
    out.print(f"metadata: {lit(res.metadata_path)}; valid mask: {lit(res.valid_path)}")
    tgt = res.metadata.get("target")
    if tgt:
        T = tgt["board_to_camera"]
        out.print(f"board pose from the amplitude image: origin at ({T[0][3]:.4f}, {T[1][3]:.4f}, {T[2][3]:.4f}) m, "
                  f"{tgt['corners']} corners, reprojection {tgt['reprojection_rms_px']:.3f} px rms; range offset and "
                  "pose are observable against it")
    if res.metadata["unobservable"]:
        out.print("not observable with this scene (its planes were fitted to the same depth): "
                  + ", ".join(res.metadata["unobservable"]))
