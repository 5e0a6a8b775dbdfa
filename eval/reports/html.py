"""Report pages: one self-contained HTML file (PNG figures inlined as base64 data URIs, no
script, nothing fetched), the figures every report draws, and the JSON next to it.

Each figure is defined once here and used by every report that shows it (``compare``,
``diagnose``). Colour scales come from robust percentiles of the data shown, so that one
outlier (a jump edge, a saturated pixel) does not set the scale and hide millimetre
structure: residuals use a symmetric scale ``+-max(|p2|, |p98|)``, distances the 1-99 %
range; values beyond the scale are drawn in the end colours.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from tofhil.errors import TofhilError

#: Percentiles that set a residual map's symmetric colour scale.
RESIDUAL_PERCENTILES = (2.0, 98.0)

CSS = """body{font-family:sans-serif;max-width:1400px;margin:1em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}
th{background:#eee}td:first-child,td:nth-child(2){text-align:left}img{max-width:100%}
h2{border-bottom:1px solid #ccc;margin-top:1.6em}.note{color:#555;font-size:13px}.warn{color:#a40000}
.wide{max-width:100%;overflow-x:auto}.cases th{overflow-wrap:anywhere;min-width:5em;max-width:14em}"""


def esc(x: Any) -> str:
    return html.escape(str(x))


def fmt(x: Any, scale: float = 1.0) -> str:
    """A table cell: numbers to 4 significant digits, missing or non-finite as an en dash."""
    if x is None:
        return "–"
    if isinstance(x, (float, np.floating)) or (isinstance(x, (int, np.integer)) and scale != 1.0):
        v = float(x) * scale
        return "–" if not math.isfinite(v) else f"{v:.4g}"
    return esc(x)


# ---------------------------------------------------------------------------- output




def write_json(path: Path, payload: dict[str, Any]) -> None:
    from tofhil.eval.metrics.core import json_safe

    path.write_text(json.dumps(json_safe(payload), indent=2), encoding="utf-8")


# ---------------------------------------------------------------------------- figure plumbing


def fig_uri(fig: Any) -> str:
    """A matplotlib figure as a PNG data URI (the figure is closed)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def grid(n: int, width: float = 4.2, height: float = 3.4) -> tuple[Any, np.ndarray]:
    plt = pyplot()
    cols = min(max(n, 1), 3)
    rows = math.ceil(max(n, 1) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols, height * rows), squeeze=False,
                             layout="constrained")
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    return fig, axes.ravel()


def image_panel(fig: Any, ax: Any, img: np.ndarray, title: str, cmap: str, vmin: float, vmax: float,
                unit: str) -> None:
    extend = "neither"
    finite = np.asarray(img, float)[np.isfinite(img)]
    if finite.size:
        below, above = bool((finite < vmin).any()), bool((finite > vmax).any())
        extend = "both" if below and above else "min" if below else "max" if above else "neither"
    im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_title("\n".join(textwrap.wrap(title, 38)), fontsize=9)
    ax.set_xlabel("pixel column", fontsize=8)
    ax.set_ylabel("pixel row", fontsize=8)
    ax.tick_params(labelsize=7)
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, extend=extend)
    cb.set_label(unit, fontsize=8)
    cb.ax.tick_params(labelsize=7)


def robust_range(images: Sequence[np.ndarray], lo: float = 1, hi: float = 99) -> tuple[float, float]:
    """The ``lo``-``hi`` percentile range of the finite values of all images."""
    parts = [np.asarray(i, float)[np.isfinite(i)] for i in images]
    vals = np.concatenate(parts) if parts else np.zeros(0)
    if vals.size == 0:
        return 0.0, 1.0
    a, b = np.percentile(vals, [lo, hi])
    return (float(a), float(b)) if b > a else (float(a) - 0.5, float(a) + 0.5)


def symmetric_range(images: Sequence[np.ndarray], floor: float = 1e-12,
                    percentiles: tuple[float, float] = RESIDUAL_PERCENTILES) -> tuple[float, float]:
    """``+-max(|p_lo|, |p_hi|)`` of the finite values: a residual scale centred on zero."""
    a, b = robust_range(images, *percentiles)
    m = max(abs(a), abs(b), floor)
    return -m, m


# ---------------------------------------------------------------------------- the figures


def figure_distance_maps(panels: Sequence[tuple[str, np.ndarray]]) -> str:
    """Radial distance maps on one shared (1-99 %) scale."""
    lo, hi = robust_range([img for _, img in panels])
    fig, axes = grid(len(panels))
    for ax, (t, img) in zip(axes, panels):
        image_panel(fig, ax, img, f"radial distance: {t}", "viridis", lo, hi, "m")
    return fig_uri(fig)


def figure_amplitude_maps(panels: Sequence[tuple[str, np.ndarray]], unit: str = "a.u.") -> str:
    """Amplitude maps, each on its own scale (a device's and the twin's units differ)."""
    fig, axes = grid(len(panels))
    for ax, (t, img) in zip(axes, panels):
        lo, hi = robust_range([img], 0.5, 99.5)
        image_panel(fig, ax, img, f"amplitude: {t}", "gray", lo, hi, unit)
    return fig_uri(fig)


def figure_residual_maps(panels: Sequence[tuple[str, np.ndarray]], *, unit: str = "mm", scale: float = 1e3,
                         cmap: str = "RdBu_r", floor: float = 1e-3, columns: int | None = None,
                         scale_masks: Sequence[np.ndarray] | None = None) -> str:
    """Residual maps (values times ``scale`` in ``unit``) on one shared symmetric robust scale,
    set by the pixels of ``scale_masks`` (one per panel: the pixels a report's figures use)
    when given, so that a strip of pixels left out of the figures does not stretch it."""
    imgs = [(t, np.asarray(img, float) * scale) for t, img in panels]
    basis = [i if m is None else np.where(np.asarray(m, bool), i, np.nan)
             for (_, i), m in zip(imgs, scale_masks or [None] * len(imgs))]
    vmin, vmax = symmetric_range(basis, floor=floor)
    fig, axes = grid(len(imgs))
    for ax, (t, img) in zip(axes, imgs):
        image_panel(fig, ax, img, t, cmap, vmin, vmax, unit)
    return fig_uri(fig)


def figure_ratio_maps(panels: Sequence[tuple[str, np.ndarray]]) -> str | None:
    """Amplitude ratio maps A/B on a log2 scale (0 = equal); None when no ratio is finite."""
    if not any(np.isfinite(m).any() for _, m in panels):
        return None
    logs = []
    for t, m in panels:
        m = np.asarray(m, float)
        pos = np.isfinite(m) & (m > 0)
        logs.append((f"amplitude ratio A/B: {t}", np.where(pos, np.log2(np.where(pos, m, 1.0)), np.nan)))
    return figure_residual_maps(logs, unit="log2(A/B)", scale=1.0, cmap="PuOr_r", floor=0.05)


def figure_likelihood_maps(panels: Sequence[tuple[str, np.ndarray]]) -> str:
    """NDT trilinear likelihood maps on [0, 1]."""
    fig, axes = grid(len(panels))
    for ax, (t, m) in zip(axes, panels):
        image_panel(fig, ax, m, f"NDT likelihood: {t}", "magma", 0.0, 1.0, "trilinear likelihood")
    return fig_uri(fig)


def figure_histogram(residuals: Sequence[tuple[str, np.ndarray]], *, scale: float = 1e3, unit: str = "mm") -> str:
    """Distributions of residuals, clipped to the 0.5-99.5 % range, log counts."""
    plt = pyplot()
    vals = [(t, np.asarray(r, float)[np.isfinite(r)] * scale) for t, r in residuals]
    lo, hi = robust_range([v for _, v in vals if v.size], 0.5, 99.5)
    fig, ax = plt.subplots(figsize=(8, 4))
    bins = np.linspace(lo, hi, 81)
    for label, v in vals:
        if v.size:
            ax.hist(np.clip(v, lo, hi), bins=bins, histtype="step", lw=1.5, label=f"{label} (n={v.size})")
    ax.set_xlabel(f"depth residual A - B ({unit}), clipped to the 0.5-99.5 % range")
    ax.set_ylabel("pixels")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig_uri(fig)


@dataclass(frozen=True)
class CrossSection:
    """One image row (``axis="row"``) or column (``axis="column"``) to plot along."""

    axis: str
    index: int

    @classmethod
    def choose(cls, shape: tuple[int, int], row: int | None = None, column: int | None = None) -> "CrossSection":
        """``--row N`` or ``--column N`` (not both); default the centre row."""
        h, w = shape
        if row is not None and column is not None:
            raise TofhilError("give --row or --column, not both", field="--row")
        if column is not None:
            if not 0 <= column < w:
                raise TofhilError(f"is {column}", field="--column", expected=f"a pixel column in 0..{w - 1}")
            return cls("column", int(column))
        r = h // 2 if row is None else row
        if not 0 <= r < h:
            raise TofhilError(f"is {r}", field="--row", expected=f"a pixel row in 0..{h - 1}")
        return cls("row", int(r))

    def take(self, img: np.ndarray) -> np.ndarray:
        img = np.asarray(img, float)
        return img[self.index, :] if self.axis == "row" else img[:, self.index]

    @property
    def along(self) -> str:
        return "pixel column" if self.axis == "row" else "pixel row"

    def describe(self) -> str:
        return f"pixel {self.axis} {self.index}"


def figure_cross_section(section: CrossSection, reference: tuple[str, np.ndarray],
                         lines: Sequence[tuple[str, np.ndarray]],
                         residuals: Sequence[tuple[str, np.ndarray]] = ()) -> str:
    """Distance along a row or column (the reference in black, each other line in colour), and
    next to it the residual A - B along the same line."""
    plt = pyplot()
    ncols = 2 if residuals else 1
    fig, axes = plt.subplots(1, ncols, figsize=(8 * ncols * 0.75 if ncols == 2 else 8, 4), squeeze=False,
                             layout="constrained")
    ax = axes[0, 0]
    ref_label, ref = reference
    y = section.take(ref)
    x = np.arange(y.size)
    ax.plot(x, y, "k-", lw=2, label=ref_label)
    for label, img in lines:
        ax.plot(x, section.take(img), lw=1.2, label=label)
    ax.set_xlabel(section.along)
    ax.set_ylabel("radial distance (m)")
    ax.set_title(f"distance along {section.describe()}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if residuals:
        ax = axes[0, 1]
        vals = [section.take(img) * 1e3 for _, img in residuals]
        lo, hi = symmetric_range(vals, floor=1e-3, percentiles=(1.0, 99.0))
        lo, hi = 1.15 * lo, 1.15 * hi  # robust: a jump edge does not flatten the rest; it is drawn at the edge
        for (label, _), v in zip(residuals, vals):
            ax.plot(x, np.clip(v, lo, hi), lw=1.2, label=label)
        ax.axhline(0, color="0.5", lw=0.5)
        ax.set_ylim(lo, hi)
        ax.set_xlabel(section.along)
        ax.set_ylabel("A - B (mm)")
        ax.set_title(f"residual along {section.describe()}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return fig_uri(fig)


# ---------------------------------------------------------------------------- tables and pages


def region_table(rows: Sequence[tuple[str, Any]], *, label: str = "variant") -> str:
    """The per-region table every report shows: one row per (label, RegionMetrics)."""
    from tofhil.eval.metrics.core import DEPTH_RMSE, TRIM_FRACTION

    head = (f"<tr><th>{esc(label)}</th><th>region</th><th>pixels</th><th>compared</th><th>saturated A</th>"
            f"<th>median (mm)</th><th>MAD (mm)</th><th>RMSE, {100 * TRIM_FRACTION:g} % largest |r| trimmed (mm)</th>"
            f"<th>{esc(DEPTH_RMSE)} (mm)</th><th>noise floor (mm)</th>"
            "<th>p95 |r| (mm)</th>"
            "<th>amp. ratio</th><th>chamfer (mm)</th><th>F-score</th><th>NDT mean lik.</th><th>NVTL</th></tr>")
    body = []
    for name, r in rows:
        d = r.depth_residual_m
        c, n = r.cloud, r.ndt
        cells = [esc(name), esc(r.name), fmt(r.pixels), fmt(r.valid_both_fraction), fmt(r.saturated_fraction_a),
                 fmt(d.median, 1e3), fmt(d.mad, 1e3), fmt(d.rmse_trimmed, 1e3), fmt(d.rmse, 1e3),
                 fmt(getattr(r, "noise_floor_m", None), 1e3), fmt(d.p95_abs, 1e3),
                 fmt(r.amplitude_ratio.median), fmt(None if c is None else c.chamfer, 1e3),
                 fmt(None if c is None else c.fscore), fmt(None if n is None else n.mean_likelihood_trilinear),
                 fmt(None if n is None else n.nvtl)]
        body.append("<tr>" + "".join(f"<td>{x}</td>" for x in cells) + "</tr>")
    return f"<table>{head}{''.join(body)}</table>"


def notes_html(lines: Sequence[str], css: str = "warn") -> str:
    if not lines:
        return ""
    return f"<ul class='{css}'>" + "".join(f"<li>{esc(x)}</li>" for x in lines) + "</ul>"


def figures_html(figures: Sequence[tuple[str, str | None, str]]) -> str:
    parts = []
    for title, uri, caption in figures:
        if uri is None:
            continue
        parts.append(f"<h2>{esc(title)}</h2><p class='note'>{esc(caption)}</p><img alt='{esc(title)}' src='{uri}'>")
    return "\n".join(parts)


def write_page(path: Path, title: str, body: Sequence[str]) -> None:
    """One self-contained page from HTML fragments."""
    text = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{esc(title)}</title><style>{CSS}</style>"
            f"</head><body><h1>{esc(title)}</h1>\n" + "\n".join(body) + "\n</body></html>")
    path.write_text(text, encoding="utf-8")
