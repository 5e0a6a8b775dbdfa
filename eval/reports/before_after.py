"""The compare page's before-and-after table: each correction, per region, against the reference."""

from __future__ import annotations

from typing import Any, Mapping

from tofhil.eval.reports.html import esc, fmt, notes_html


def before_after_html(metrics: Mapping[str, Any]) -> str:
    """One row per corrected variant and region: median and RMSE before -> after, the noise of
    the median, flagged pixels and, for a region made worse beyond its noise, the reason."""
    rows = []
    for label, v in metrics.get("variants", {}).items():
        for region, ch in (v.get("before_after") or {}).items():
            fl = ", ".join(f"{k} {100 * x:.0f} %" for k, x in ch["flagged_fraction"].items() if x > 0) or "-"
            verdict = ("<b>worse</b> (" + esc(" and ".join(ch["worse_in"])) + "): " + esc(ch["reason"] or "reason not known")
                       if ch["worse"] else "not worse")
            cells = [esc(label), esc(region), f"{fmt(ch['median_before_m'], 1e3)} &rarr; {fmt(ch['median_after_m'], 1e3)}",
                     fmt(ch["median_noise_m"], 1e3),
                     f"{fmt(ch['rmse_before_m'], 1e3)} &rarr; {fmt(ch['rmse_after_m'], 1e3)}", esc(fl), verdict]
            rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    if not rows:
        return ""
    notes = [n for v in metrics["variants"].values() for n in (v.get("correction") or {}).get("notes", [])]
    head = ("<tr><th>correction</th><th>region</th><th>median (mm) before &rarr; after</th>"
            "<th>noise of the median (mm)</th><th>RMSE (mm) before &rarr; after</th><th>flagged pixels</th>"
            "<th>verdict</th></tr>")
    held = metrics.get("heldout") or {}
    scored = (f"<p class='note'>Scored {'in-sample' if held.get('in_sample') else 'on held-out frames'}: "
              f"{esc(held['text'])}.</p>") if held else ""
    return ("<h2>Before and after each correction</h2>" + scored + notes_html(notes, "note")
            + f"<table>{head}{''.join(rows)}</table>"
            + "<p class='note'>Worse: |median| grown by more than 3 x the median's noise, or the RMSE by more than "
              "3 x the noise of the region's mean (per-pixel noise floor / sqrt(pixels), before and after "
              "combined). Flags: stray_light / multipath where the twin's removed light exceeds 3 x the noise; "
              "untrusted where light of clipped source pixels, unknown to the correction, exceeds 1 % of the "
              "signal; restored_from_twin: clipped pixels whose light the twin's prediction gave.</p>")
