"""``tofhil calibrate-camera``: intrinsics and distortion from amplitude images of a board."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from tofhil.cli import app, lit, out, progress
from tofhil.cli import options as opt
from tofhil.errors import TofhilError

_TARGET_HELP = ("The board: KIND:COLSxROWS:SIZE_M[:SECOND_M[:DICTIONARY]] (squares, not inner corners), e.g. "
                "checkerboard:9x6:0.03 | charuco:7x5:0.04:0.03[:DICT_4X4_50] | aruco:4x3:0.04:0.01 (marker, gap); "
                "or a YAML file with the board mapping (docs/scene-format.md, type: board).")


@app.command("calibrate-camera")
def calibrate_camera_cmd(
        sessions: List[Path] = typer.Argument(..., parser=opt.existing_file,
                                              help="Sessions, one board pose each (their frames are averaged)."),
        target: str = typer.Option(..., "--target", help=_TARGET_HELP),
        out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="Camera preset to write (.yaml)."),
        model: str = typer.Option("k1k2p", "--model",
                                  help="Distortion coefficients fitted: none | k1 | k1k2 | k1k2p (k1, k2, p1, p2) | "
                                       "full (k1, k2, p1, p2, k3) | rational (OpenCV CALIB_RATIONAL_MODEL: "
                                       "k1..k6, p1, p2) | thin_prism (rational + CALIB_THIN_PRISM_MODEL: s1..s4) | "
                                       "fisheye (cv2.fisheye.calibrate: k1..k4, equidistant)."),
        max_view_error: float = typer.Option(1.0, "--max-view-error", parser=opt.finite(0.0, lo_open=True, unit="px"),
                                             help="A view is rejected when its RMS reprojection error exceeds this "
                                                  "and 3x the median view's."),
        name: Optional[str] = typer.Option(None, "--name", help="Camera name in the preset (default the sessions')."),
        report: Optional[Path] = typer.Option(None, "--report", parser=opt.new_file,
                                              help="Also write the per-view results as JSON."),
        force: bool = typer.Option(False, "--force", help="Overwrite OUT (and --report) if they exist.")) -> None:
    """Calibrate the camera from amplitude images of a board (OpenCV): fx, fy, cx, cy and distortion."""
    from tofhil.boards import BoardSpec
    from tofhil.eval.calibration.camera import DISTORTION_MODELS, calibrate_sessions, preset_text

    if model not in DISTORTION_MODELS:
        raise TofhilError(f"got {model!r}", field="--model", expected="one of " + ", ".join(DISTORTION_MODELS))
    opt.check_output(out_path, force, (".yaml", ".yml"), "a camera preset path ending in .yaml")
    if report is not None:
        opt.check_output(report, force)
    spec = BoardSpec.parse(target, field="--target")
    cal = calibrate_sessions(sessions, spec, model=model, max_view_error_px=max_view_error, progress=progress)
    text = preset_text(cal, spec, name=name)
    out_path.write_text(text, encoding="utf-8")
    if report is not None:
        report.write_text(json.dumps(cal.to_dict() | {"target": spec.to_dict()}, indent=2), encoding="utf-8")
    for v in cal.views:
        state = f"RMS {v.rms_px:.4f} px" if v.used else f"rejected: {v.reason}"
        out.print(f"{lit(v.name)}: {v.corners} corners, {lit(state)}", highlight=False, soft_wrap=True)
    c = cal.camera
    out.print(f"fx {c.fx:.3f}  fy {c.fy:.3f}  cx {c.cx:.3f}  cy {c.cy:.3f}  {c.distortion_model} dist "
              + " ".join(f"{d:.5g}" for d in c.dist) + f"  (RMS {cal.rms_px:.4f} px over {len(cal.used)} views)",
              highlight=False, soft_wrap=True)
    out.print(f"wrote camera preset to {lit(out_path)}", highlight=False, soft_wrap=True)


@app.command("colorize")
def colorize_cmd(recording: Path = typer.Argument(..., parser=opt.existing_file,
                                                 help="Azure Kinect recording (.mkv) with DEPTH and COLOR tracks, or a "
                                                      "session (.h5) with an rgb/ group."),
                 out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="Coloured point cloud (.ply)."),
                 frame: int = typer.Option(0, "--frame", parser=opt.count(0, what="a frame index"),
                                           help="Frame index (depth and colour)."),
                 extrinsics: Optional[Path] = typer.Option(None, "--extrinsics", parser=opt.existing_file,
                                                           help="A session's ToF -> camera transform from "
                                                                "tofhil calibrate-stereo (.yaml); default the rgb/ "
                                                                "group's own."),
                 keep_occluded: bool = typer.Option(False, "--keep-occluded",
                                                    help="Write points the colour camera does not see too (black)."),
                 report: Optional[Path] = typer.Option(None, "--report", parser=opt.out_dir,
                                                       help="Directory for colorize.html and colorize.json: the "
                                                            "coloured cloud and the misalignment at depth edges."),
                 force: bool = typer.Option(False, "--force", help="Overwrite OUT (and the report files) if they exist.")
                 ) -> None:
    """Colour the depth points of an Azure Kinect recording (factory calibration) or of a session
    with a second camera's frames (rgb/ group) from the colour camera; points the colour camera
    cannot see are occluded and left out."""
    import numpy as np

    from tofhil.cli import new_output_dir
    from tofhil.drivers.importers.k4a_color import read_depth_with_color
    from tofhil.eval.rgb.colorize import colorize_points, depth_noise, session_inputs, write_ply

    opt.check_output(out_path, force, (".ply",), "a path ending in .ply")
    if report is not None:
        from tofhil.eval.rgb.report import REPORT_FILES
        from tofhil.outputs import prepare_output_dir

        prepare_output_dir(report, REPORT_FILES, force=force)
    if recording.suffix.lower() in (".h5", ".hdf5"):
        t = None
        if extrinsics is not None:
            from tofhil.yamlio import load_yaml

            doc = load_yaml(extrinsics.read_text(encoding="utf-8"), source=str(extrinsics))
            t = np.asarray(doc.get("tof_to_camera") if isinstance(doc, dict) else None, dtype=np.float64)
            if t.shape != (4, 4) or not np.all(np.isfinite(t)):
                raise TofhilError("has no usable tof_to_camera", file=extrinsics, field="tof_to_camera",
                                  expected="a 4x4 transform (tofhil calibrate-stereo's output)")
        inp = session_inputs(recording, frame, t)
    else:
        if extrinsics is not None:
            raise TofhilError("applies to sessions only", field="--extrinsics",
                              expected="no --extrinsics with a Kinect recording (its factory calibration is used)")
        inp = read_depth_with_color(recording, frame)
    pts = inp.points()
    res = colorize_points(pts, inp.tof_to_color, inp.color_camera, inp.rgb,
                          noise_m=depth_noise(inp.z_m, inp.valid)[inp.valid])  # row-major, as points()
    keep = np.ones(len(pts), bool) if keep_occluded else res.visible
    text = (f"{int(res.visible.sum())} of {len(pts)} depth points coloured, {int(res.occluded.sum())} occluded, "
            f"{int(len(pts) - res.visible.sum() - res.occluded.sum())} outside the colour image")
    edges = None
    if report is not None:
        from tofhil.eval.rgb.edge_alignment import edge_alignment

        edges = edge_alignment(inp.z_m, inp.valid, inp.pixel_to_ray, inp.tof_to_color, inp.color_camera, inp.rgb)
    write_ply(out_path, pts[keep], res.colors[keep])
    out.print(f"{text}; wrote {int(keep.sum())} points to {lit(out_path)}", highlight=False, soft_wrap=True)
    if edges is not None:
        from tofhil.eval.rgb.report import cloud_view, write_colorize_report

        with new_output_dir(report):
            write_colorize_report(report, cloud_img=cloud_view(pts[res.visible], res.colors[res.visible]),
                                  rgb=inp.rgb, edges=edges,
                                  summary={"input": str(recording), "frame": frame, "text": text})
        state = "self-check passed" if edges.passed else "self-check FAILED: not a measure of the registration"
        out.print(f"misalignment at depth edges: shift {edges.shift_px:+.2f} colour px, spread {edges.spread_px:+.2f} px "
                  f"(left {edges.left.median_px:+.2f}, right {edges.right.median_px:+.2f}; {state}, slope "
                  f"{edges.slope:.2f}); wrote the report to {lit(report)}", highlight=False, soft_wrap=True)


@app.command("calibrate-stereo")
def calibrate_stereo_cmd(
        sessions: List[Path] = typer.Argument(..., parser=opt.existing_file,
                                              help="Sessions with an rgb/ group, one board pose each."),
        target: str = typer.Option(..., "--target", help=_TARGET_HELP),
        out_path: Path = typer.Option(..., "--out", parser=opt.new_file,
                                      help="Extrinsics to write (.yaml: tof_to_camera 4x4, errors, views)."),
        tof_camera: Optional[Path] = typer.Option(None, "--tof-camera", parser=opt.existing_file,
                                                  help="ToF camera preset (e.g. from calibrate-camera); default the sessions'."),
        rgb_camera: Optional[Path] = typer.Option(None, "--rgb-camera", parser=opt.existing_file,
                                                  help="Second camera preset; default the sessions' rgb.camera."),
        force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists.")) -> None:
    """ToF <-> second camera extrinsics from simultaneous board views (OpenCV stereoCalibrate, intrinsics fixed)."""
    import yaml

    from tofhil.boards import BoardSpec
    from tofhil.camera import load_camera_preset
    from tofhil.eval.calibration.camera import calibrate_stereo_sessions

    opt.check_output(out_path, force, (".yaml", ".yml"), "a path ending in .yaml")
    spec = BoardSpec.parse(target, field="--target")
    cal = calibrate_stereo_sessions(sessions, spec,
                                    tof_camera=load_camera_preset(tof_camera) if tof_camera else None,
                                    other_camera=load_camera_preset(rgb_camera) if rgb_camera else None)
    out_path.write_text("# ToF frame -> second camera frame (m), by tofhil calibrate-stereo\n"
                        + yaml.safe_dump(cal.to_dict() | {"target": spec.to_dict()}, sort_keys=False,
                                         default_flow_style=None), encoding="utf-8")
    for v in cal.views:
        state = f"RMS {v.rms_px:.4f} px" if v.used else f"skipped: {v.reason}"
        out.print(f"{lit(v.name)}: {v.corners} corners, {lit(state)}", highlight=False, soft_wrap=True)
    t = cal.tof_to_camera[:3, 3] * 1e3
    out.print(f"translation [{t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}] mm, RMS {cal.rms_px:.4f} px; "
              f"wrote {lit(out_path)}", highlight=False, soft_wrap=True)
