"""What a sweep writes: one record per finished case, the table, and the report page.

Every finished case is one ``cases/CASE_ID.json`` (written atomically, so a killed sweep
never leaves half a record); the table (``results.parquet``, ``results.csv``: one row per
case, the axis values and every metric) and the self-contained ``report.html`` (each metric
against each swept axis, the failed cases, the table) are rebuilt from those files.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Sequence

from tofhil.app.sweep.cases import effects_label
from tofhil.outputs import atomic_path

if TYPE_CHECKING:
    from tofhil.app.sweep.spec import SweepSpec


def write_record(out_dir: str | Path, record: Mapping[str, Any]) -> Path:
    """Write ``cases/CASE_ID.json`` atomically (a temporary file renamed over it: a kill
    leaves the old record or the new one, never half of one)."""
    from tofhil.eval.metrics.core import json_safe

    cases = Path(out_dir) / "cases"
    cases.mkdir(parents=True, exist_ok=True)
    path = cases / f"{record['id']}.json"
    with atomic_path(path) as tmp:  # a plain file (the umask's mode), as the table's
        tmp.write_text(json.dumps(json_safe(dict(record)), indent=1), encoding="utf-8")
    return path


def read_records(out_dir: str | Path) -> dict[str, dict[str, Any]]:
    """The finished cases of a sweep directory, by case id (unreadable files are skipped:
    they are redone)."""
    out = {}
    for p in sorted((Path(out_dir) / "cases").glob("*.json")):
        try:
            r = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if isinstance(r, dict) and r.get("id") == p.stem:
            out[p.stem] = r
    return out


def _param_cell(name: str, value: Any) -> Any:
    if name == "effects" and isinstance(value, Mapping):
        return effects_label(value)
    return value


def results_table(records: Iterable[Mapping[str, Any]], axes: Sequence[str]) -> Any:
    """One row per case: id, status, error, the axis values, seconds, then every metric."""
    import pandas as pd

    rows = []
    for r in sorted(records, key=lambda r: r["index"]):
        row: dict[str, Any] = {"case": r["id"], "status": r["status"], "error": r.get("error")}
        for a in axes:
            row[a] = _param_cell(a, r["params"].get(a))
        row["seconds"] = r.get("seconds")
        row.update(r.get("metrics") or {})
        rows.append(row)
    df = pd.DataFrame(rows)
    for c in df.columns:  # a column of mixed numbers and None stays numeric
        if df[c].dtype == object and c not in axes and c not in ("case", "status", "error"):
            conv = pd.to_numeric(df[c], errors="coerce")
            if conv.notna().sum() == df[c].notna().sum():
                df[c] = conv
    return df


def write_table(df: Any, out_dir: str | Path) -> None:
    """``results.parquet`` and ``results.csv`` (each written to a temporary name first)."""
    out = Path(out_dir)
    with atomic_path(out / "results.parquet") as tmp:
        df.to_parquet(tmp, index=False)
    with atomic_path(out / "results.csv") as tmp:
        df.to_csv(tmp, index=False)


# ----------------------------------------------------------------------------- the report page
_PREFERRED = ("correct", "rmse", "chi2", "removed", "mean_abs", "median")


def report_metrics(df: Any, axes: Sequence[str], wanted: Sequence[str] = (), limit: int = 12) -> list[str]:
    """The metric columns to plot: those asked for, else numeric ones that vary, the
    headline figures (RMSE, misfit, correct) first."""
    if wanted:  # asked for, but a column without a value would be an empty panel
        return [m for m in wanted if m in df.columns and _numeric(df[m]).notna().any()]
    cols = []
    for c in df.columns:
        if c in axes or c in ("case", "status", "error") or c.endswith("seconds") and c != "seconds":
            continue
        v = _numeric(df[c])
        if v.notna().sum() >= 1 and v.nunique(dropna=True) > 1:
            cols.append(c)
    cols.sort(key=lambda c: (min((i for i, p in enumerate(_PREFERRED) if p in c), default=len(_PREFERRED)), c))
    return cols[:limit]


def _numeric(column: Any) -> Any:
    """A column as floats (NaN where a value is not a finite number)."""
    import numpy as np
    import pandas as pd

    v = column.astype(float) if column.dtype == bool else pd.to_numeric(column, errors="coerce")
    return v.where(np.isfinite(v))


def metric_panel(a: Any, x: Any, y: Any, cats: Sequence[str] | None) -> None:
    """One metric against one axis: the cases as points, the mean over cases of each value as
    a line for a numeric axis, and as a mark per category for a categorical one (categories
    have no order a line between them would mean)."""
    import pandas as pd

    a.plot(x, y, "o", alpha=0.6, ms=4)
    means = pd.DataFrame({"x": x, "y": y}).groupby("x")["y"].mean()
    if cats is None:
        a.plot(means.index, means.values, "-", color="C1", lw=1.2, label="mean")
    else:
        a.plot(means.index, means.values, "_", color="C1", ms=14, mew=2, linestyle="none", label="mean")


def write_report(df: Any, spec: SweepSpec, out_dir: str | Path) -> Path:
    """A self-contained ``report.html``: each metric against each swept axis, the failed
    cases with their errors, and the table."""
    import pandas as pd

    from tofhil.eval.reports import html as H

    out = Path(out_dir)
    axes = [a for a in spec.axes if a in df.columns and df[a].nunique(dropna=True) > 1] or \
        [a for a in spec.axes if a in df.columns]
    ok = df[df["status"] == "ok"] if len(df) else df
    metrics = report_metrics(ok, list(spec.axes), spec.report_metrics)
    figures = []
    for ax_name in axes:
        if not metrics or not len(ok):
            break
        x_raw = ok[ax_name]
        numeric = pd.api.types.is_numeric_dtype(x_raw)
        cats = None if numeric else sorted(map(str, x_raw.dropna().unique()))
        x = x_raw.astype(float) if numeric else x_raw.astype(str).map({c: i for i, c in enumerate(cats)})
        fig, axs = H.grid(len(metrics), width=4.0, height=3.0)
        for a, m in zip(axs, metrics):
            metric_panel(a, x, _numeric(ok[m]), cats)
            a.set_xlabel(ax_name, fontsize=8)
            a.set_title(m, fontsize=8)
            a.tick_params(labelsize=7)
            if cats is not None:
                a.set_xticks(range(len(cats)))
                a.set_xticklabels(cats, rotation=30, ha="right", fontsize=7)
            elif numeric and x.min() > 0 and x.max() / max(x.min(), 1e-300) > 50:
                a.set_xscale("log")
        figures.append((f"metrics against {ax_name}", H.fig_uri(fig),
                        "each point a case; the line (a mark per category) the mean over cases with the same "
                        "value (other axes vary)"))
    n_err = int((df["status"] != "ok").sum()) if len(df) else 0
    body = [f"<p>{H.esc(spec.description or spec.name)}</p>",
            f"<p>{len(df)} cases ({n_err} failed); design {H.esc(spec.design)}; axes: "
            f"{H.esc(', '.join(spec.axes) or '-')}. Scene: {H.esc(spec.scene or '-')}.</p>",
            H.figures_html(figures)]
    if n_err:
        body.append("<h2>failed cases</h2>" + H.notes_html(
            [f"{r['case']}: {r['error']}" for _, r in df[df['status'] != 'ok'].iterrows()]))
    cols = ["case", "status"] + list(spec.axes) + metrics
    cols = [c for c in cols if c in df.columns]
    head = "<tr>" + "".join(f"<th>{H.esc(c)}</th>" for c in cols) + "</tr>"
    rows = "".join("<tr>" + "".join(f"<td>{H.esc(H.fmt(r[c]) if isinstance(r[c], float) else r[c])}</td>"
                                    for c in cols) + "</tr>" for _, r in df.iterrows())
    # in a box of the page's width that scrolls: a sweep's columns are many and their names long
    body.append(f"<h2>cases</h2><div class='wide'><table class='cases'>{head}{rows}</table></div>"
                "<p class='note'>every figure per case: results.csv, "
                "results.parquet; each case's files: cases/CASE_ID/</p>")
    H.write_page(out / "report.html", f"sweep: {spec.name}", body)
    return out / "report.html"

