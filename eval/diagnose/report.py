"""The diagnosis report: one self-contained HTML page with the cause, the evidence, the gain,
the residual maps before and after, the fitted effects' signatures and the ranking."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tofhil import __version__
from tofhil.eval.reports import html as H
from tofhil.eval.diagnose import verdict as V
from tofhil.eval.metrics.core import DEPTH_RMSE


def _usable(res: Any, img: np.ndarray) -> np.ndarray:
    return np.where(res.data.usable, img, np.nan)


def figure_depth_residuals(res: Any) -> str:
    m = res.maps
    return H.figure_residual_maps([("depth residual, base twin (measured - twin)", m["depth_residual_before"]),
                                   ("depth residual, extended twin", m["depth_residual_after"])])


def figure_amplitude_residuals(res: Any) -> str:
    m = res.maps
    return H.figure_residual_maps([("amplitude residual, base twin", m["amplitude_residual_before"]),
                                   ("amplitude residual, extended twin", m["amplitude_residual_after"])],
                                  unit="DN", scale=1.0, cmap="PuOr_r", floor=1e-9)


def figure_signatures(res: Any) -> str | None:
    if not res.causes:
        return None
    fig, ax = H.grid(2 * len(res.causes), 4.0, 3.2)
    for i, e in enumerate(res.causes):
        d = res.maps[f"signature_depth_{e}"] * 1e3
        a = res.maps[f"signature_amplitude_{e}"]
        H.image_panel(fig, ax[2 * i], d, f"{e}: change of the twin's depth", "RdBu_r", *H.symmetric_range([d]), "mm")
        H.image_panel(fig, ax[2 * i + 1], a, f"{e}: change of the twin's amplitude", "PuOr_r",
                      *H.symmetric_range([a]), "DN")
    return H.fig_uri(fig)


def figure_profile(res: Any) -> str:
    m = res.maps
    section = H.CrossSection.choose(res.data.usable.shape)
    return H.figure_cross_section(
        section, ("measured", _usable(res, m["depth_measured_before"])),
        [("base twin", _usable(res, m["depth_twin_before"])), ("extended twin", _usable(res, m["depth_twin_after"]))],
        [("base twin", m["depth_residual_before"]), ("extended twin", m["depth_residual_after"])])


def figure_ranking(res: Any) -> str:
    plt = H.pyplot()

    ranked = res.ranked
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(ranked) + 1.2), layout="constrained")
    names = [r["effect"] for r in ranked][::-1]
    gains = [100 * r["relative_gain"] for r in ranked][::-1]
    colors = ["C3" if r["significant"] else "0.6" for r in ranked][::-1]
    ax.barh(names, gains, color=colors)
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xlabel("held-out misfit removed [%] (red: significant after the parameter penalty)")
    ax.set_title("first round: every effect fitted alone on the training data")
    return H.fig_uri(fig)


def figure_ndt(res: Any) -> str:
    return H.figure_likelihood_maps([("measured points, base twin", res.maps["ndt_likelihood_before"]),
                                     ("measured points, extended twin", res.maps["ndt_likelihood_after"])])


#: What each gain row means (the keys of ``DiagnosisResult.gain``).
GAIN_LABELS = {"depth_rmse_m": (f"{DEPTH_RMSE} (mm)", 1e3), "depth_median_m": ("depth residual median (mm)", 1e3),
               "depth_mad_m": ("depth residual MAD (mm)", 1e3), "amplitude_rmse": ("amplitude RMSE (DN)", 1.0),
               "chi2_per_value": ("misfit per value (1.0 = noise)", 1.0),
               "icp_inlier_rmse_m": ("ICP inlier RMSE (mm)", 1e3), "icp_fitness": ("ICP fitness", 1.0),
               "ndt_score_per_point": ("NDT score per point", 1.0), "ndt_nvtl": ("NDT NVTL", 1.0),
               "ndt_mean_likelihood_trilinear": ("NDT mean likelihood (trilinear)", 1.0)}


def channel_table(res: Any) -> str:
    """Held-out misfit per channel before and after; a channel worse beyond its noise in red."""
    if not res.channels:
        return ""
    rows = ["<h3>Held-out misfit per channel (1.0 = noise)</h3><table><tr><th>channel</th><th>base twin</th>"
            "<th>extended twin</th><th>noise margin</th><th>worse</th></tr>"]
    for c, v in res.channels.items():
        style = " style='color:#c00;font-weight:bold'" if v["worse"] else ""
        rows.append(f"<tr{style}><td>{H.esc(c)}</td><td>{v['before_per_value']:.3f}</td>"
                    f"<td>{v['after_per_value']:.3f}</td><td>+{v['noise_margin_per_value']:.3f}</td>"
                    f"<td>{'WORSE' if v['worse'] else 'no'}</td></tr>")
    rows.append("</table><p class='note'>depth: the residual across the measured phasor (phase), amplitude: "
                "along it, offset: the tap offset channel. Worse: grown by more than z sqrt(2 n) of its n values "
                "(one-sided false-alarm probability 1e-3).</p>")
    return "".join(rows)


def effect_size_table(res: Any) -> str:
    """Each channel's held-out RMSE in its own units, base twin -> extended twin, the
    systematic part removed and the minimum a cause needs to be named."""
    es = getattr(res, "effect_size", None) or {}
    if not es.get("channels"):
        return ""
    rows = ["<h3>Is it worth naming? Held-out RMSE per channel in its own units</h3><table><tr><th>channel</th>"
            "<th>base twin</th><th>extended twin</th><th>noise (median pixel)</th><th>systematic part removed</th>"
            "<th>minimum</th><th>enough</th>"
            "<th>worse</th></tr>"]
    for c, v in es["channels"].items():
        style = " style='color:#c00;font-weight:bold'" if v["worse"] else ""
        u = H.esc(v["unit"])
        rows.append(f"<tr{style}><td>{H.esc(c)}</td><td>{v['rmse_before']:.4g} {u}</td><td>{v['rmse_after']:.4g} {u}"
                    f"</td><td>{v['noise_median_pixel']:.3g} {u}</td><td>{v['systematic_removed']:.3g} {u}</td>"
                    f"<td>{v['minimum_gain']:.3g} {u}</td>"
                    f"<td>{'yes' if v['enough'] else 'no'}</td><td>{'WORSE' if v['worse'] else 'no'}</td></tr>")
    rows.append(f"</table><p class='note'>{H.esc(es['rule'])}.</p>")
    if es.get("fitted_too_small"):
        rows.append(H.notes_html(["fitted, not named: " + t for t in es["fitted_too_small"].values()], css="note"))
    return "".join(rows)


def residual_region_table(res: Any) -> str:
    """Where the misfit left above noise is: connected regions, by object."""
    if not res.residual_regions:
        return "<p class='note'>No connected region of the held-out frames is left above noise.</p>"
    rows = ["<h3>Left above noise</h3><table><tr><th>pixels</th><th>x0, y0, x1, y1</th><th>objects</th>"
            "<th>what it looks like</th><th>misfit per value</th><th>depth residual (mm)</th>"
            "<th>depth spread / pixel noise (mm)</th><th>amplitude measured / twin</th>"
            "<th>amplitude residual (DN)</th></tr>"]
    num = lambda x, f: "-" if x is None else format(x, f)  # noqa: E731
    for r in res.residual_regions:
        objs = ", ".join(f"{k} {100 * f:.0f} %" for k, f in r["objects"].items())
        rows.append(f"<tr><td>{r['pixels']}</td><td>{', '.join(map(str, r['bbox_x0y0x1y1']))}</td>"
                    f"<td>{H.esc(objs)}</td><td>{H.esc(r.get('kind', ''))}</td><td>{r['misfit_per_value']:.2f}</td>"
                    f"<td>{r['depth_residual_mm']:+.1f}</td>"
                    f"<td>{num(r.get('depth_spread_mm'), '.1f')} / {num(r.get('depth_sigma_mm'), '.1f')}</td>"
                    f"<td>{num(r.get('amplitude_ratio'), '.2f')}</td><td>{r['amplitude_residual']:+.3g}</td></tr>")
    rows.append("</table><p class='note'>Connected pixels (held-out frames) whose 3 x 3 mean misfit is above the "
                "noise threshold of its values. What it looks like: a median depth offset beyond "
                f"{V.REGION_SIGMAS:g} x one pixel's noise is an object the twin lacks (the capture nearer) or "
                "misplaces (the twin nearer); a spread about it beyond that, a shape the twin's surface does not "
                "follow; the depth right and the amplitude ratio beyond that many of its noise (the scene's "
                "amplitude model error included), a wrong material.</p>")
    return "".join(rows)


def structure_list(res: Any) -> str:
    """What the residual left shows (edges, smooth field errors, fixed patterns, spots)."""
    items = getattr(res, "structure", None) or []
    if not items:
        return ("<p class='note'>The residual left shows no structure above its noise: no edge excess, no smooth "
                "field error, no row or column pattern, no spot.</p>")
    return ("<h3>What the residual left shows</h3>" + H.notes_html([f["text"] for f in items], css="warn")
            + "<p class='note'>Each part tested against the noise of its own pixels (chi-square, false-alarm "
              "probability 1e-3); see docs/diagnose.md, residual structure.</p>")


def _value(v: Any) -> str:
    """A fitted parameter for the tables: numbers to 4 digits, anything else (a map's form,
    its file) as it is."""
    return f"{v:.4g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


#: A cause that removes less of the held-out excess than this is tentative: shown beside its
#: alternatives, not as the page's headline.
TENTATIVE_BELOW = 0.5


def headline(res: Any) -> str:
    """The verdict and the share explained first; a cause only as firmly as its gain allows."""
    v = res.verdict
    if v is None:
        return "Cause: " + (" + ".join(res.causes) if res.causes else "none")
    share = v.excess_removed
    text = f"Verdict: {v.kind}"
    if share is not None and v.kind in (V.Kind.EXPLAINED, V.Kind.PARTLY_EXPLAINED):
        text += f", {100 * share:.0f} % of the held-out excess over noise explained"
    if res.causes:
        if share is not None and share < TENTATIVE_BELOW:
            alts = sorted({a["effect"] for e in res.causes for a in res.alternatives.get(e, [])} - set(res.causes))
            text += (" -- tentative: " + " + ".join(res.causes)
                     + (f" (or {', '.join(alts)})" if alts else "") + ", which removes less than half of the excess")
        else:
            text += " -- cause: " + " + ".join(res.causes)
    return text


def defects_section(res: Any) -> str:
    """The defective pixels left out before the fit: how many of which kind, and a map."""
    d = res.defects or {}
    if not d.get("pixels"):
        return "<p class='note'>Defective pixels: none found" + (
            " (" + "; ".join(H.esc(n) for n in d.get("notes", [])) + ")" if d.get("notes") else "") + ".</p>"
    rows = "".join(f"<tr><td>{H.esc(k)}</td><td>{v['pixels']}</td><td>{H.esc(v['what'])}</td></tr>"
                   for k, v in d["kinds"].items() if v["pixels"])
    fig = ""
    if "defects" in res.maps:
        plt = H.pyplot()
        f, ax = plt.subplots(figsize=(4.0, 3.2))
        ax.imshow(res.maps["defects"], cmap="Reds", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title("defective pixels (left out)")
        ax.set_xticks([])
        ax.set_yticks([])
        fig = f"<img src='{H.fig_uri(f)}' alt='defect map'>"
    return (f"<h3>Defective pixels</h3><p class='warn'>{H.esc(d['text'])}</p>"
            f"<table><tr><th>kind</th><th>pixels</th><th>what</th></tr>{rows}</table>{fig}")


def residual_by_channel_table(res: Any) -> str:
    """The held-out residual by channel, base twin and extended, each estimate against its noise."""
    t = res.channel_table or {}
    if not t:
        return ""
    after = {r["name"]: r for r in t.get("after", {}).get("readings", [])}
    rows = []
    for r in t.get("before", {}).get("readings", []):
        a = after.get(r["name"], {})

        def z(x: Any) -> str:
            return "-" if x is None else f"{x:+.1f}"
        style = " style='color:#c00'" if r["significant"] else ""
        rows.append(f"<tr><td>{H.esc(r['channel'])}</td><td>{H.esc(r['name'])}</td><td{style}>{z(r['z'])}</td>"
                    f"<td>{z(a.get('z'))}</td><td>{H.esc(r['text'])}</td></tr>")
    notes = t.get("before", {}).get("notes", [])
    return ("<h3>The residual by channel</h3><p class='note'>Each estimate over its standard error from the held-out "
            f"noise (z; |z| &gt; {t.get('before', {}).get('z_significant', 5):g} is a part the noise cannot make), "
            "with the base twin and with the extended one.</p><table><tr><th>channel</th><th>reading</th>"
            "<th>z, base twin</th><th>z, extended</th><th>base twin</th></tr>" + "".join(rows) + "</table>"
            + (H.notes_html(notes, css="note") if notes else ""))


def write_report(res: Any, path: Path, *, session_path: str, scene_path: str, camera: Any = None) -> None:
    """The diagnosis page: cause, evidence, held-out gain, per-region table, figures, ranking;
    with the twin's ``camera`` a lens prescription's ghost PSFs (eval/reports/optics.py)."""
    esc = H.esc
    v = res.verdict
    parts = [f"<p class='note'>session: {esc(session_path)}<br>base scene: {esc(scene_path)}<br>"
             f"extended scene: {esc(res.extended_scene)}<br>tofhil {__version__}, {res.seconds:.1f} s</p>",
             f"<h2>{esc(headline(res))}</h2>"]
    if v is not None:
        css = "warn" if v.kind.leaves_a_residual else "note"
        parts.append(f"<p class='{css}'><b>Verdict: {esc(v.kind)}.</b> {esc(v.text)}</p>")
        if getattr(res, "left", None):
            parts.append(f"<p class='warn'><b>{esc(res.left)}</b></p>")
        if v.notes:
            parts.append(H.notes_html(v.notes, css="warn"))
    parts.append(H.notes_html(res.evidence, css="note"))
    parts.append(defects_section(res))
    parts.append(channel_table(res))
    parts.append(residual_by_channel_table(res))
    parts.append(effect_size_table(res))
    parts.append(residual_region_table(res))
    parts.append(structure_list(res))
    if res.params:
        parts.append("<table><tr><th>effect</th><th>fitted parameters</th></tr>")
        for e, p in res.params.items():
            form = res.forms.get(e, "")
            parts.append(f"<tr><td>{esc(e)}{esc(f' ({form} form)' if form else '')}</td><td>{esc(', '.join(f'{k} = {_value(v)}' for k, v in p.items()))}</td></tr>")
        parts.append("</table>")
    parts.append("<h2>Gain on held-out data</h2><p class='note'>Held-out: the odd frames and the pixels of the "
                 "checkerboard blocks the fit did not see. The extended twin is the extended scene file, read back "
                 f"and re-rendered. {esc(DEPTH_RMSE)}: sqrt(mean((measured - twin)^2)) over the held-out pixels "
                 "valid in both (signal above noise and no clipped tap in the measurement, signal above noise in "
                 "both twins) -- the figure tofhil compare gives on the same pixels.</p>"
                 "<table><tr><th>figure</th><th>base twin</th><th>extended twin</th></tr>")
    for k, v in res.gain.items():
        label, scale = GAIN_LABELS.get(k, (k, 1.0))
        parts.append(f"<tr><td>{esc(label)}</td><td>{H.fmt(v['before'], scale)}</td>"
                     f"<td>{H.fmt(v['after'], scale)}</td></tr>")
    parts.append("</table><h3>Per region (held-out pixels)</h3>")
    ev = res.evaluations
    parts.append(H.region_table([(twin, r) for twin, key in (("base twin", "before"), ("extended twin", "after"))
                                 for r in ev[key].regions.values()], label="twin"))
    figures = [("Depth residual maps, before and after", figure_depth_residuals(res),
                "Measured minus twin on every pixel valid in both (training and held-out), shared symmetric "
                f"scale +-max(|p{H.RESIDUAL_PERCENTILES[0]:g}|, |p{H.RESIDUAL_PERCENTILES[1]:g}|)."),
               ("Amplitude residual maps, before and after", figure_amplitude_residuals(res),
                "Measured minus twin amplitude |S| (DN), same pixels and scale rule."),
               ("Cross-section", figure_profile(res), "Radial distance and residual along the centre row."),
               ("Ranking of the candidate effects", figure_ranking(res),
                "Share of the held-out misfit each effect removes when fitted alone.")]
    sig = figure_signatures(res)
    if sig:
        figures.insert(2, ("Signature of the fitted effects", sig,
                           "What each selected effect changes in the twin (with all selected effects minus without it)."))
    figures.append(("NDT likelihood maps", figure_ndt(res),
                    "Trilinear NDT likelihood of each measured held-out point on the twin's NDT grid."))
    parts.append(H.figures_html(figures))
    parts.append("<h2>Ranking</h2><table><tr><th>effect</th><th>held-out misfit removed</th><th>score gain</th>"
                 "<th>significant</th><th>channels worse</th><th>at a bound</th><th>parameters</th></tr>")
    for r in res.ranked:
        p = ", ".join(f"{k} = {_value(v)}" for k, v in r["params"].items())
        worse = ", ".join(r.get("worse_channels", []))
        parts.append(f"<tr><td>{esc(r['effect'])}</td><td>{100 * r['relative_gain']:.2f}%</td>"
                     f"<td>{r['delta_score']:.1f}</td><td>{'yes' if r['significant'] else 'no'}</td>"
                     f"<td style='color:#c00'>{esc(worse)}</td><td>{esc(', '.join(r.get('at_bounds', [])))}</td>"
                     f"<td>{esc(p)}</td></tr>")
    parts.append("</table>")
    if camera is not None:
        from tofhil.eval.reports.optics import lens_section

        parts.extend(lens_section(camera, whose="the twin's camera (base scene)"))
    H.write_page(path, "tofhil diagnose", parts)
