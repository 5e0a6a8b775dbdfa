"""``tofhil compare``: A against B, before and after corrections; a layout over :mod:`metrics`.

A is the measurement (a bench or emulated session), B the reference (the twin's render or
a ground truth) taken with the same camera model. Each variant of A -- as measured, and
after each requested correction -- is reduced to the temporal mean of its frames and
evaluated against B's mean by :func:`tofhil.eval.metrics.evaluate` (residual maps,
regions, cloud and NDT metrics); the page is drawn by :mod:`tofhil.eval.html`.
``metrics.json`` holds every number; ``report.html`` is one self-contained file.

Pixels with a clipped (saturated) or non-finite tap in any averaged frame are invalid, and
each region reports how many it lost that way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from tofhil import __version__
from tofhil.demod import TapLimits
from tofhil.errors import TofhilError
from tofhil.eval import html as H
from tofhil.eval import metrics as M
from tofhil.eval.corrections import correct_depth, correct_raw, get_method, load_params, parse_method_spec, resolve_params
from tofhil.frames import DepthFrame

MEASURED = "measured"
OUTPUTS = ("metrics.json", "report.html")


@dataclass
class Variant:
    """One version of A: its label, mean depth frame, per-pixel temporal std and evaluation."""

    label: str
    frame: DepthFrame
    temporal_std_m: np.ndarray
    method: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    evaluation: M.Evaluation | None = None


# ---------------------------------------------------------------------------- loading


def session_depth_frames(session: Any, n: int, method: str | None = None,
                         params: dict[str, Any] | None = None, min_amplitude: float = 0.0) -> list[DepthFrame]:
    """Depth frames of the first ``n`` frames, optionally corrected.

    Raw sessions are demodulated here (the same pipeline before and after correction);
    depth-only sessions use their stored depth.
    """
    from tofhil.depth import depth_from_raw

    frames = []
    for i in range(min(n, session.n_frames)):
        if session.has_raw:
            raw = session.raw_frame(i)
            if method is None:
                frames.append(depth_from_raw(raw, min_amplitude=min_amplitude))
            else:
                frames.append(correct_raw(raw, method, params, min_amplitude=min_amplitude)[1])
        else:
            d = session.depth_frame(i)
            frames.append(d if method is None else correct_depth(d, method, params))
    return frames


def tap_health(session: Any, n: int) -> M.TapHealth:
    """Clipped and non-finite taps over the first ``n`` frames (none for depth-only sessions)."""
    if not session.has_raw:
        return M.TapHealth.none(session.camera.shape)
    declared = TapLimits.from_meta(session.raw_frame(0).meta) if session.n_frames else None
    return M.TapHealth.from_taps((session.raw_frame(i).taps for i in range(min(n, session.n_frames))), declared=declared)


def object_id_map(session: Any) -> tuple[np.ndarray | None, dict[int, str]]:
    """The twin's object-id map of a session, and the object names.

    From a ``depth/object_id`` dataset when the session has one, else by re-rendering the
    scene embedded in the session (ids are indices into the scene's objects). ``None``
    when neither is available.
    """
    f = session._file  # noqa: SLF001 -- optional dataset outside the core reader's API
    names: dict[int, str] = {}
    scene = None
    if session.scene_text:
        try:
            from tofhil.sim.scene import scene_from_yaml

            scene = scene_from_yaml(session.scene_text, source=f"{session.path}:scene")
            names = {i: o.name for i, o in enumerate(scene.objects)}
        except Exception:  # a scene written by another tool version: regions by ROI only
            scene = None
    if "depth/object_id" in f:
        ids = np.asarray(f["depth/object_id"][0 if f["depth/object_id"].ndim == 3 else ()])
        return ids.astype(np.int64), names
    if scene is None:
        return None, names
    try:
        from tofhil.sim.render import render

        r = render(scene, camera=session.camera, samples_per_pixel=1, bounces=0)
    except Exception:
        return None, names
    return np.asarray(r.object_id, dtype=np.int64), names


def _mask_shadows(frame: DepthFrame, min_relative_amplitude: float, regions: list[np.ndarray]) -> None:
    """Invalidate unlit pixels (:func:`tofhil.eval.metrics.lit_pixels`, relative to each
    object's own amplitude)."""
    lit = M.lit_pixels(frame.amplitude, min_relative_amplitude, regions)
    if lit is not None:
        frame.valid = frame.valid & lit


# ---------------------------------------------------------------------------- report


def _masked(frame: DepthFrame, img: np.ndarray | None, valid: np.ndarray | None = None) -> np.ndarray:
    if img is None:
        return np.full(frame.camera.shape, np.nan)
    return np.where(frame.valid if valid is None else valid, np.asarray(img, float), np.nan)


def figures(variants: list[Variant], ref: DepthFrame, section: H.CrossSection,
            cell_size: float) -> list[tuple[str, str | None, str]]:
    """The compare page's figures, each drawn by :mod:`tofhil.eval.html`."""
    ev = [(v.label, v.evaluation) for v in variants]
    ref_valid = ev[0][1].maps.valid_b
    dist = [("reference (B)", _masked(ref, ref.radial_m, ref_valid))] + \
           [(f"{v.label} (A)", _masked(v.frame, v.frame.radial_m, e.maps.valid_a)) for v, (_, e) in zip(variants, ev)]
    amp = [("reference (B)", _masked(ref, ref.amplitude, ref_valid))] + \
          [(f"{v.label} (A)", _masked(v.frame, v.frame.amplitude, e.maps.valid_a)) for v, (_, e) in zip(variants, ev)]
    res = [(label, e.maps.depth_residual_m) for label, e in ev]
    out = [
        ("Depth maps", H.figure_distance_maps(dist),
         "Radial distance of the reference B and of A before and after each correction (shared 1-99 % scale; "
         "invalid and saturated pixels blank)."),
        ("Amplitude maps", H.figure_amplitude_maps(amp), "Amplitude |S| (mean over frequencies); each panel on its "
                                                         "own scale."),
        ("Residual maps", H.figure_residual_maps([(f"residual A - B: {t}", r) for t, r in res]),
         "Depth residual A - B in millimetres (red: A farther, blue: A nearer); shared symmetric scale "
         f"+-max(|p{H.RESIDUAL_PERCENTILES[0]:g}|, |p{H.RESIDUAL_PERCENTILES[1]:g}|) of the residuals, "
         "values beyond it in the end colours."),
        ("Amplitude ratio maps", H.figure_ratio_maps([(label, e.maps.amplitude_ratio) for label, e in ev]),
         "Amplitude of A over amplitude of B per pixel, log2 (0: equal; +1: A twice as bright). "
         "A device's and the twin's amplitude units differ by a constant: look at the pattern."),
        ("Cross-section", H.figure_cross_section(section, ("reference (B)", dist[0][1]),
                                                 [(t, d) for t, d in dist[1:]], res),
         f"Radial distance and residual A - B along {section.describe()} (choose with --row or --column); "
         "the residual axis spans the line's 1-99 % range, values beyond it are drawn at its edge."),
        ("Residual histograms", H.figure_histogram(res),
         "Distribution of the depth residual over all pixels valid in A and B (log scale)."),
    ]
    ndt = [(label, e.ndt_map) for label, e in ev if e.ndt_map is not None]
    if ndt:
        out.append(("NDT likelihood maps", H.figure_likelihood_maps(ndt),
                    f"Trilinear NDT likelihood of each pixel's point of A on B's NDT grid "
                    f"(cell {cell_size:g} m): 1 = on the reference surface, 0 = far from it."))
    return out


def write_report(out: Path, metrics: dict[str, Any], variants: list[Variant],
                 figs: list[tuple[str, str | None, str]]) -> None:
    a, b = metrics["inputs"]["a"], metrics["inputs"]["b"]
    s = metrics["settings"]
    notes = sorted({n for v in variants for n in v.evaluation.validity_notes()})
    body = [f"<p class='note'>A (measured): {H.esc(a)}<br>B (reference): {H.esc(b)}<br>frames averaged: "
            f"A {metrics['frames']['a']}, B {metrics['frames']['b']} &middot; residual = A - B (radial distance"
            f"{', wrapped to the ' + format(s['wrap_m'], '.4g') + ' m unambiguous range' if s['wrap_m'] else ''}) "
            f"&middot; {H.esc(metrics['software'])}</p>",
            "<h2>Summary</h2>", H.notes_html(notes),
            H.region_table([(v.label, r) for v in variants for r in v.evaluation.regions.values()]),
            f"<p class='note'>{H.esc(M.DEPTH_RMSE)}: sqrt(mean((A - B)^2)) over the region's pixels valid in A "
            "and in B (not saturated, finite, lit). compared: that fraction of the region; saturated A: fraction "
            "of the region with a clipped tap in A. MAD: median absolute deviation from the median (raw, not "
            f"scaled). Cloud metrics: A's points against B's (threshold {s['threshold_m'] * 1000:g} mm); NDT: A's "
            f"points scored on B's NDT grid (cell {s['cell_size_m']:g} m). Full numbers in metrics.json.</p>",
            H.figures_html(figs)]
    H.write_page(out / "report.html", "tofhil compare", body)


# ---------------------------------------------------------------------------- orchestration


def acquisition_mismatches(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """Camera settings in which two sessions differ (a capture compared with a twin rendered
    at other settings compares different measurements)."""
    out = []
    for key in ("freq_hz", "theta_deg", "integration_time_s"):
        if key not in a or key not in b:
            continue
        va, vb = np.ravel(a[key]), np.ravel(b[key])
        if va.size != vb.size or not np.allclose(va, vb, rtol=1e-9):
            out.append(f"{key} differs: A {a[key]}, B {b[key]}")
    sa, sb = a.get("sensor_config") or {}, b.get("sensor_config") or {}
    for key in sorted(set(sa) & set(sb) - {"freq_hz", "theta_deg", "taps", "integration_time_s"}):
        if sa[key] != sb[key]:
            out.append(f"sensor {key} differs: A {sa[key]}, B {sb[key]}")
    return out


def compare_sessions(a_path: str | Path, b_path: str | Path, out_dir: str | Path, *,
                     corrections: Sequence[str] = (), rois: Sequence[str] = (), masks: Sequence[str | Path] = (),
                     row: int | None = None, column: int | None = None, max_frames: int = 10,
                     cell_size: float = 0.1, threshold: float = 0.01, min_amplitude: float = 0.0,
                     min_relative_amplitude: float = M.MIN_RELATIVE_AMPLITUDE, objects: bool = True, force: bool = False,
                     log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Compare session A with reference B, write ``metrics.json`` and ``report.html``.

    ``corrections`` are method specs (``"psf:psf=cal.npz"``, ``"uniform:w=2e-5"``), each
    applied to A; ``rois`` are ``"X0,Y0,X1,Y1"`` pixel boxes (half-open); ``masks`` mask
    files (.png, .npy); ``row`` / ``column`` the cross-section. Returns the metrics.
    """
    from tofhil.session import open_session

    say = log or (lambda s: None)
    for name, v, lo in (("--threshold", threshold, 0.0), ("--cell-size", cell_size, 0.0)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > lo):
            raise TofhilError(f"is {v}", field=name, expected="a positive distance in metres")
    if not (math.isfinite(min_relative_amplitude) and 0 <= min_relative_amplitude < 1):
        raise TofhilError(f"is {min_relative_amplitude}", field="--min-relative-amplitude",
                          expected="a fraction in [0, 1)")
    if not (math.isfinite(min_amplitude) and min_amplitude >= 0):
        raise TofhilError(f"is {min_amplitude}", field="--min-amplitude", expected="an amplitude >= 0")
    if max_frames < 1:
        raise TofhilError(f"is {max_frames}", field="--frames", expected="an integer >= 1")
    out = H.prepare_output_dir(out_dir, OUTPUTS, force=force)
    specs = [parse_method_spec(c) for c in corrections]
    labels = list(corrections)
    if len(set(labels)) != len(labels):
        raise TofhilError("the same correction is given twice", field="--correct")
    with open_session(a_path) as sa, open_session(b_path) as sb:
        for (name, params), label in zip(specs, labels):
            m = get_method(name)
            resolve_params(m, params)
            if m.domain == "complex" and not sa.has_raw:
                raise TofhilError(f"correction {label!r} works on the complex signal and needs raw taps; "
                                  "A has depth only", file=a_path, field="raw/taps",
                                  expected="a raw session, or depth methods only")
        shape = sb.camera.shape
        section = H.CrossSection.choose(shape, row, column)
        regions: list[M.Region] = [M.parse_roi(r, shape) for r in rois] + [M.load_mask(p, shape) for p in masks]
        n_a, n_b = min(max_frames, sa.n_frames), min(max_frames, sb.n_frames)
        say(f"reference: averaging {n_b} frames of {b_path}")
        ref, ref_std = M.mean_depth_frame(session_depth_frames(sb, max_frames, min_amplitude=min_amplitude))
        health_b = tap_health(sb, max_frames)
        say(f"measured: averaging {n_a} frames of {a_path}")
        health_a = tap_health(sa, max_frames)
        fa, std = M.mean_depth_frame(session_depth_frames(sa, max_frames, min_amplitude=min_amplitude))
        variants = [Variant(MEASURED, fa, std)]
        for (name, params), label in zip(specs, labels):
            p = load_params(name, params)
            say(f"correcting A with {label}")
            f, s = M.mean_depth_frame(session_depth_frames(sa, max_frames, name, p, min_amplitude))
            variants.append(Variant(label, f, s, name, dict(params)))
        obj_source = None
        if objects:
            for sess, tag in ((sb, "B"), (sa, "A")):
                ids, names = object_id_map(sess)
                if ids is not None and ids.shape == shape:
                    regions = M.object_regions(ids, names, min_pixels=20) + regions
                    obj_source = tag
                    break
        # Validity relative to each object's own amplitude: a 1 % square is dark, not a shadow.
        own = [r.mask for r in regions if r.kind == "object"]
        for f in [ref] + [v.frame for v in variants]:
            _mask_shadows(f, min_relative_amplitude, own)
        freqs = getattr(sa, "freq_hz", None) if sa.has_raw else None
        wrap_m = M.wrap_period(freqs) if freqs is not None else None
        a_label = str(sa.device.get("model") or sa.device.get("name") or Path(a_path).name)
        b_label = str(sb.device.get("model") or sb.device.get("name") or Path(b_path).name)
        acquisition = {"a": sa.acquisition(), "b": sb.acquisition()}
        mismatches = acquisition_mismatches(acquisition["a"], acquisition["b"])
        for w in mismatches:
            say(f"warning: {w}")

    metrics: dict[str, Any] = {
        "software": f"tofhil {__version__}",
        "inputs": {"a": str(a_path), "b": str(b_path), "a_device": a_label, "b_device": b_label},
        "frames": {"a": n_a, "b": n_b},
        # The camera settings of each side (a twin session records its full sensor configuration).
        "acquisition": acquisition,
        "acquisition_mismatches": mismatches,
        "settings": {"cell_size_m": cell_size, "threshold_m": threshold, "min_amplitude": min_amplitude,
                     "min_relative_amplitude": min_relative_amplitude, "wrap_m": wrap_m,
                     "object_regions_from": obj_source, "rois": list(rois), "masks": [str(p) for p in masks],
                     "cross_section": {"axis": section.axis, "index": section.index},
                     "roi_convention": "X0,Y0,X1,Y1 half-open (X1, Y1 exclusive)"},
        "depth_rmse_definition": M.DEPTH_RMSE,
        "reference_temporal_std_m_median": float(np.nanmedian(ref_std)) if np.isfinite(ref_std).any() else None,
        "variants": {},
    }
    for f, h, path in ((ref, health_b, b_path), (fa, health_a, a_path)):
        if not M.frame_validity(f, h).any():
            raise TofhilError(f"has no valid pixel in the {min(max_frames, n_a if path == a_path else n_b)} frame(s) "
                              "compared (NaN, saturated, unlit or flagged invalid everywhere)", file=path,
                              field="depth/valid", expected="a capture with valid pixels in common with the other")
    for v in variants:
        say(f"metrics: {v.label}")
        v.evaluation = M.evaluate(v.frame, ref, regions, wrap_m=wrap_m, health_a=health_a, health_b=health_b,
                                  cloud_regions=True, cell_size=cell_size, threshold=threshold,
                                  source=f"{a_path} vs {b_path}")
        res = v.evaluation.to_json()
        res["temporal_std_m_median"] = (float(np.nanmedian(v.temporal_std_m))
                                        if np.isfinite(v.temporal_std_m).any() else None)
        res["method"] = v.method
        res["params"] = v.params
        res["notes"] = v.evaluation.validity_notes()
        metrics["variants"][v.label] = res

    say("figures")
    figs = figures(variants, ref, section, cell_size)
    out.mkdir(parents=True, exist_ok=True)
    H.write_json(out / "metrics.json", metrics)
    write_report(out, metrics, variants, figs)
    return M.json_safe(metrics)
