"""``tofhil model``: a multi-view model from several sessions (registration, TSDF fusion, score)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from tofhil.cli import app, lit, new_output_dir, out, progress
from tofhil.cli import options as opt
from tofhil.errors import TofhilError


@app.command("model")
def model_cmd(sessions: List[Path] = typer.Argument(..., parser=opt.existing_file,
                                                    help="Sessions, one view each (their depth frames are averaged)."),
              out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="The fused model (.ply)."),
              report: Optional[Path] = typer.Option(None, "--report", parser=opt.out_dir,
                                                    help="Directory for model.html and model.json."),
              voxel: float = typer.Option(0.04, "--voxel", parser=opt.finite(0.001, 1.0, unit="m"),
                                          help="Coarse registration voxel (features, first ICP scale)."),
              tsdf_voxel: float = typer.Option(0.02, "--tsdf-voxel", parser=opt.finite(0.001, 0.5, unit="m"),
                                               help="TSDF voxel of the fused model."),
              ndt_cell: float = typer.Option(0.1, "--ndt-cell", parser=opt.finite(0.005, 10.0, unit="m"),
                                             help="NDT cell of the score against the truth."),
              threshold: float = typer.Option(0.02, "--fscore-threshold", parser=opt.finite(0.0, 1.0, lo_open=True,
                                                                                           unit="m"),
                                              help="F-score distance."),
              force: bool = typer.Option(False, "--force", help="Overwrite OUT and the report files.")) -> None:
    """Register the views (FPFH/RANSAC then ICP, pose graph), fuse them (TSDF) into a model and,
    for simulated views, score it against the scene's geometry (NDT, Chamfer, F-score) with per-view pose errors."""
    from tofhil.eval.rgb.colorize import write_ply
    from tofhil.outputs import prepare_output_dir
    from tofhil.eval.multiview.model import build_model, load_view
    from tofhil.eval.multiview.report import REPORT_FILES, write_model_report

    opt.check_output(out_path, force, (".ply",), "a path ending in .ply")
    if report is not None:
        prepare_output_dir(report, REPORT_FILES, force=force)
    if len(sessions) < 2:
        raise TofhilError(f"got {len(sessions)} session", field="SESSIONS", expected="at least two sessions (views)")
    views = [load_view(p) for p in sessions]
    model = build_model(views, voxel_m=voxel, tsdf_voxel_m=tsdf_voxel, cell_m=ndt_cell, threshold_m=threshold,
                        progress=progress)
    import numpy as np

    g = np.round(model.grey * 255).astype(np.uint8)
    write_ply(out_path, model.points, np.stack([g, g, g], axis=1))
    summary = model.to_dict()
    if report is not None:
        with new_output_dir(report):
            write_model_report(model, report, inputs=[str(p) for p in sessions])
    for v in model.views:
        err = ("" if v.translation_error_m is None else
               f", pose error {v.translation_error_m * 1e3:.2f} mm {v.rotation_error_deg:.3f} deg")
        out.print(f"{lit(v.name)}: {v.points} points{err}", highlight=False, soft_wrap=True)
    if model.score is not None:
        s = model.score
        out.print(f"model vs truth: Chamfer {s.chamfer_m * 1e3:.2f} mm, F-score {s.fscore:.3f} at "
                  f"{s.fscore_threshold_m * 1e3:g} mm; {summary['ndt_verdict']}", highlight=False, soft_wrap=True)
    for n in model.notes:
        out.print(lit(n), highlight=False, soft_wrap=True)
    out.print(f"wrote {len(model.points)} model points to {lit(out_path)}"
              + (f" and the report to {lit(report)}" if report is not None else ""), highlight=False, soft_wrap=True)
