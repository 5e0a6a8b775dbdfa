"""Stray light from the optics on the thesis's scene: which ghosts dominate the distance error,
and how much the band-pass filter and the sensor's reflectance change it.

The bundled ``dark_square_card_lens`` scene (white wall at 1 m, a dark square of 5 % of the
wall's reflectance in the middle, a white card 0.17 m from the lens, seen through the scene's
lens prescription) is rendered ONCE. The lens stage (sim/optics.py) is then applied with the
prescription's whole stray light, with each group of ghosts alone (between lens surfaces;
involving the band-pass filter; the cover glass; the sensor) and the housing veil alone, and
with the filter's and the sensor's reflectance varied. The distance error of a case is the
noise-free distance (44 MHz fundamental) minus that of the same lens without stray light,
averaged over the dark square, the wall (outside square and card, and outside the card's
shadow, where there is no direct light) and the card.

Run: ``python benchmarks/optics_ghosts.py [--out DIR]`` (writes ``DIR/report.html`` with the
ghost PSFs and the error maps, and ``DIR/results.json``; default ``optics-ghosts-out``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from tofhil.demod import phase_to_distance
from tofhil.eval.reports import html
from tofhil.eval.reports.optics import figure_ghost_psfs, ghost_group, ghost_table_html, lens_summary
from tofhil.sim.optics import LensCamera, apply_lens, lens_model
from tofhil.sim.scene import load_scene
from tofhil.sim.sensor import OpticalSignal, waveform_from_scene
from tofhil.sim.straylight import StrayLightPSF
from tofhil.sim.twin import Twin


def distance(signal: OpticalSignal) -> np.ndarray:
    s1 = signal.phasor_w[0, signal.harmonics.index(1)]
    return phase_to_distance(np.mod(np.angle(s1), 2 * math.pi), float(signal.freq_hz[0]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="optics-ghosts-out")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = load_scene("dark_square_card_lens")
    cam = scene.camera
    assert isinstance(cam, LensCamera)
    twin = Twin(scene)
    scene2, result = twin.render({})
    base = OpticalSignal.from_render(result, waveform_from_scene(scene2))
    oid = np.asarray(result.object_id)
    names = [o.name for o in scene.objects]
    # The card's shadow on the wall (the emitter sits beside the lens) gets no direct light:
    # there the distance is the stray light's alone, so it is left out of the regions.
    amp = np.abs(base.phasor_w[0, base.harmonics.index(1)])
    lit = amp > 1e-4 * np.median(amp)
    regions = {"square": (oid == names.index("square")) & lit, "card": (oid == names.index("card")) & lit,
               "wall": (oid == names.index("wall")) & lit}
    model = lens_model(cam.lens)
    pitch = float(cam.pixel_pitch_m)
    t_render = time.perf_counter() - t0

    def run(psf: StrayLightPSF, camera: LensCamera = cam) -> dict[str, Any]:
        ref = distance(apply_lens(base, camera, psf=StrayLightPSF(conserve=False)))
        d = distance(apply_lens(base, camera, psf=psf))
        err = d - ref
        return {"err": err, **{k: float(np.mean(err[m]) * 1e3) for k, m in regions.items()}}

    ghosts = model.ghosts
    rows: list[dict[str, Any]] = []
    maps: list[tuple[str, np.ndarray]] = []

    def record(label: str, r: dict[str, Any], **extra: Any) -> None:
        rows.append({"case": label, **{k: r[k] for k in regions}, **extra})
        if len(maps) < 6:
            maps.append((label, np.where(lit, r["err"], np.nan)))  # the unlit shadow blank

    full = model.stray_light(pitch)
    record("all (ghosts + housing veil)", run(full), weight=full.total_weight)
    groups = ("sensor", "filter", "cover glass", "lens")
    for grp in groups:
        sub = [g for g in ghosts if ghost_group(g) == grp]
        psf = model.stray_light(pitch, ghosts=sub, veil=False)
        record(f"{grp} ghosts only ({len(sub)})", run(psf), weight=psf.total_weight)
    psf = model.stray_light(pitch, ghosts=[], veil=True)
    record("housing veil only", run(psf), weight=psf.total_weight)

    # The filter's and the sensor's reflectance: the prescription changed, the render reused.
    sweep: list[dict[str, Any]] = []
    pres = cam.lens
    for what, values in (("sensor_reflectance", (0.0, 0.05, 0.15, 0.3)), ("filter_reflectance", (0.0, 0.01, 0.02, 0.05))):
        for v in values:
            if what == "sensor_reflectance":
                p2 = replace(pres, sensor_reflectance=v)
            else:
                p2 = replace(pres, surfaces=tuple(replace(s, reflectance=v) if "filter" in s.name else s
                                                  for s in pres.surfaces))
            cam2 = replace(cam, lens=p2)
            m2 = lens_model(p2)
            r = run(m2.stray_light(pitch), cam2)
            sweep.append({"parameter": what, "value": v, **{k: r[k] for k in regions},
                          "weight": m2.stray_light(pitch).total_weight})
    t_all = time.perf_counter() - t0

    # Figures: the ghost PSF of a point source (the library's report figure, eval/reports/optics.py).
    psf_uri = figure_ghost_psfs(cam)
    fig, axes = html.grid(len(maps))
    lim = max(float(np.nanpercentile(np.abs(e) * 1e3, 99)) for _, e in maps) or 1.0
    for ax, (title, err) in zip(axes, maps):
        html.image_panel(fig, ax, err * 1e3, title, "RdBu_r", -lim, lim, "mm")
    err_uri = html.fig_uri(fig)

    table = ["<table><tr><th>case</th><th>scattered fraction</th><th>square (mm)</th><th>wall (mm)</th>"
             "<th>card (mm)</th></tr>"]
    for r in rows:
        table.append(f"<tr><td>{html.esc(r['case'])}</td><td>{r['weight']:.4f}</td><td>{r['square']:.2f}</td>"
                     f"<td>{r['wall']:.3f}</td><td>{r['card']:.3f}</td></tr>")
    table.append("</table><h2>Filter and sensor reflectance</h2><table><tr><th>parameter</th><th>value</th>"
                 "<th>scattered fraction</th><th>square (mm)</th><th>wall (mm)</th><th>card (mm)</th></tr>")
    for r in sweep:
        table.append(f"<tr><td>{r['parameter']}</td><td>{r['value']}</td><td>{r['weight']:.4f}</td>"
                     f"<td>{r['square']:.2f}</td><td>{r['wall']:.3f}</td><td>{r['card']:.3f}</td></tr>")
    table.append("</table>")
    gtab = ["<h2>Ghosts of the prescription</h2>", ghost_table_html(cam)]
    lens_info = lens_summary(cam)
    html.write_page(out / "report.html", "Stray light from the optics: dark_square_card_lens", [
        f"<p class='note'>{html.esc(lens_info)}. Distance errors are means over each region of the noise-free "
        "distance with the stray light minus without (same lens, same render).</p>", "".join(table),
        html.figures_html([("Ghost PSFs", psf_uri, "The prescription's ghosts (no veil) for a point source at three "
                            "positions: light per pixel as a fraction of the source's (log10)."),
                           ("Distance error maps", err_uri, "Distance with the stray light minus without (mm); "
                            "the card's shadow (no direct light) is left blank.")]),
        "".join(gtab)])
    res = {"lens": lens_info, "cases": rows, "sweep": sweep, "render_s": t_render, "total_s": t_all,
           "ghosts": [{"name": g.name, "group": ghost_group(g), "weight": g.weight, "sigma_px": g.sigma_m / pitch,
                       "magnification": g.magnification, "extra_path_m": g.extra_path_m,
                       "focus_shift_m": g.focus_shift_m} for g in ghosts]}
    (out / "results.json").write_text(json.dumps(res, indent=2))
    print(lens_info)
    print(f"{'case':34s} {'W':>7s} {'square':>8s} {'wall':>8s} {'card':>8s}  (mean distance error, mm)")
    for r in rows:
        print(f"{r['case']:34s} {r['weight']:7.4f} {r['square']:8.2f} {r['wall']:8.3f} {r['card']:8.3f}")
    for r in sweep:
        print(f"{r['parameter'] + ' = ' + str(r['value']):34s} {r['weight']:7.4f} {r['square']:8.2f} "
              f"{r['wall']:8.3f} {r['card']:8.3f}")
    print("strongest ghosts: " + ", ".join(f"{g.name} {g.weight:.1e}" for g in ghosts[:5]))
    print(f"render {t_render:.1f} s, all {t_all:.1f} s; report {out / 'report.html'}")


if __name__ == "__main__":
    main()
