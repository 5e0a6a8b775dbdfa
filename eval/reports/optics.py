"""The twin's lens in a report: the ghost PSFs of a lens prescription and its ghost table.

One place for the figure the optics benchmark (benchmarks/optics_ghosts.py), ``compare`` and
``diagnose`` show when the twin's camera has a prescription (``camera.lens``,
:class:`tofhil.sim.optics.LensCamera`); a pinhole/OpenCV camera has no section.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from tofhil.eval.reports import html as H


def surface_kind(name: str) -> str:
    """A prescription surface's group by its name: filter, cover glass, sensor or lens."""
    n = name.lower()
    return "filter" if "filter" in n else "cover glass" if "cover" in n else "sensor" if n == "sensor" else "lens"


def ghost_group(g: Any) -> str:
    """The group of a two-reflection ghost: sensor, filter, cover glass or lens (in that order)."""
    a, b = (surface_kind(x) for x in g.name.split("-", 1))
    for grp in ("sensor", "filter", "cover glass"):
        if grp in (a, b):
            return grp
    return "lens"


def has_lens(camera: Any) -> bool:
    from tofhil.sim.optics import LensCamera

    return isinstance(camera, LensCamera) and camera.lens is not None


def figure_ghost_psfs(camera: Any) -> str | None:
    """The prescription's ghosts (no veil) for a point source at the centre, at half field and
    near the corner: log10 of the light per pixel as a fraction of the source's. None without
    a prescription."""
    if not has_lens(camera):
        return None
    from tofhil.sim.optics import lens_model
    from tofhil.sim.straylight import StrayLightOperator

    full = lens_model(camera.lens).stray_light(float(camera.pixel_pitch_m))
    h, w = camera.shape
    op = StrayLightOperator(replace(full, veil=0.0), (h, w), (camera.cx, camera.cy))
    panels = []
    for label, (x, y) in (("source at the centre", (w // 2, h // 2)), ("source at half field", (w * 3 // 4, h // 2)),
                          ("source near the corner", (max(w - 12, 0), min(10, h - 1)))):
        src = np.zeros((h, w))
        src[y, x] = 1.0
        panels.append((f"ghost PSF, {label}", np.log10(np.maximum(op.scatter(src), 1e-9))))
    fig, axes = H.grid(len(panels))
    for ax, (title, img) in zip(axes, panels):
        H.image_panel(fig, ax, img, title, "magma", -9.0, -3.0, "log10 fraction of the source")
    return H.fig_uri(fig)


def lens_summary(camera: Any) -> str:
    """EFL, f-number, entrance pupil, field and relative illumination at the corner."""
    from tofhil.sim.optics import lens_model

    model = lens_model(camera.lens)
    corner = model.field_angle(float(camera.pixel_pitch_m) * math.hypot(camera.cx, camera.cy))
    return (f"EFL {model.efl_m * 1e3:.3f} mm, F/{model.f_number:.2f}, entrance pupil at "
            f"z = {model.entrance_pupil[0] * 1e3:.3f} mm, field to the corner {math.degrees(float(corner)):.1f} deg, "
            f"relative illumination at the corner {float(model.relative_illumination(corner)):.3f}")


def ghost_table_html(camera: Any) -> str:
    """The prescription's ghosts: group, weight, blur, magnification, extra path, focus shift."""
    from tofhil.sim.optics import lens_model

    pitch = float(camera.pixel_pitch_m)
    rows = ["<table><tr><th>ghost</th><th>group</th><th>weight</th><th>blur sigma (px)</th><th>magnification</th>"
            "<th>extra path (mm)</th><th>focus shift (mm)</th></tr>"]
    for g in lens_model(camera.lens).ghosts:
        rows.append(f"<tr><td>{H.esc(g.name)}</td><td>{ghost_group(g)}</td><td>{g.weight:.2e}</td>"
                    f"<td>{g.sigma_m / pitch:.1f}</td><td>{g.magnification:.3f}</td>"
                    f"<td>{g.extra_path_m * 1e3:.2f}</td><td>{g.focus_shift_m * 1e3:.3f}</td></tr>")
    rows.append("</table>")
    return "".join(rows)


def lens_section(camera: Any, *, whose: str = "the twin's camera") -> list[str]:
    """HTML fragments of a report's lens section (empty without a prescription)."""
    uri = figure_ghost_psfs(camera)
    if uri is None:
        return []
    return [f"<h2>Lens prescription of {H.esc(whose)}</h2><p class='note'>{H.esc(lens_summary(camera))}</p>",
            H.figures_html([("Ghost PSFs", uri, "The prescription's two-reflection ghosts (no housing veil) for a "
                             "point source at three positions: light per pixel as a fraction of the source's (log10).")]),
            ghost_table_html(camera)]


__all__ = ["figure_ghost_psfs", "ghost_group", "ghost_table_html", "has_lens", "lens_section", "lens_summary",
           "surface_kind"]
