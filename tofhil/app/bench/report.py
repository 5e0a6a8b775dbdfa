"""A bench procedure's report: the spec-sheet verdict first, then the figures with the twin's
prediction, what was found, the curves as plots; ``figures.json`` and ``curves.parquet``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from tofhil.app.bench.base import FIGURES, BenchResult
from tofhil.eval.reports.html import esc, figures_html, fmt, write_json, write_page

_VERDICT_CSS = {"pass": "#1a7f37", "marginal": "#9a6700", "fail": "#cf222e", "not measured": "#57606a"}


#: Figures that are shares, shown in percent.
_PERCENT = {"prnu", "fill_rate"}


def _display(name: str, unit: str) -> tuple[float, str]:
    """Scale and unit a figure is shown in: metres as millimetres (a bench reads mm), shares in %."""
    if unit == "m":
        return 1e3, "mm"
    if name in _PERCENT:
        return 100.0, "%"
    return 1.0, unit


def _g(v: float) -> str:
    """4 significant digits, without an exponent between 1e-3 and 1e7."""
    if 1e3 <= abs(v) < 1e7:
        return f"{v:,.0f}"
    return f"{v:.4g}"


def _num(v: float, s: float = math.nan, unit: str = "", name: str = "") -> str:
    if v is None or not math.isfinite(v):
        return "–"
    k, unit = _display(name, unit)
    text = _g(v * k)
    if math.isfinite(s) and s > 0:
        e = f"{s * k:.2g}"
        text += f" ± {f'{s * k:,.0f}' if 'e+' in e else e}"
    return f"{text} {unit}".strip()


def _limit(name: str, lo: float, hi: float, unit: str) -> str:
    k, unit = _display(name, unit)
    if math.isfinite(lo) and math.isfinite(hi):
        return f"{_g(lo * k)} .. {_g(hi * k)} {unit}".strip()
    return (f"≤ {_g(hi * k)} {unit}" if math.isfinite(hi) else f"≥ {_g(lo * k)} {unit}").strip()


def verdict_table(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "<p class='note'>No spec sheet given (--spec SHEET.yaml): no verdict.</p>"
    body = "".join(
        f"<tr><td>{esc(r['figure'])}</td><td>{esc(FIGURES[r['figure']][1])}</td>"
        f"<td>{esc(_limit(r['figure'], r['lo'], r['hi'], r['unit']))}</td>"
        f"<td>{_num(r['value'], r['sigma'], r['unit'], r['figure'])}</td>"
        f"<td style='color:#fff;background:{_VERDICT_CSS[r['verdict']]};font-weight:bold;text-align:center'>"
        f"{esc(r['verdict'])}</td></tr>" for r in rows)
    return ("<table><tr><th>figure</th><th>what</th><th>spec sheet</th><th>measured</th><th>verdict</th></tr>"
            f"{body}</table>")


def figure_table(result: BenchResult) -> str:
    body = []
    for f in result.figures:
        z = (f.value - f.predicted) / f.sigma if math.isfinite(f.sigma) and f.sigma > 0 and math.isfinite(
            f.predicted) else math.nan
        body.append(f"<tr><td>{esc(f.name)}</td><td>{esc(FIGURES[f.name][1])}</td>"
                    f"<td>{_num(f.value, f.sigma, f.unit, f.name)}</td>"
                    f"<td>{_num(f.predicted, f.predicted_sigma, f.unit, f.name)}</td>"
                    f"<td>{fmt(z)}</td><td>{esc(f.note)}</td></tr>")
    return ("<table><tr><th>figure</th><th>what</th><th>measured (± 1 sigma)</th><th>twin predicts</th>"
            "<th>(measured − twin) / sigma</th><th>note</th></tr>" + "".join(body) + "</table>")


def write_report(result: BenchResult, out_dir: Path) -> None:
    """``report.html`` (self-contained), ``figures.json`` and ``curves.parquet`` in ``out_dir``."""
    out_dir = Path(out_dir)
    payload = {"procedure": result.procedure, "device": result.device,
               "figures": [f.to_dict() for f in result.figures], "verdict": result.verdict,
               "findings": result.findings, "curves": result.curves, "details": result.details,
               "files": result.files, "seconds": result.seconds}
    write_json(out_dir / "figures.json", payload)
    try:
        import pandas as pd

        frames = [pd.DataFrame(rows).assign(curve=name) for name, rows in result.curves.items() if rows]
        if frames:
            pd.concat(frames, ignore_index=True).to_parquet(out_dir / "curves.parquet")
            result.files["curves"] = "curves.parquet"
    except ImportError:  # pyarrow is a dependency; a stripped environment still gets the JSON
        pass
    sheet = result.details.get("spec_sheet")
    body = [f"<p class='note'>device {esc(result.device)}; "
            f"{esc(result.details.get('campaign', {}).get('taken', 0))} captures taken, "
            f"{esc(result.details.get('campaign', {}).get('skipped', 0))} kept from an earlier run</p>",
            "<h2>Spec-sheet verdict" + (f" ({esc(sheet['name'])})" if sheet else "") + "</h2>",
            verdict_table(result.verdict),
            "<h2>Measured and predicted</h2>", figure_table(result),
            "<h2>What was found</h2>",
            "<ul>" + "".join(f"<li>{esc(x)}</li>" for x in result.findings) + "</ul>" if result.findings else "",
            figures_html(result.plots() if result.plots else [])]
    if result.files:
        body.append("<h2>Files</h2><ul>" + "".join(f"<li>{esc(k)}: {esc(v)}</li>" for k, v in result.files.items())
                    + "<li>figures: figures.json</li><li>captures: sessions/, campaign.json</li></ul>")
    write_page(out_dir / "report.html", f"tofhil bench {result.procedure}", body)
