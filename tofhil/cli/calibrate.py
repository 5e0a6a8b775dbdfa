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
                                       "full (k1, k2, p1, p2, k3)."),
        max_view_error: float = typer.Option(1.0, "--max-view-error", parser=opt.finite(0.0, lo_open=True, unit="px"),
                                             help="A view is rejected when its RMS reprojection error exceeds this "
                                                  "and 3x the median view's."),
        name: Optional[str] = typer.Option(None, "--name", help="Camera name in the preset (default the sessions')."),
        report: Optional[Path] = typer.Option(None, "--report", parser=opt.new_file,
                                              help="Also write the per-view results as JSON."),
        force: bool = typer.Option(False, "--force", help="Overwrite OUT (and --report) if they exist.")) -> None:
    """Calibrate the camera from amplitude images of a board (OpenCV): fx, fy, cx, cy and distortion."""
    from tofhil.boards import BoardSpec
    from tofhil.eval.calibration import DISTORTION_MODELS, calibrate_sessions, preset_text

    if model not in DISTORTION_MODELS:
        raise TofhilError(f"got {model!r}", field="--model", expected="one of " + ", ".join(DISTORTION_MODELS))
    if out_path.suffix.lower() not in (".yaml", ".yml"):
        raise TofhilError("is not a .yaml file", file=out_path, field="--out", expected="a camera preset path ending in .yaml")
    for p in (out_path, report):
        if p is not None and p.exists() and not force:
            raise TofhilError("already exists; refusing to overwrite (use --force)", file=p)
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
    out.print(f"fx {c.fx:.3f}  fy {c.fy:.3f}  cx {c.cx:.3f}  cy {c.cy:.3f}  dist "
              + " ".join(f"{d:.5g}" for d in c.dist) + f"  (RMS {cal.rms_px:.4f} px over {len(cal.used)} views)",
              highlight=False, soft_wrap=True)
    out.print(f"wrote camera preset to {lit(out_path)}", highlight=False, soft_wrap=True)
