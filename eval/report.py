"""``tofhil compare``: metrics of A against B, before and after corrections, and an HTML report.

A is the measurement (a bench or emulated session), B the reference (the twin's render or
a ground truth) taken with the same camera model. Each variant of A -- as measured, and
after each requested correction -- is reduced to the temporal mean of its frames and
compared pixel by pixel with B's mean (:mod:`tofhil.eval.compare`), as point clouds
(:func:`tofhil.eval.matching.cloud_metrics`) and by NDT scores against B's cloud
(:func:`tofhil.eval.ndt.ndt_score`). ``metrics.json`` holds every number; ``report.html``
is one self-contained file (PNG figures inlined as base64 data URIs, no network).
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from tofhil import __version__
from tofhil.errors import TofhilError
from tofhil.eval import compare as cmp
from tofhil.eval.corrections import correct_depth, correct_raw, get_method, load_params, parse_method_spec, resolve_params
from tofhil.frames import DepthFrame

MEASURED = "measured"


@dataclass
class Variant:
    """One version of A: its label, mean depth frame and per-pixel temporal std."""

    label: str
    frame: DepthFrame
    temporal_std_m: np.ndarray
    method: str | None = None
    params: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------------------- data


def _session_depth_frames(session: Any, n: int, method: str | None = None,
                          params: dict[str, Any] | None = None, min_amplitude: float = 0.0) -> list[DepthFrame]:
    """Depth frames of the first ``n`` frames, optionally corrected.

    Raw sessions are demodulated here (the same pipeline before and after correction);
    depth-only sessions use their stored depth.
    """
    frames = []
    for i in range(min(n, session.n_frames)):
        if session.has_raw:
            raw = session.raw_frame(i)
            if method is None:
                from tofhil.depth import depth_from_raw

                frames.append(depth_from_raw(raw, min_amplitude=min_amplitude))
            else:
                frames.append(correct_raw(raw, method, params, min_amplitude=min_amplitude)[1])
        else:
            d = session.depth_frame(i)
            frames.append(d if method is None else correct_depth(d, method, params))
    return frames


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


def _points_map(frame: DepthFrame) -> tuple[np.ndarray, np.ndarray]:
    mask = frame.camera.valid_mask(frame.distance_m, frame.valid)
    return frame.points(), mask


def cloud_and_ndt(a: DepthFrame, b: DepthFrame, region: np.ndarray, *, cell_size: float,
                  threshold: float) -> tuple[dict[str, Any], np.ndarray | None]:
    """Point-cloud metrics and NDT scores of A's points against B's, within a region.

    Returns the metrics and (for the caller's maps) the per-pixel trilinear NDT
    likelihood of A's points (NaN where A has no point).
    """
    from tofhil.eval.matching import cloud_metrics
    from tofhil.eval.ndt import ndt_score

    ma = a.camera.valid_mask(a.distance_m, a.valid) & region
    mb = b.camera.valid_mask(b.distance_m, b.valid) & region
    pa = a.camera.points(a.distance_m, a.kind, ma)
    pb = b.camera.points(b.distance_m, b.kind, mb)
    if len(pa) < 10 or len(pb) < 10:
        return {"skipped": f"too few points (A {len(pa)}, B {len(pb)})"}, None
    out: dict[str, Any] = {"cloud": cloud_metrics(pa, pb, threshold=threshold)}
    score = ndt_score(pb, pa, cell_size=cell_size)
    out["ndt"] = score.to_dict()
    lmap = np.full(a.camera.shape, np.nan)
    lmap[ma] = score.likelihood_trilinear
    return out, lmap


# ---------------------------------------------------------------------------- figures


def _fig_uri(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _grid(n: int, width: float = 4.2, height: float = 3.4) -> tuple[Any, np.ndarray]:
    import matplotlib.pyplot as plt

    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols, height * rows), squeeze=False,
                             layout="constrained")
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    return fig, axes.ravel()


def _image_panel(fig: Any, ax: Any, img: np.ndarray, title: str, cmap: str, vmin: float, vmax: float,
                 unit: str) -> None:
    im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_title("\n".join(textwrap.wrap(title, 38)), fontsize=9)
    ax.set_xlabel("pixel column", fontsize=8)
    ax.set_ylabel("pixel row", fontsize=8)
    ax.tick_params(labelsize=7)
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    cb.set_label(unit, fontsize=8)
    cb.ax.tick_params(labelsize=7)


def _robust_range(images: Sequence[np.ndarray], lo: float = 1, hi: float = 99) -> tuple[float, float]:
    vals = np.concatenate([np.asarray(i, float)[np.isfinite(i)] for i in images] or [np.zeros(1)])
    if vals.size == 0:
        return 0.0, 1.0
    a, b = np.percentile(vals, [lo, hi])
    return (float(a), float(b)) if b > a else (float(a) - 0.5, float(a) + 0.5)


def _masked(frame: DepthFrame, img: np.ndarray | None) -> np.ndarray:
    if img is None:
        return np.full(frame.camera.shape, np.nan)
    return np.where(frame.valid, np.asarray(img, float), np.nan)


def figure_depth_maps(variants: list[Variant], ref: DepthFrame, ref_label: str) -> str:
    imgs = [(f"{ref_label} (B)", _masked(ref, ref.radial_m))] + \
           [(f"{v.label} (A)", _masked(v.frame, v.frame.radial_m)) for v in variants]
    lo, hi = _robust_range([i for _, i in imgs])
    fig, axes = _grid(len(imgs))
    for ax, (t, img) in zip(axes, imgs):
        _image_panel(fig, ax, img, f"radial distance: {t}", "viridis", lo, hi, "m")
    return _fig_uri(fig)


def figure_amplitude_maps(variants: list[Variant], ref: DepthFrame, ref_label: str) -> str:
    imgs = [(f"{ref_label} (B)", _masked(ref, ref.amplitude))] + \
           [(f"{v.label} (A)", _masked(v.frame, v.frame.amplitude)) for v in variants]
    fig, axes = _grid(len(imgs))
    for ax, (t, img) in zip(axes, imgs):
        # Each its own scale: A and B amplitudes are in different units (device counts vs model).
        lo, hi = _robust_range([img], 0.5, 99.5)
        _image_panel(fig, ax, img, f"amplitude: {t}", "gray", lo, hi, "a.u.")
    return _fig_uri(fig)


def figure_residual_maps(variants: list[Variant], ref: DepthFrame) -> str:
    res = [(v.label, cmp.residual_maps(v.frame, ref)["depth_residual_m"]) for v in variants]
    _, hi = _robust_range([np.abs(r) for _, r in res], 0, 98)
    hi = max(hi, 1e-4)
    fig, axes = _grid(len(res))
    for ax, (t, r) in zip(axes, res):
        _image_panel(fig, ax, r * 1000, f"residual A - B: {t}", "RdBu_r", -hi * 1000, hi * 1000, "mm")
    return _fig_uri(fig)


def figure_amplitude_ratio_maps(variants: list[Variant], ref: DepthFrame) -> str | None:
    """Per-pixel amplitude ratio A/B (log2 scale: 0 = equal); None without amplitudes."""
    maps = []
    for v in variants:
        r = cmp.residual_maps(v.frame, ref)
        maps.append((v.label, np.where(r["valid_both"], r["amplitude_ratio"], np.nan)))
    if not any(np.isfinite(m).any() for _, m in maps):
        return None
    logs = [(t, np.where(m > 0, np.log2(np.where(m > 0, m, 1.0)), np.nan)) for t, m in maps]
    _, hi = _robust_range([np.abs(m) for _, m in logs], 0, 98)
    hi = max(hi, 0.05)
    fig, axes = _grid(len(logs))
    for ax, (t, m) in zip(axes, logs):
        _image_panel(fig, ax, m, f"amplitude ratio A/B: {t}", "PuOr_r", -hi, hi, "log2(A/B)")
    return _fig_uri(fig)


def figure_row_profile(variants: list[Variant], ref: DepthFrame, ref_label: str, column: int) -> str:
    """Distance against pixel row through the image centre (the thesis's 2-D plots)."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    rows = np.arange(ref.camera.height)
    ax.plot(rows, _masked(ref, ref.radial_m)[:, column], "k-", lw=2, label=f"{ref_label} (B)")
    for v in variants:
        ax.plot(rows, _masked(v.frame, v.frame.radial_m)[:, column], lw=1.2, label=v.label)
    ax.set_xlabel("pixel row")
    ax.set_ylabel("radial distance (m)")
    ax.set_title(f"distance along pixel column {column} (through the image centre)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _fig_uri(fig)


def figure_ndt_maps(maps: list[tuple[str, np.ndarray]]) -> str:
    fig, axes = _grid(len(maps))
    for ax, (t, m) in zip(axes, maps):
        _image_panel(fig, ax, m, f"NDT likelihood: {t}", "magma", 0.0, 1.0, "trilinear likelihood")
    return _fig_uri(fig)


def figure_histograms(variants: list[Variant], ref: DepthFrame) -> str:
    import matplotlib.pyplot as plt

    res = [(v.label, cmp.residual_maps(v.frame, ref)["depth_residual_m"]) for v in variants]
    vals = [r[np.isfinite(r)] * 1000 for _, r in res]
    lo, hi = _robust_range([v for v in vals if v.size], 0.5, 99.5)
    fig, ax = plt.subplots(figsize=(8, 4))
    bins = np.linspace(lo, hi, 81)
    for (label, _), v in zip(res, vals):
        if v.size:
            ax.hist(np.clip(v, lo, hi), bins=bins, histtype="step", lw=1.5, label=f"{label} (n={v.size})")
    ax.set_xlabel("depth residual A - B (mm), clipped to the 0.5-99.5 % range")
    ax.set_ylabel("pixels")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _fig_uri(fig)


# ---------------------------------------------------------------------------- HTML


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        if not math.isfinite(x):
            return "–"
        return f"{x:.4g}"
    return html.escape(str(x))


def _summary_table(metrics: dict[str, Any]) -> str:
    head = ("<tr><th>variant</th><th>region</th><th>pixels</th><th>valid A</th><th>median (mm)</th>"
            "<th>MAD (mm)</th><th>RMSE (mm)</th><th>p95 |r| (mm)</th><th>amp. ratio</th>"
            "<th>chamfer (mm)</th><th>F-score</th><th>NDT mean lik.</th><th>NVTL</th></tr>")
    rows = []
    for vname, v in metrics["variants"].items():
        for rname, r in v["regions"].items():
            d = r["depth_residual_m"]
            c = r.get("cloud", {}).get("cloud", {})
            n = r.get("cloud", {}).get("ndt", {})
            cells = [vname, rname, r["pixels"], r["valid_fraction_a"], d["median"] * 1000, d["mad"] * 1000,
                     d["rmse"] * 1000, d["p95_abs"] * 1000, r["amplitude_ratio_median"],
                     c.get("chamfer", float("nan")) * 1000, c.get("fscore", float("nan")),
                     n.get("mean_likelihood_trilinear", float("nan")), n.get("nvtl", float("nan"))]
            rows.append("<tr>" + "".join(f"<td>{_fmt(x)}</td>" for x in cells) + "</tr>")
    return f"<table>{head}{''.join(rows)}</table>"


CSS = """body{font-family:sans-serif;max-width:1400px;margin:1em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}
th{background:#eee}td:first-child,td:nth-child(2){text-align:left}img{max-width:100%}
h2{border-bottom:1px solid #ccc;margin-top:1.6em}.note{color:#555;font-size:13px}"""


def write_html(path: Path, metrics: dict[str, Any], figures: list[tuple[str, str, str]]) -> None:
    """One self-contained page: summary table, then each figure (title, data URI, caption)."""
    a, b = metrics["inputs"]["a"], metrics["inputs"]["b"]
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>tofhil compare</title>"
             f"<style>{CSS}</style></head><body>",
             f"<h1>tofhil compare</h1><p class='note'>A (measured): {html.escape(a)}<br>"
             f"B (reference): {html.escape(b)}<br>frames averaged: A {metrics['frames']['a']}, "
             f"B {metrics['frames']['b']} &middot; residual = A - B (radial distance) &middot; "
             f"{html.escape(metrics['software'])}</p>",
             "<h2>Summary</h2>", _summary_table(metrics),
             "<p class='note'>MAD: median absolute deviation from the median (raw, not scaled). "
             "Cloud metrics: A's points against B's (threshold "
             f"{metrics['settings']['threshold_m'] * 1000:g} mm); NDT: A's points scored on B's NDT grid "
             f"(cell {metrics['settings']['cell_size_m']:g} m). Full numbers in metrics.json.</p>"]
    for title, uri, caption in figures:
        parts.append(f"<h2>{html.escape(title)}</h2><p class='note'>{html.escape(caption)}</p>"
                     f"<img alt='{html.escape(title)}' src='{uri}'>")
    parts.append("</body></html>")
    path.write_text("\n".join(parts), encoding="utf-8")


# ---------------------------------------------------------------------------- orchestration


def _json_safe(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


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
                     corrections: Sequence[str] = (), rois: Sequence[str] = (), max_frames: int = 10,
                     cell_size: float = 0.1, threshold: float = 0.01, min_amplitude: float = 0.0,
                     min_relative_amplitude: float = 1e-3, objects: bool = True, force: bool = False,
                     log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Compare session A with reference B, write ``metrics.json`` and ``report.html``.

    ``corrections`` are method specs (``"psf:psf=cal.npz"``, ``"uniform:w=2e-5"``), each
    applied to A; ``rois`` are ``"x0,y0,x1,y1"`` pixel boxes. Pixels whose mean amplitude
    is below ``min_relative_amplitude`` of the frame's 99th percentile are invalid (no
    light reaches them -- a shadow -- so their phase means nothing). Returns the metrics.
    """
    import matplotlib

    matplotlib.use("Agg")
    from tofhil.session import open_session

    say = log or (lambda s: None)
    out = Path(out_dir)
    for name in ("metrics.json", "report.html"):
        if (out / name).exists() and not force:
            raise TofhilError("already exists; refusing to overwrite (use --force)", file=out / name)
    specs = [parse_method_spec(c) for c in corrections]
    labels = [c for c in corrections]
    if len(set(labels)) != len(labels):
        raise TofhilError("the same correction is given twice", field="--correct")
    with open_session(a_path) as sa, open_session(b_path) as sb:
        for (name, params), label in zip(specs, labels):
            m = get_method(name)
            p = resolve_params(m, params)
            if m.domain == "complex" and not sa.has_raw:
                raise TofhilError(f"correction {label!r} works on the complex signal and needs raw taps; "
                                  "A has depth only", file=a_path, field="raw/taps",
                                  expected="a raw session, or depth methods only")
        say(f"reference: averaging {min(max_frames, sb.n_frames)} frames of {b_path}")
        ref, ref_std = cmp.mean_depth_frame(_session_depth_frames(sb, max_frames, min_amplitude=min_amplitude))
        variants = []
        say(f"measured: averaging {min(max_frames, sa.n_frames)} frames of {a_path}")
        fa, std = cmp.mean_depth_frame(_session_depth_frames(sa, max_frames, min_amplitude=min_amplitude))
        variants.append(Variant(MEASURED, fa, std))
        for (name, params), label in zip(specs, labels):
            p = load_params(name, params)
            say(f"correcting A with {label}")
            f, s = cmp.mean_depth_frame(_session_depth_frames(sa, max_frames, name, p, min_amplitude))
            variants.append(Variant(label, f, s, name, {k: v for k, v in params.items()}))
        for f in [ref] + [v.frame for v in variants]:
            if f.amplitude is not None and np.isfinite(f.amplitude).any() and min_relative_amplitude > 0:
                top = np.nanpercentile(f.amplitude, 99)
                f.valid = f.valid & (np.nan_to_num(f.amplitude) >= min_relative_amplitude * top)
        regions: list[cmp.Region] = []
        obj_source = None
        if objects:
            for sess, tag in ((sb, "B"), (sa, "A")):
                ids, names = object_id_map(sess)
                if ids is not None and ids.shape == ref.camera.shape:
                    regions += cmp.object_regions(ids, names, min_pixels=20)
                    obj_source = tag
                    break
        regions += [cmp.parse_roi(r, ref.camera.shape) for r in rois]
        n_a, n_b = min(max_frames, sa.n_frames), min(max_frames, sb.n_frames)
        a_label = str(sa.device.get("model") or sa.device.get("name") or Path(a_path).name)
        b_label = str(sb.device.get("model") or sb.device.get("name") or Path(b_path).name)
        acquisition = {"a": sa.acquisition(), "b": sb.acquisition()}
        for w in acquisition_mismatches(acquisition["a"], acquisition["b"]):
            say(f"warning: {w}")

    metrics: dict[str, Any] = {
        "software": f"tofhil {__version__}",
        "inputs": {"a": str(a_path), "b": str(b_path), "a_device": a_label, "b_device": b_label},
        "frames": {"a": n_a, "b": n_b},
        # The camera settings of each side (a twin session records its full sensor configuration).
        "acquisition": acquisition,
        "acquisition_mismatches": acquisition_mismatches(acquisition["a"], acquisition["b"]),
        "settings": {"cell_size_m": cell_size, "threshold_m": threshold, "min_amplitude": min_amplitude,
                     "min_relative_amplitude": min_relative_amplitude,
                     "object_regions_from": obj_source, "rois": list(rois)},
        "reference_temporal_std_m_median": float(np.nanmedian(ref_std)) if np.isfinite(ref_std).any() else None,
        "variants": {},
    }
    ndt_maps = []
    all_mask = np.ones(ref.camera.shape, dtype=bool)
    for v in variants:
        say(f"metrics: {v.label}")
        res = cmp.compare_frames(v.frame, ref, regions)
        for r in [cmp.Region("all", all_mask, "all")] + regions:
            cm, lmap = cloud_and_ndt(v.frame, ref, r.mask, cell_size=cell_size, threshold=threshold)
            res["regions"][r.name]["cloud"] = cm
            if r.name == "all" and lmap is not None:
                ndt_maps.append((v.label, lmap))
        res["temporal_std_m_median"] = float(np.nanmedian(v.temporal_std_m)) if np.isfinite(v.temporal_std_m).any() else None
        res["method"] = v.method
        res["params"] = v.params
        metrics["variants"][v.label] = res

    say("figures")
    col = int(round(ref.camera.cx))
    figures = [
        ("Depth maps", figure_depth_maps(variants, ref, "reference"),
         "Radial distance of the reference B and of A before and after each correction (shared colour scale)."),
        ("Amplitude maps", figure_amplitude_maps(variants, ref, "reference"),
         "Amplitude |S| (mean over frequencies); each panel on its own scale."),
        ("Residual maps", figure_residual_maps(variants, ref),
         "Depth residual A - B in millimetres (red: A farther, blue: A nearer); shared symmetric scale."),
        ("Amplitude ratio maps", figure_amplitude_ratio_maps(variants, ref),
         "Amplitude of A over amplitude of B per pixel, log2 (0: equal; +1: A twice as bright). "
         "A device's and the twin's amplitude units differ by a constant: look at the pattern."),
        ("Distance against pixel row", figure_row_profile(variants, ref, "reference", col),
         f"Radial distance along pixel column {col} through the image centre."),
        ("Residual histograms", figure_histograms(variants, ref),
         "Distribution of the depth residual over all pixels valid in A and B (log scale)."),
    ]
    figures = [f for f in figures if f[1] is not None]
    if ndt_maps:
        figures.append(("NDT likelihood maps", figure_ndt_maps(ndt_maps),
                        f"Trilinear NDT likelihood of each pixel's point of A on B's NDT grid "
                        f"(cell {cell_size:g} m): 1 = on the reference surface, 0 = far from it."))
    out.mkdir(parents=True, exist_ok=True)
    safe = _json_safe(metrics)
    (out / "metrics.json").write_text(json.dumps(safe, indent=2), encoding="utf-8")
    write_html(out / "report.html", metrics, figures)
    return safe
