"""``tofhil import`` and ``tofhil export``: captures from other tools -> tofhil sessions, and
sessions (with the twin's render) -> ROS 2 MCAP bags for robotics tools such as Foxglove."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from tofhil.cli import app, check_interrupt, console, lit, out
from tofhil.cli import options as opt
from tofhil.errors import TofhilError


@app.command("import")
def import_(file: Path = typer.Argument(..., parser=opt.existing_file,
                                        help="The capture: ADI .bin (interleaved or *_depth*.bin "
                                                  "with its *_ir*.bin), Azure Kinect .mkv, ROS 2 bag .mcap, "
                                                  "or a tofhil session."),
            out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="The session file to write (.h5)."),
            camera: Optional[str] = typer.Option(None, "--camera", help="Camera preset name or YAML file "
                                                 "(default: the file's own calibration, or an assumed preset)."),
            fmt: Optional[str] = typer.Option(None, "--format", help="Force the format: adi-interleaved | "
                                              "adi-pair | k4a-mkv | ros2-mcap | session (default: detected)."),
            salvage: bool = typer.Option(False, "--salvage", help="Import the complete frames of a "
                                         "truncated recording instead of refusing it."),
            adi_max_confidence: Optional[int] = typer.Option(None, "--adi-max-confidence", parser=opt.count(0, 255),
                                                             help="ADI: mark "
                                                             "pixels whose confidence byte exceeds N invalid."),
            depth_topic: Optional[str] = typer.Option(None, "--depth-topic", help="ROS 2 bag: the depth Image "
                                                      "topic (16UC1 mm or 32FC1 m; default: the one depth-like topic)."),
            amplitude_topic: Optional[str] = typer.Option(None, "--amplitude-topic", help="ROS 2 bag: the IR / "
                                                          "amplitude Image topic (default: found by name and encoding)."),
            confidence_topic: Optional[str] = typer.Option(None, "--confidence-topic", help="ROS 2 bag: a "
                                                           "confidence Image topic (default: one named confidence)."),
            info_topic: Optional[str] = typer.Option(None, "--info-topic", help="ROS 2 bag: the depth camera's "
                                                     "CameraInfo topic (default: the only one, or the depth topic's)."),
            depth_kind: Optional[str] = typer.Option(None, "--depth-kind",
                                                     help="ROS 2 bag: what the depth images hold, z | radial "
                                                     "(default: the bag's tofhil metadata, else z as in ROS)."),
            force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists.")) -> None:
    """Turn a real capture into a session: radial depth (m), amplitude, validity, camera model."""
    from tofhil.drivers.importers.dispatch import import_file

    def on_frame(i: int, n: int) -> None:
        # each frame is where an interrupt is honoured: the KeyboardInterrupt that SIGTERM raises can
        # land in h5py's object finaliser and be lost, and the import then ran to its end (exit 0)
        check_interrupt()
        if console.is_terminal and (i == n or i % 10 == 0):
            console.print(f"imported {i}/{n} frames", end="\r")

    topics = {"depth": depth_topic, "amplitude": amplitude_topic, "confidence": confidence_topic, "info": info_topic}
    result = import_file(file, out_path, camera=camera, force=force, fmt=fmt, salvage=salvage,
                         adi_max_confidence=adi_max_confidence, topics=topics, depth_kind=depth_kind,
                         on_frame=on_frame)
    cam = result.camera
    out.print(f"wrote {result.n_frames} frame(s) from {lit(file)} ({lit(result.format)}) to {lit(result.out)}")
    out.print(f"camera {lit(cam.name or '-')} {cam.width}x{cam.height} fx={cam.fx:.2f} fy={cam.fy:.2f} "
              f"cx={cam.cx:.2f} cy={cam.cy:.2f} {cam.distortion_model} dist={[round(v, 6) for v in cam.dist]}")
    for note in result.notes:
        out.print(f"note: {lit(note)}")


@app.command("export")
def export(session: Path = typer.Argument(..., parser=opt.existing_file, help="A session file (.h5)."),
           out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="The MCAP file to write (.mcap)."),
           scene: Optional[str] = typer.Option(None, "--scene", help="A scene file or bundled scene name: also "
                                               "write the twin's render of it for the session's camera and the "
                                               "residual depth (measured - twin)."),
           depth_kind: str = typer.Option("radial", "--depth-kind", help="Depth images as radial distance (as the "
                                          "session stores it) or z along the optical axis (ROS's depth convention)."),
           force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists.")) -> None:
    """Write a session as a ROS 2 bag (MCAP) that Foxglove opens: depth, amplitude, CameraInfo and a
    point cloud per frame, and with --scene the twin's depth, amplitude, cloud and the residual."""
    from tofhil.app.export import export_mcap

    if out_path.suffix.lower() != ".mcap":
        raise TofhilError("is not a .mcap file", file=out_path, field="--out", expected="an output name ending in .mcap")

    def on_frame(i: int, n: int) -> None:
        check_interrupt()  # as the import's
        if console.is_terminal and (i == n or i % 10 == 0):
            console.print(f"exported {i}/{n} frames", end="\r")

    result = export_mcap(session, out_path, scene=scene, force=force, depth_kind=depth_kind, on_frame=on_frame)
    out.print(f"wrote {result.n_frames} frame(s) of {lit(session)} to {lit(result.out)}")
    for topic, n in result.counts.items():
        info = result.topics.get(topic, {})
        what = ", ".join(str(v) for v in (info.get("encoding"), info.get("kind")) if v)
        out.print(f"  {lit(topic)}: {n} message(s){' (' + lit(what) + ')' if what else ''}")
    for note in result.notes:
        out.print(f"note: {lit(note)}")
