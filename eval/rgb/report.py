"""The report of ``tofhil colorize --report DIR``: the coloured cloud seen from an oblique view,
the depth silhouettes over the colour image with the colour edges they were matched to, and the
edge-alignment self-check (``colorize.html``, ``colorize.json``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tofhil.eval.rgb.edge_alignment import SLOPE_RANGE, EdgeAlignment
from tofhil.eval.reports.html import esc, fig_uri, pyplot, write_json, write_page

REPORT_FILES = ("colorize.html", "colorize.json")


def cloud_view(points: np.ndarray, colors: np.ndarray, *, turn_deg: float = -20.0, width: int = 640,
               height: int = 480) -> np.ndarray:
    """An RGB image of coloured points seen by a pinhole camera turned ``turn_deg`` about a
    vertical axis through the near part of the cloud (its 5th-percentile depth on the optical
    axis; nearest point per pixel, black elsewhere)."""
    c = np.array([0.0, 0.0, float(np.percentile(points[:, 2], 5))])
    a = np.radians(turn_deg)
    rot = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    p = (points - c) @ rot.T + [0.0, 0.0, float(c[2])]
    z = p[:, 2]
    ok = z > 1e-3
    f = 0.45 * width
    u = np.round(f * p[ok, 0] / z[ok] + width / 2).astype(np.int64)
    v = np.round(f * p[ok, 1] / z[ok] + height / 2).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, zz, col = u[inside], v[inside], z[ok][inside], colors[ok][inside]
    order = np.argsort(-zz)          # far first: the nearest point is written last
    img = np.zeros((height, width, 3), np.uint8)
    img[v[order], u[order]] = col[order]
    return img


def figure_cloud(img: np.ndarray, title: str) -> str:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 5.4), layout="constrained")
    ax.imshow(img)
    ax.set_title(title, fontsize=10)
    ax.axis("off")
    return fig_uri(fig)


def figure_edges(rgb: np.ndarray, res: EdgeAlignment) -> str | None:
    """Left: the colour image around the silhouettes, depth silhouettes (red left side, blue right
    side) and the colour edges matched to them (yellow); right: the self-check."""
    uv = res.depth_edges_uv
    if uv is None or not np.isfinite(uv).any():
        return None
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 5), layout="constrained", width_ratios=[1.6, 1])
    lo = np.floor(np.nanmin(uv, axis=0) - 30).astype(int).clip(0)
    hi = np.ceil(np.nanmax(uv, axis=0) + 30).astype(int)
    hi = np.minimum(hi, [rgb.shape[1], rgb.shape[0]])
    ax.imshow(rgb[lo[1]:hi[1], lo[0]:hi[0]], extent=(lo[0] - 0.5, hi[0] - 0.5, hi[1] - 0.5, lo[1] - 0.5))
    for side, colour in ((-1, "red"), (1, "deepskyblue")):
        m = res.side == side
        ax.plot(uv[m, 0], uv[m, 1], ".", ms=2.5, color=colour, label=f"depth silhouette ({'left' if side < 0 else 'right'})")
    ok = np.isfinite(res.color_edges_u)
    ax.plot(res.color_edges_u[ok], uv[ok, 1], ".", ms=1.5, color="yellow", label="matched colour edge")
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"shift {res.shift_px:+.2f} px, spread {res.spread_px:+.2f} px (colour px)", fontsize=10)
    pred = [p["predicted_px"] for p in res.probes]
    bx.plot(pred, [p["measured_px"] for p in res.probes], "ko-", label=f"both sides (slope {res.slope:.2f})")
    bx.plot(pred, [p["measured_left_px"] for p in res.probes], "r.--", label=f"left (slope {res.slope_left:.2f})")
    bx.plot(pred, [p["measured_right_px"] for p in res.probes], "b.--", label=f"right (slope {res.slope_right:.2f})")
    lim = max(abs(x) for x in pred) * 1.1 if pred else 1.0
    bx.plot([-lim, lim], [-lim, lim], color="grey", lw=0.8, label="slope 1")
    bx.set_xlabel("predicted change (colour px) for the baseline moved", fontsize=9)
    bx.set_ylabel("measured change of the offsets (colour px)", fontsize=9)
    bx.set_title("self-check: " + ("passed" if res.passed else "FAILED")
                 + f" (slope in [{SLOPE_RANGE[0]:g}, {SLOPE_RANGE[1]:g}])", fontsize=10)
    bx.legend(fontsize=8)
    return fig_uri(fig)


def write_colorize_report(out_dir: Path, *, cloud_img: np.ndarray, rgb: np.ndarray, edges: EdgeAlignment,
                          summary: dict[str, Any]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "colorize.json", summary | {"edge_alignment": edges.to_dict()})
    verdict = ("The measure passed its self-check" if edges.passed else
               "The measure FAILED its self-check: the figures do not measure the registration")
    body = [f"<p>{esc(summary.get('text', ''))}</p>",
            "<h2>Coloured cloud</h2><img alt='coloured cloud' src='" + figure_cloud(cloud_img, "coloured points, "
                                                                                  "oblique view") + "'>",
            "<h2>Alignment at depth edges</h2><p class='note'>Signed offsets along the image rows, colour edge minus "
            "depth silhouette, in colour pixels; shift = mean of the two sides (registration error along the "
            "baseline), spread = half their difference, outward positive (the colour silhouette's extra width). "
            f"{esc(verdict)}.</p>"]
    uri = figure_edges(rgb, edges)
    body.append(f"<img alt='edges' src='{uri}'>" if uri else "<p class='warn'>No depth silhouettes found.</p>")
    write_page(out_dir / "colorize.html", "tofhil colorize", body)
