"""The report of a multi-view model (``tofhil model --report DIR``): ``model.html`` with the
per-view pose errors, the pairwise registrations, the model's scores against the truth and its
NDT score map, and ``model.json`` with the same figures."""

from __future__ import annotations

from pathlib import Path
import numpy as np

from tofhil.eval.reports.html import esc, fig_uri, fmt, notes_html, pyplot, write_json, write_page
from tofhil.eval.multiview.model import MultiViewModel

REPORT_FILES = ("model.html", "model.json")


def figure_ndt_map(points: np.ndarray, likelihood: np.ndarray, title: str) -> str:
    """The model's points in a top view (x-z) and a side view (x-y, y down) coloured by their
    trilinear NDT likelihood on the truth's grid (1: on the truth's surface)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), layout="constrained")
    order = np.argsort(-np.nan_to_num(likelihood))   # the worst points drawn last (on top)
    p, lk = points[order], likelihood[order]
    for ax, (i, j, label) in zip(axes, ((0, 2, "top view: x (m) / z (m)"), (0, 1, "side view: x (m) / y (m, down)"))):
        sc = ax.scatter(p[:, i], p[:, j], c=lk, s=1.0, cmap="viridis", vmin=0.0, vmax=1.0, linewidths=0)
        ax.set_aspect("equal")
        ax.set_title(label, fontsize=9)
        ax.tick_params(labelsize=7)
        if j == 1:
            ax.invert_yaxis()
    cb = fig.colorbar(sc, ax=axes, fraction=0.03)
    cb.set_label("NDT likelihood", fontsize=8)
    fig.suptitle(title, fontsize=10)
    return fig_uri(fig)


def write_model_report(model: MultiViewModel, out_dir: Path, *, inputs: list[str]) -> None:
    """Write ``model.html`` and ``model.json`` into ``out_dir`` (created)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    payload = model.to_dict() | {"inputs": inputs}
    write_json(out_dir / "model.json", payload)
    body = [notes_html(model.notes)]
    rows = []
    for v in model.views:
        t = v.pose[:3, 3]
        rows.append("<tr>" + "".join(f"<td>{x}</td>" for x in (
            esc(v.name), fmt(v.points), f"{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}",
            fmt(v.translation_error_m, 1e3), fmt(v.rotation_error_deg))) + "</tr>")
    body.append("<h2>Views</h2><p class='note'>Estimated pose of each view in the model frame (view 0's camera "
                "frame); errors against the true poses with view 0 as the anchor.</p><table><tr><th>view</th>"
                "<th>points</th><th>position (m)</th><th>translation error (mm)</th><th>rotation error (deg)</th></tr>"
                + "".join(rows) + "</table>")
    prow = ["<tr>" + "".join(f"<td>{x}</td>" for x in (
        f"{p.source} -> {p.target}", "loop" if p.loop else "odometry", esc(p.coarse), fmt(p.fitness),
        fmt(p.inlier_rmse_m, 1e3))) + "</tr>" for p in model.registration.pairs]
    body.append("<h2>Pairwise registrations</h2><table><tr><th>pair</th><th>edge</th><th>coarse start</th>"
                "<th>fitness</th><th>inlier RMSE (mm)</th></tr>" + "".join(prow) + "</table>")
    s = model.score
    if s is not None:
        nd = s.ndt
        verdict = payload["ndt_verdict"] or ""
        top = model.ceiling.ndt["mean_likelihood"] if model.ceiling is not None else None
        body.append("<h2>Model against the truth</h2><table><tr><th>figure</th><th>value</th></tr>"
                    + "".join(f"<tr><td>{esc(k)}</td><td>{v}</td></tr>" for k, v in (
                        ("NDT cell (m)", fmt(nd["cell_size"])), ("NDT mean likelihood", fmt(nd["mean_likelihood"])),
                        ("NDT mean likelihood of the true-pose model", fmt(top)),
                        ("NDT mean trilinear likelihood", fmt(nd["mean_likelihood_trilinear"])),
                        ("NDT fraction above 0.5", fmt(nd["fraction_above"].get("0.5"))),
                        ("NDT score per point (PCL)", fmt(nd["score_per_point"])), ("NVTL", fmt(nd["nvtl"])),
                        ("Chamfer (mm)", fmt(s.chamfer_m, 1e3)),
                        (f"F-score at {s.fscore_threshold_m * 1e3:g} mm", fmt(s.fscore)),
                        ("precision / recall", f"{s.precision:.4f} / {s.recall:.4f}"),
                        ("truth points seen by a view / sampled", f"{s.truth_points_visible} / {s.truth_points}")))
                    + "</table>" + (f"<p>{esc(verdict)}</p>" if verdict else ""))
        wp = model.world_points()
        body.append("<h2>NDT score map</h2><p class='note'>Model points (world frame) coloured by their trilinear "
                    "NDT likelihood on the truth's grid: low values mark where the model leaves the true surfaces."
                    f"</p><img alt='NDT map' src='{figure_ndt_map(wp, s.likelihood, 'model vs truth')}'>")
    write_page(out_dir / "model.html", "tofhil model", body)
