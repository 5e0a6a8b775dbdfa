"""The sweep report fits the page (issue 34's walkthrough): no empty panel for a column
without values, categories not joined by lines, the case table in a box that scrolls."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from tofhil.app.sweep.results import metric_panel, report_metrics, write_report  # noqa: E402
from tofhil.app.sweep.spec import SweepSpec  # noqa: E402


def _table() -> pd.DataFrame:
    return pd.DataFrame({
        "case": [f"{i:04d}-x" for i in range(6)], "status": ["ok"] * 6, "error": [""] * 6,
        "camera.preset": ["epc635", "holmlund_thesis", "epc635", "holmlund_thesis", "o3r", "o3r"],
        "effects.stray_light.weight": [0.01, 0.01, 0.03, 0.03, 0.05, 0.05],
        "compare.measured.regions.all.depth_rmse_m": [0.01, 0.02, 0.03, 0.02, 0.05, 0.04],
        "compare.measured.regions.square.depth_rmse_m": [np.nan] * 6,   # a column without values
    })


def test_a_column_without_values_gets_no_panel() -> None:
    df = _table()
    wanted = ["compare.measured.regions.all.depth_rmse_m", "compare.measured.regions.square.depth_rmse_m"]
    assert report_metrics(df, ["camera.preset"], wanted) == wanted[:1]
    assert "compare.measured.regions.square.depth_rmse_m" not in report_metrics(df, ["camera.preset"])


def test_categories_are_not_joined_by_a_line() -> None:
    fig, (cat, num) = plt.subplots(1, 2)
    y = pd.Series([1.0, 2.0, 3.0, 2.5])
    metric_panel(cat, pd.Series([0, 1, 0, 1]), y, ["a", "b"])
    metric_panel(num, pd.Series([0.1, 0.2, 0.1, 0.2]), y, None)
    assert all(line.get_linestyle() in ("None", "none", "") for line in cat.get_lines())
    assert any(line.get_linestyle() == "-" for line in num.get_lines())
    plt.close(fig)


def test_the_case_table_scrolls_inside_the_page(tmp_path: Path) -> None:
    spec = SweepSpec(name="t", scene="wall", axes={"camera.preset": ["epc635", "holmlund_thesis", "o3r"],
                                                   "effects.stray_light.weight": [0.01, 0.03, 0.05]})
    page = write_report(_table(), spec, tmp_path).read_text()
    assert "<div class='wide'><table class='cases'>" in page
    assert ".wide{max-width:100%;overflow-x:auto}" in page
