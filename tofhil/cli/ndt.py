"""``tofhil ndt``: 3D-NDT scores of a cloud against a reference cloud."""

from __future__ import annotations

from typing import List, Optional

import typer

from tofhil.cli import app, lit, out, print_json
from tofhil.cli import options as opt
from tofhil.errors import TofhilError


@app.command()
def ndt(ref: str = typer.Argument(..., help="Reference cloud: PLY, PCD, xyz text, .npy or SESSION.h5[:FRAME]."),
        cloud: str = typer.Argument(..., help="Cloud to score, same formats."),
        cell_size: Optional[List[float]] = typer.Option(
            None, "--cell-size", parser=opt.finite(0.0, 1e3, lo_open=True, unit="m"),
            help="NDT cell side R [m] (default 0.1); repeat for several resolutions."),
        outlier_ratio: float = typer.Option(0.55, "--outlier-ratio", parser=opt.finite(0.0, 1.0, lo_open=True, hi_open=True),
                                            help="Outlier ratio r for d1, d2 (PCL 0.55)."),
        min_points: int = typer.Option(6, "--min-points", parser=opt.count(3, 1_000_000),
                                       help="Minimum points per cell (PCL 6)."),
        eig_floor: float = typer.Option(0.01, "--eig-floor", parser=opt.finite(0.0, 1.0, lo_open=True),
                                        help="Eigenvalue floor, fraction of the largest."),
        threshold: Optional[List[float]] = typer.Option(None, "--threshold", parser=opt.finite(0.0, 1.0),
                                                        help="Likelihood threshold for fraction_above (repeatable)."),
        d2d: bool = typer.Option(False, "--d2d", help="Also the D2D score between the two clouds' grids."),
        score_only: bool = typer.Option(
            False, "--score-only", help="Only PCL's score per point (what PCL's NDT computes), without the other "
                                        "scores: numpy alone, no compiled kernel to load (about half the CPU time)."),
        as_json: bool = typer.Option(False, "--json", help="Print JSON.")) -> None:
    """Score CLOUD against the NDT of REF: PCL score per point, NVTL, likelihoods.

    With several --cell-size values the first gives the top-level numbers and JSON gains
    "resolutions": {R: {...}} for all of them.
    """
    from tofhil.eval.metrics.clouds import load_cloud
    from tofhil.eval.metrics.ndt import DEFAULT_THRESHOLDS, NDTGrid, d2d_score, gauss_params, ndt_score, pcl_score

    sizes = list(cell_size) if cell_size else [0.1]
    for r in sizes:
        if not r > 0:
            raise TofhilError(f"is {r}", field="--cell-size", expected="a positive length in metres")
    if not 0 < outlier_ratio < 1:
        raise TofhilError(f"is {outlier_ratio}", field="--outlier-ratio", expected="a value in (0, 1)")
    if min_points < 3:
        raise TofhilError(f"is {min_points}", field="--min-points", expected="at least 3")
    thresholds = tuple(threshold) if threshold else DEFAULT_THRESHOLDS
    for t in thresholds:
        if not 0 <= t <= 1:
            raise TofhilError(f"is {t}", field="--threshold", expected="a likelihood in [0, 1]")
    ref_pts = load_cloud(ref)
    pts = load_cloud(cloud)
    results: dict = {}
    for r in sizes:
        grid = NDTGrid.from_points(ref_pts, r, min_points=min_points, eig_floor=eig_floor)
        if grid.cells == 0:
            raise TofhilError(f"gives no NDT cell with at least {min_points} points at cell size {r} m",
                              file=ref, expected="a denser reference or a larger --cell-size")
        if score_only:
            d = {"score_per_point": pcl_score(grid, pts, outlier_ratio=outlier_ratio), "cells": grid.cells,
                 "n_points": int(pts.shape[0]), "cell_size": grid.cell_size, "outlier_ratio": float(outlier_ratio)}
            s = None
        else:
            s = ndt_score(grid, pts, outlier_ratio=outlier_ratio, thresholds=thresholds)
            d = s.to_dict()
        if d2d:
            other = NDTGrid.from_points(pts, r, min_points=min_points, eig_floor=eig_floor)
            d["d2d"] = d2d_score(grid, other, outlier_ratio=outlier_ratio).to_dict()
        results[r] = (s, d)
    first_s, first = results[sizes[0]]
    payload = dict(first)
    if len(sizes) > 1:
        payload["resolutions"] = {repr(float(r)): d for r, (_, d) in results.items()}
    if as_json:
        print_json(payload)
        return
    out.print(f"reference {lit(ref)}: {ref_pts.shape[0]} points")
    out.print(f"cloud     {lit(cloud)}: {pts.shape[0]} points")
    for r, (s, d) in results.items():
        out.print(f"[bold]cell size {r:g} m[/bold]: {d['cells']} cells (min {min_points} points)")
        d1, d2 = gauss_params(d["cell_size"], outlier_ratio)
        out.print(f"  score per point (PCL)      {d['score_per_point']:.6f}   (d1={d1:.5g}, d2={d2:.5g})")
        if s is not None:
            out.print(f"  NVTL (Autoware)            {s.nvtl:.6f}")
            out.print(f"  mean likelihood (cell)     {s.mean_likelihood:.6f}")
            out.print(f"  mean likelihood (trilin.)  {s.mean_likelihood_trilinear:.6f}")
            for t, v in s.fraction_above.items():
                out.print(f"  fraction above {t:<11g} {v:.4f}")
        if d2d:
            out.print(f"  D2D score per cell         {d['d2d']['score_per_cell']:.6f}   "
                      f"mean similarity {d['d2d']['mean_similarity']:.4f}")
