"""The report of ``tofhil simulate --report DIR``: where each pixel's light comes from (shares
by bounce and by source object, :mod:`tofhil.sim.multipath`), a direct-ToF scene's histograms
and peaks, and a lens prescription's ghost PSFs."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from tofhil import __version__
from tofhil.outputs import prepare_output_dir
from tofhil.eval.reports import html as H

#: Files a simulate report writes.
OUTPUTS = ("report.html", "report.json")


def figure_shares(shares: Any) -> str:
    """Maps of the shares by bounce and by source object, one colour scale 0..1."""
    panels = [(("direct light" if b == 0 else f"{b} bounce{'s' if b > 1 else ''}") + " (share)", img)
              for b, img in enumerate(shares.by_bounce)]
    panels += [(f"light from object {n!r} (share)", img) for n, img in zip(shares.object_names, shares.by_object)]
    fig, axes = H.grid(len(panels))
    for ax, (t, img) in zip(axes, panels):
        H.image_panel(fig, ax, img, t, "magma", 0.0, 1.0, "share of the pixel's light")
    return H.fig_uri(fig)


def histogram_pixels(peaks: Any) -> list[tuple[str, tuple[int, int]]]:
    """Pixels worth plotting: the centre and the pixel with the most peaks (strongest second)."""
    h, w = peaks.time_s.shape[1:]
    out = [("centre pixel", (h // 2, w // 2))]
    if peaks.time_s.shape[0] > 1:
        second = np.where(np.isfinite(peaks.time_s[1]), peaks.significance[1], -np.inf)
        if np.isfinite(second).any() and second.max() > -np.inf:
            y, x = np.unravel_index(int(np.argmax(second)), second.shape)
            out.append(("strongest second peak", (int(y), int(x))))
    return out


def figure_histograms(sim: Any, frame: int = 0) -> str:
    """Counts per bin of a few pixels (frame ``frame``), the expected counts and the peaks found."""
    plt = H.pyplot()
    cfg = sim.config
    peaks = sim.peaks[frame]
    pix = histogram_pixels(peaks)
    fig, axes = plt.subplots(1, len(pix), figsize=(6.0 * len(pix), 3.6), squeeze=False, layout="constrained")
    t_ns = (cfg.edges_s[:-1] + 0.5 * cfg.bin_width_s) * 1e9
    from tofhil.sim.direct_tof import record_probabilities

    for ax, (label, (y, x)) in zip(axes[0], pix):
        lam = sim.expected_photons[:, y, x]
        ax.step(t_ns, sim.counts[frame][:, y, x], where="mid", lw=0.8, label="counts")
        ax.plot(t_ns, cfg.cycles_per_frame * record_probabilities(lam[:, None], cfg.dead_bins)[:, 0], lw=0.8,
                label="expected (pile-up)")
        ax.plot(t_ns, cfg.cycles_per_frame * lam, lw=0.8, ls="--", label="photons (no dead time)")
        for k, t in enumerate(peaks.time_s[:, y, x]):
            if np.isfinite(t):
                ax.axvline(t * 1e9, color="C3" if k == 0 else "C4", lw=0.8, ls=":")
        ax.set_title(f"{label} (row {y}, column {x}): {int(peaks.count[y, x])} peak(s)", fontsize=9)
        ax.set_xlabel("time after the pulse (ns)", fontsize=8)
        ax.set_ylabel("counts per bin", fontsize=8)
        ax.legend(fontsize=7)
    return H.fig_uri(fig)


def figure_direct_maps(sim: Any, frame: int = 0) -> str:
    """Depth of the strongest peak, the number of peaks and the second peak's distance."""
    p = sim.peaks[frame]
    d0 = p.distance_m[0]
    fig, axes = H.grid(3)
    lo, hi = H.robust_range([d0])
    H.image_panel(fig, axes[0], d0, "distance of the strongest peak", "viridis", lo, hi, "m")
    H.image_panel(fig, axes[1], p.count.astype(float), "peaks above the threshold", "cividis", 0, p.time_s.shape[0],
                  "peaks")
    second = p.distance_m[1] if p.time_s.shape[0] > 1 else np.full_like(d0, np.nan)
    lo2, hi2 = H.robust_range([second]) if np.isfinite(second).any() else (lo, hi)
    H.image_panel(fig, axes[2], second, "distance of the second peak (multipath)", "viridis", lo2, hi2, "m")
    return H.fig_uri(fig)


def write_simulate_report(out_dir: str | Path, scene: Any, *, shares: Any = None, direct: Any = None,
                          session_path: str | Path = "", force: bool = False, notes: Sequence[str] = ()) -> Path:
    """Write ``report.html`` and ``report.json`` into ``out_dir``; returns the page's path.
    ``notes``: what the page does not show, and why (one line each, above the figures)."""
    out = prepare_output_dir(out_dir, OUTPUTS, force=force)
    figs: list[tuple[str, str | None, str]] = []
    payload: dict[str, Any] = {"software": f"tofhil {__version__}", "scene": str(getattr(scene, "source", "")),
                               "session": str(session_path)}
    if shares is not None:
        figs.append(("Where the light comes from", figure_shares(shares),
                     "Share of each pixel's returned emitter light by bounce count (direct = emitter -> seen "
                     "surface -> camera) and by the object the light came from (direct light: the seen object; "
                     "indirect light: the object of the vertex before the seen surface). Shares sum to 1 per "
                     "lit pixel."))
        payload["multipath_shares"] = shares.summary()
    if direct is not None:
        cfg = direct.config
        figs.append(("Direct ToF: depth and multipath peaks", figure_direct_maps(direct),
                     f"Peaks of the Coates-corrected histograms (frame 0) above {cfg.peak_threshold:g} sigma of the "
                     "matched filter's noise, strongest first."))
        figs.append(("Direct ToF: histograms", figure_histograms(direct),
                     f"{cfg.cycles_per_frame} cycles, {cfg.bin_width_s * 1e12:g} ps bins, dead time "
                     f"{cfg.dead_time_s * 1e9:g} ns; dotted lines: the peaks found."))
        p = direct.peaks[0]
        payload["direct_tof"] = {"config": cfg.to_dict(), "pixels_with_peak": int(np.sum(p.count >= 1)),
                                 "pixels_with_second_peak": int(np.sum(p.count >= 2)),
                                 "max_photons_per_cycle": float(direct.expected_photons.sum(axis=0).max())}
    payload["notes"] = list(notes)
    body = [f"<p class='note'>scene: {H.esc(payload['scene'])}<br>session: {H.esc(session_path)}<br>"
            f"tofhil {__version__}</p>", H.notes_html(list(notes), css="note"), H.figures_html(figs)]
    from tofhil.eval.reports.optics import lens_section

    body.extend(lens_section(scene.camera, whose="the scene's camera"))
    out.mkdir(parents=True, exist_ok=True)
    H.write_json(out / "report.json", payload)
    H.write_page(out / "report.html", f"tofhil simulate: {getattr(scene, 'name', '') or 'scene'}", body)
    return out / "report.html"


__all__ = ["OUTPUTS", "figure_direct_maps", "figure_histograms", "figure_shares", "write_simulate_report"]
