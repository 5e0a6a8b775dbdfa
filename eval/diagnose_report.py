"""The diagnosis report: one self-contained HTML page with the cause, the evidence, the gain,
the residual maps before and after, the fitted effects' signatures and the ranking."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from tofhil import __version__
from tofhil.eval.report import CSS, _fig_uri, _grid, _image_panel, _robust_range


def _symmetric(images: list[np.ndarray]) -> tuple[float, float]:
    lo, hi = _robust_range(images)
    m = max(abs(lo), abs(hi), 1e-12)
    return -m, m


def figure_residuals(res: Any) -> str:
    m = res.maps
    fig, ax = _grid(4, 4.0, 3.2)
    vmin, vmax = _symmetric([m["depth_residual_before"] * 1e3, m["depth_residual_after"] * 1e3])
    _image_panel(fig, ax[0], m["depth_residual_before"] * 1e3, "depth residual, base twin (measured - twin)",
                 "RdBu_r", vmin, vmax, "mm")
    _image_panel(fig, ax[1], m["depth_residual_after"] * 1e3, "depth residual, extended twin", "RdBu_r", vmin, vmax, "mm")
    amin, amax = _symmetric([m["amplitude_residual_before"], m["amplitude_residual_after"]])
    _image_panel(fig, ax[2], m["amplitude_residual_before"], "amplitude residual, base twin", "PuOr_r", amin, amax, "DN")
    _image_panel(fig, ax[3], m["amplitude_residual_after"], "amplitude residual, extended twin", "PuOr_r",
                 amin, amax, "DN")
    return _fig_uri(fig)


def figure_signatures(res: Any) -> str | None:
    if not res.causes:
        return None
    fig, ax = _grid(2 * len(res.causes), 4.0, 3.2)
    for i, e in enumerate(res.causes):
        d = res.maps[f"signature_depth_{e}"] * 1e3
        a = res.maps[f"signature_amplitude_{e}"]
        _image_panel(fig, ax[2 * i], d, f"{e}: change of the twin's depth", "RdBu_r", *_symmetric([d]), "mm")
        _image_panel(fig, ax[2 * i + 1], a, f"{e}: change of the twin's amplitude", "PuOr_r", *_symmetric([a]), "DN")
    return _fig_uri(fig)


def figure_profile(res: Any) -> str:
    import matplotlib.pyplot as plt

    m = res.maps
    row = m["depth_measured_before"].shape[0] // 2
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.4), layout="constrained")
    usable = res.data.usable[row]
    x = np.arange(usable.size)
    for key, label, style in (("depth_measured_before", "measured", "k."), ("depth_twin_before", "base twin", "C0-"),
                              ("depth_twin_after", "extended twin", "C3-")):
        y = np.where(usable, m[key][row], np.nan)
        ax[0].plot(x, y, style, label=label, ms=3, lw=1)
    ax[0].set_xlabel("pixel column (centre row)")
    ax[0].set_ylabel("radial distance [m]")
    ax[0].legend(fontsize=8)
    ax[0].set_title("distance along the centre row")
    for key, label, style in (("depth_residual_before", "base twin", "C0-"), ("depth_residual_after", "extended twin", "C3-")):
        ax[1].plot(x, np.where(usable, m[key][row], np.nan) * 1e3, style, label=label, lw=1)
    ax[1].axhline(0, color="0.5", lw=0.5)
    ax[1].set_xlabel("pixel column (centre row)")
    ax[1].set_ylabel("measured - twin [mm]")
    ax[1].legend(fontsize=8)
    ax[1].set_title("residual along the centre row")
    return _fig_uri(fig)


def figure_ranking(res: Any) -> str:
    import matplotlib.pyplot as plt

    ranked = res.ranked
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(ranked) + 1.2), layout="constrained")
    names = [r["effect"] for r in ranked][::-1]
    gains = [100 * r["relative_gain"] for r in ranked][::-1]
    colors = ["C3" if r["significant"] else "0.6" for r in ranked][::-1]
    ax.barh(names, gains, color=colors)
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xlabel("held-out misfit removed [%] (red: significant after the parameter penalty)")
    ax.set_title("first round: every effect fitted alone on the training data")
    return _fig_uri(fig)


def figure_ndt(res: Any) -> str:
    fig, ax = _grid(2, 4.0, 3.2)
    _image_panel(fig, ax[0], res.maps["ndt_likelihood_before"], "NDT likelihood of measured points, base twin",
                 "viridis", 0, 1, "")
    _image_panel(fig, ax[1], res.maps["ndt_likelihood_after"], "NDT likelihood, extended twin", "viridis", 0, 1, "")
    return _fig_uri(fig)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def write_report(res: Any, path: Path, *, session_path: str, scene_path: str) -> None:
    cause = res.cause or "none: no significant effect is missing"
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>tofhil diagnose</title><style>{CSS}</style>"
             "</head><body><h1>tofhil diagnose</h1>",
             f"<p class='note'>session: {html.escape(session_path)}<br>base scene: {html.escape(scene_path)}<br>"
             f"extended scene: {html.escape(res.extended_scene)}<br>tofhil {__version__}, {res.seconds:.1f} s</p>",
             f"<h2>Cause: {html.escape(' + '.join(res.causes) if res.causes else cause)}</h2><ul>"]
    parts += [f"<li>{html.escape(line)}</li>" for line in res.evidence]
    parts.append("</ul>")
    if res.params:
        parts.append("<table><tr><th>effect</th><th>fitted parameters</th></tr>")
        for e, p in res.params.items():
            parts.append(f"<tr><td>{html.escape(e)}</td><td>{html.escape(', '.join(f'{k} = {v:.4g}' for k, v in p.items()))}</td></tr>")
        parts.append("</table>")
    parts.append("<h2>Gain on held-out data</h2><p class='note'>Held-out: the odd frames and the pixels of the "
                 "checkerboard blocks the fit did not see. The extended twin is the extended scene file, read back "
                 "and re-rendered.</p><table><tr><th>figure</th><th>base twin</th><th>extended twin</th></tr>")
    for k, v in res.gain.items():
        parts.append(f"<tr><td>{html.escape(k)}</td><td>{_fmt(v['before'])}</td><td>{_fmt(v['after'])}</td></tr>")
    parts.append("</table><h3>Per region</h3><table><tr><th>region</th><th>pixels</th><th>depth RMSE before [mm]</th>"
                 "<th>after [mm]</th><th>amplitude RMSE before</th><th>after</th></tr>")
    for name, b in res.regions["before"].items():
        a = res.regions["after"].get(name, {})
        parts.append(f"<tr><td>{html.escape(name)}</td><td>{b['pixels']}</td><td>{b['depth_rmse_m'] * 1e3:.2f}</td>"
                     f"<td>{a.get('depth_rmse_m', float('nan')) * 1e3:.2f}</td><td>{b['amplitude_rmse']:.3g}</td>"
                     f"<td>{a.get('amplitude_rmse', float('nan')):.3g}</td></tr>")
    parts.append("</table>")
    figures = [("Residual maps, before and after", figure_residuals(res),
                "Measured minus twin, on every usable pixel (training and held-out)."),
               ("Centre row", figure_profile(res), "Radial distance and residual along the centre row."),
               ("Ranking of the candidate effects", figure_ranking(res),
                "Share of the held-out misfit each effect removes when fitted alone.")]
    sig = figure_signatures(res)
    if sig:
        figures.insert(1, ("Signature of the fitted effects", sig,
                           "What each selected effect changes in the twin (with all selected effects minus without it)."))
    figures.append(("NDT likelihood maps", figure_ndt(res),
                    "Trilinear NDT likelihood of each measured held-out point on the twin's NDT grid."))
    for title, uri, caption in figures:
        parts.append(f"<h2>{html.escape(title)}</h2><p class='note'>{html.escape(caption)}</p>"
                     f"<img alt='{html.escape(title)}' src='{uri}'>")
    parts.append("<h2>Ranking</h2><table><tr><th>effect</th><th>held-out misfit removed</th><th>score gain</th>"
                 "<th>significant</th><th>parameters</th></tr>")
    for r in res.ranked:
        p = ", ".join(f"{k} = {v:.4g}" for k, v in r["params"].items())
        parts.append(f"<tr><td>{html.escape(r['effect'])}</td><td>{100 * r['relative_gain']:.2f}%</td>"
                     f"<td>{r['delta_score']:.1f}</td><td>{'yes' if r['significant'] else 'no'}</td>"
                     f"<td>{html.escape(p)}</td></tr>")
    parts.append("</table></body></html>")
    path.write_text("\n".join(parts), encoding="utf-8")
