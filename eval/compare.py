"""``tofhil compare``: A against B, before and after corrections; a layout over :mod:`metrics`.

A is the measurement (a bench or emulated session), B the reference (the twin's render or
a ground truth) taken with the same camera model. Each variant of A -- as measured, and
after each requested correction -- is reduced to the temporal mean of its frames and
evaluated against B's mean by :func:`tofhil.eval.metrics.core.evaluate` (residual maps,
regions, cloud and NDT metrics); the page is drawn by :mod:`tofhil.eval.reports.html`.
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
from tofhil.outputs import prepare_output_dir
from tofhil.demod import TapLimits
from tofhil.errors import TofhilError
from tofhil.eval.reports import html as H
from tofhil.eval.metrics import core as M
from tofhil.eval.metrics import before_after as BA
from tofhil.eval.reports.before_after import before_after_html
from tofhil.eval.corrections import (context_for_session, correct_depth, get_method, load_params, parse_method_spec,
                                     resolve_params)
from tofhil.frames import DepthFrame

MEASURED = "measured"
OUTPUTS = ("metrics.json", "report.html")


@dataclass
class Variant:
    """One version of A: its label, mean depth frame, per-pixel temporal std, the noise of
    the mean, and its evaluation."""

    label: str
    frame: DepthFrame
    temporal_std_m: np.ndarray  # per frame
    method: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    evaluation: M.Evaluation | None = None
    noise_m: np.ndarray | None = None  # standard deviation of the mean's distance
    correction: Any = None  # a complex correction's CorrectionContext (flags, notes)


# ---------------------------------------------------------------------------- loading


def variant_frame(session: Any, n: int, method: str | None = None, params: dict[str, Any] | None = None,
                  min_amplitude: float = 0.0, flat: Any = None, context: Any = None,
                  frames: Sequence[int] | None = None,
                  noise_frames: Sequence[int] = ()) -> tuple[DepthFrame, np.ndarray]:
    """The mean of the first ``n`` frames (or of the frames numbered ``frames``), optionally
    corrected, and the per-pixel standard deviation of its distance expected from the
    frames' scatter (joined by the scatter of ``noise_frames``, other frames of the session
    held out from this mean, :func:`tofhil.eval.corrections.averaging.mean_signal`).

    Raw sessions are averaged in the complex domain after the tap calibration ``flat``
    (:func:`tofhil.eval.corrections.averaging.mean_signal`), a complex correction is applied
    to the mean, and the mean is demodulated once (the same pipeline before and after
    correction); depth methods filter that depth. Depth-only sessions average their stored
    depth (:func:`tofhil.eval.metrics.core.mean_depth_frame`; noise = temporal std / sqrt(n)).
    ``context`` (a :class:`tofhil.eval.corrections.CorrectionContext` of the session's mean)
    receives a complex correction's flags and notes.
    """
    from tofhil.depth import depth_from_raw
    from tofhil.eval.corrections.averaging import mean_signal

    m = None if method is None else get_method(method)
    p = {} if m is None else resolve_params(m, params)
    p.pop("flat", None)  # the caller resolves the variant's tap calibration (both sides)
    idx = list(range(min(n, session.n_frames))) if frames is None else list(frames)
    k = len(idx)
    if not session.has_raw:
        frame, std = M.mean_depth_frame(session.depth_frame(i) for i in idx)
        if m is not None:
            frame = correct_depth(frame, method, p)
        return frame, std / np.sqrt(k) if k > 1 else np.full(std.shape, np.nan)
    correct = None
    if m is not None and m.domain == "complex":
        from tofhil.eval.corrections import context_for_session

        ctx = context if context is not None else context_for_session(session, k, idx)
        correct = lambda s: m.func(s, ctx, **p)  # noqa: E731
    others = list(noise_frames)
    ms = mean_signal(lambda i: session.raw_frame(idx[i]), k, flat=flat, correct=correct,
                     others=(lambda i: session.raw_frame(others[i]), len(others)) if others else None)
    frame = depth_from_raw(ms.raw(), min_amplitude=min_amplitude)
    if m is not None and m.domain == "depth":
        frame = m.func(frame, **p)
    return frame, np.where(frame.valid, ms.distance_noise_m(), np.nan)


def heldout_split(session: Any, n: int, methods: Sequence[str], flat: Any = None
                  ) -> tuple[Any, tuple[np.ndarray, np.ndarray | None] | None]:
    """Scored like the diagnosis (:mod:`tofhil.eval.metrics.split`): with a complex
    correction among ``methods`` -- one that may fit from the data (the twin's signal scale)
    or whose parameters may have been fitted on this session (a PSF or an extended twin
    diagnosed on it, a weight tuned on it; compare cannot tell) -- the first ``n`` frames
    are split: the even ones fit, every variant of A is the mean of the odd ones. Returns
    the split (None: no such correction, every frame scored) and the training frames' mean
    signal ``[F, H, W]`` after the tap calibration ``flat`` with their clipped pixels (None
    for one frame: in-sample)."""
    from tofhil.eval.corrections.averaging import mean_signal
    from tofhil.eval.corrections.context import saturated_pixels
    from tofhil.eval.metrics.split import frame_split

    if not session.has_raw or not any(get_method(m).domain == "complex" for m in methods):
        return None, None
    split = frame_split(n)
    if split.in_sample:
        return split, None
    ms = mean_signal(lambda i: session.raw_frame(split.fit[i]), len(split.fit), flat=flat, scatter=False)
    return split, (ms.s, saturated_pixels(session.raw_frame(i) for i in split.fit))


def recorded_tap_calibration(session: Any) -> str | None:
    """The tap calibration file a corrected session was made with (``tofhil correct`` with
    ``flat=``), as recorded in its device header; None for a session without one."""
    v = session.device.get("tap_calibration") if isinstance(session.device, dict) else None
    return str(v) if v else None


def _same_file(a: str | Path | None, b: str | Path | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return Path(a).expanduser().resolve() == Path(b).expanduser().resolve()


def tap_calibration_plan(sessions: dict[str, tuple[Any, Path]], want: str | Path | None,
                         origin: str) -> dict[str, Any]:
    """What to apply to each side (``{"A": (session, path), "B": ...}``) so that both end
    with the tap calibration ``want`` (a file, or None for none): None for a side that has
    it already (recorded in its header), else the loaded calibration. A side that cannot get
    it (depth only, another calibration already applied) is refused, naming its file;
    ``origin`` says where ``want`` came from."""
    from tofhil.eval.calibration.taps import TapCalibration

    out: dict[str, Any] = {}
    for side, (sess, path) in sessions.items():
        rec = recorded_tap_calibration(sess)
        if _same_file(rec, want):
            out[side] = None
            continue
        if rec is not None:
            raise TofhilError(f"{side} was corrected with the tap calibration {rec}, {origin} asks for "
                              f"{want if want is not None else 'none'}", file=path, field="device/tap_calibration",
                              expected="the same tap calibration on both sides (compare --flat T.npz)")
        if not sess.has_raw:
            raise TofhilError(f"{side} has depth only: the tap calibration {want} ({origin}) cannot be applied to it, "
                              "and comparing a tap-calibrated side with an uncalibrated one is wrong", file=path,
                              field="raw/taps", expected="raw taps on both sides, or no tap calibration")
        cal = TapCalibration.load(want)
        taps_shape = tuple(sess.raw_frame(0).taps.shape) if sess.n_frames else None
        if taps_shape is not None and taps_shape != cal.gain.shape:
            raise TofhilError(f"{side}'s taps are {taps_shape}, the tap calibration {want} is {cal.gain.shape}",
                              file=path, field="raw/taps",
                              expected="a tap calibration made with the same camera, frequencies and taps")
        out[side] = cal
    return out


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
    """Invalidate unlit pixels (:func:`tofhil.eval.metrics.core.lit_pixels`, relative to each
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
    """The compare page's figures, each drawn by :mod:`tofhil.eval.reports.html`."""
    ev = [(v.label, v.evaluation) for v in variants]
    ref_valid = ev[0][1].maps.valid_b
    dist = [("reference (B)", _masked(ref, ref.radial_m, ref_valid))] + \
           [(f"{v.label} (A)", _masked(v.frame, v.frame.radial_m, e.maps.valid_a)) for v, (_, e) in zip(variants, ev)]
    amp = [("reference (B)", _masked(ref, ref.amplitude, ref_valid))] + \
          [(f"{v.label} (A)", _masked(v.frame, v.frame.amplitude, e.maps.valid_a)) for v, (_, e) in zip(variants, ev)]
    res = [(label, e.maps.depth_residual_m) for label, e in ev]
    compared = [e.maps.compared for _, e in ev]
    out = [
        ("Depth maps", H.figure_distance_maps(dist),
         "Radial distance of the reference B and of A before and after each correction (shared 1-99 % scale; "
         "invalid and saturated pixels blank)."),
        ("Amplitude maps", H.figure_amplitude_maps(amp), "Amplitude |S| (mean over frequencies); each panel on its "
                                                         "own scale."),
        ("Residual maps", H.figure_residual_maps([(f"residual A - B: {t}", r) for t, r in res], scale_masks=compared),
         "Depth residual A - B in millimetres (red: A farther, blue: A nearer); shared symmetric scale "
         f"+-max(|p{H.RESIDUAL_PERCENTILES[0]:g}|, |p{H.RESIDUAL_PERCENTILES[1]:g}|) of the compared pixels' "
         "residuals (those in the depth figures), values beyond it in the end colours: pixels without a signal "
         "above noise on one side are drawn, and counted in the summary, but set neither the scale nor the figures."),
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


def twin_lens_camera(*sessions: Any) -> tuple[str, Any] | None:
    """``(side, camera)`` of the first twin session (A or B) whose scene's camera has a lens
    prescription: its report shows the ghost PSFs. None when no side has one (or its embedded
    scene no longer loads: the comparison does not depend on it)."""
    from tofhil.eval.reports.optics import has_lens
    from tofhil.sim.scene import scene_from_yaml

    for side, sess in zip("AB", sessions):
        text = getattr(sess, "scene_text", "")
        if sess.device.get("model") != "tofhil-sim" or "lens" not in text:
            continue
        try:
            cam = scene_from_yaml(text, source=f"{sess.path} (embedded scene)").camera
        except (TofhilError, ValueError, OSError):
            continue
        if has_lens(cam):
            return side, cam
    return None


def write_report(out: Path, metrics: dict[str, Any], variants: list[Variant],
                 figs: list[tuple[str, str | None, str]], lens: tuple[str, Any] | None = None) -> None:
    a, b = metrics["inputs"]["a"], metrics["inputs"]["b"]
    s = metrics["settings"]
    notes = sorted({n for v in variants for n in v.evaluation.validity_notes()})
    body = [f"<p class='note'>A (measured): {H.esc(a)}<br>B (reference): {H.esc(b)}<br>frames averaged: "
            f"A {metrics['frames']['a']}"
            f"{' (corrections ' + H.esc(metrics['heldout']['text']) + ')' if metrics.get('heldout') else ''}"
            f", B {metrics['frames']['b']} &middot; residual = A - B (radial distance"
            f"{', wrapped to the ' + format(s['wrap_m'], '.4g') + ' m unambiguous range' if s['wrap_m'] else ''}) "
            f"&middot; {H.esc(metrics['software'])}</p>",
            "<h2>Summary</h2>", H.notes_html(notes),
            H.region_table([(v.label, r) for v in variants for r in v.evaluation.regions.values()]),
            f"<p class='note'>{H.esc(M.DEPTH_RMSE)}: sqrt(mean((A - B)^2)) over the region's pixels valid in A "
            "and in B (not saturated, finite, lit). compared: that fraction of the region; saturated A: fraction "
            "of the region with a clipped tap in A. noise floor: the RMS over those pixels of the residual's noise "
            "expected from the averaged frames' scatter (raw sessions are averaged in the taps, before "
            "demodulation): the RMSE noise alone would give. MAD: median absolute deviation from the median (raw, not "
            f"scaled). Cloud metrics: A's points against B's (threshold {s['threshold_m'] * 1000:g} mm); NDT: A's "
            f"points scored on B's NDT grid (cell {s['cell_size_m']:g} m). Full numbers in metrics.json.</p>",
            before_after_html(metrics), H.figures_html(figs)]
    if lens is not None:
        from tofhil.eval.reports.optics import lens_section

        body.extend(lens_section(lens[1], whose=f"the twin's camera (side {lens[0]})"))
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
                     flat: str | Path | None = None, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Compare session A with reference B, write ``metrics.json`` and ``report.html``.

    ``corrections`` are method specs (``"psf:psf=cal.npz"``, ``"uniform:w=2e-5"``), each
    applied to A; ``rois`` are ``"X0,Y0,X1,Y1"`` pixel boxes (half-open); ``masks`` mask
    files (.png, .npy); ``row`` / ``column`` the cross-section; ``flat`` a tap calibration
    applied to both A and B (:func:`tap_calibration_plan`). Raw sessions are averaged in the
    complex domain (:func:`variant_frame`); every region reports its noise floor. Returns the
    metrics.
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
    out = prepare_output_dir(out_dir, OUTPUTS, force=force)
    specs = [parse_method_spec(c) for c in corrections]
    labels = list(corrections)
    if len(set(labels)) != len(labels):
        raise TofhilError("the same correction is given twice", field="--correct")
    with open_session(a_path, need_frames=True) as sa, open_session(b_path, need_frames=True) as sb:
        for (name, params), label in zip(specs, labels):
            m = get_method(name)
            resolve_params(m, params)
            if m.domain == "complex" and not sa.has_raw:
                raise TofhilError(f"correction {label!r} works on the complex signal and needs raw taps; "
                                  "A has depth only", file=a_path, field="raw/taps",
                                  expected="a raw session, or depth methods only")
        shape = sb.camera.shape
        if sa.camera.shape != shape:  # pixel against pixel: the same camera size, or nothing to compare
            raise TofhilError(f"is {sa.camera.width} x {sa.camera.height} pixels and {b_path} "
                              f"{sb.camera.width} x {sb.camera.height}", file=a_path, field="camera",
                              expected="two sessions of the same camera size (resample or crop one first)")
        section = H.CrossSection.choose(shape, row, column)
        regions: list[M.Region] = [M.parse_roi(r, shape) for r in rois] + [M.load_mask(p, shape) for p in masks]
        n_a, n_b = min(max_frames, sa.n_frames), min(max_frames, sb.n_frames)
        # One tap calibration on both sides (the twin's taps carry the sensor's fixed pattern
        # too): --flat, else the one a corrected side was made with; a correction's own flat=
        # must be the same file.
        sides = {"A": (sa, Path(a_path)), "B": (sb, Path(b_path))}
        recorded = [(s, recorded_tap_calibration(x)) for s, (x, _) in sides.items()]
        recorded = [(s, r) for s, r in recorded if r is not None]
        want = flat if flat is not None else (recorded[0][1] if recorded else None)
        origin = "--flat" if flat is not None else (f"the header of {recorded[0][0]}" if recorded else "")
        for (name, params), label in zip(specs, labels):
            f_var = params.get("flat")
            if f_var and not _same_file(f_var, want):
                raise TofhilError(f"correction {label!r} applies the tap calibration {f_var} to A only; "
                                  f"compare applies one tap calibration to both sides ({want or 'none given'})",
                                  field="--correct", expected=f"--flat {f_var} (applied to A and B) and no flat= "
                                                              "in the correction")
        plan = tap_calibration_plan(sides, want, origin)
        if want is not None:
            say(f"tap calibration {want} ({origin}) on both sides: " + ", ".join(
                f"{s} {'applied here' if plan[s] is not None else 'already applied'}" for s in plan))
        say(f"reference: averaging {n_b} frames of {b_path} (in the complex domain)" if sb.has_raw
            else f"reference: averaging {n_b} frames of {b_path}")
        ref, ref_noise = variant_frame(sb, max_frames, min_amplitude=min_amplitude, flat=plan["B"])
        health_b = tap_health(sb, max_frames)
        health_a = tap_health(sa, max_frames)
        split, fit = heldout_split(sa, n_a, [name for name, _ in specs], plan["A"])
        scored = list(range(n_a)) if split is None else list(split.scored)
        # the fit frames' scatter joins the noise estimate: the sensor's noise, whichever frames
        unseen = [] if split is None or split.in_sample else list(split.fit)
        say(f"measured: averaging {len(scored)} frames of {a_path}")
        if split is not None:
            say(f"corrections scored {'in-sample' if split.in_sample else 'on held-out frames'}: {split.text()}")
        fa, noise = variant_frame(sa, max_frames, min_amplitude=min_amplitude, flat=plan["A"], frames=scored,
                                  noise_frames=unseen)
        variants = [Variant(MEASURED, fa, noise * np.sqrt(len(scored)), noise_m=noise)]
        for (name, params), label in zip(specs, labels):
            p = load_params(name, params)
            say(f"correcting A with {label}")
            ctx = None
            if get_method(name).domain == "complex":
                ctx = context_for_session(sa, n_a, scored)
                ctx.split = split
                if fit is not None:
                    ctx.fit_signal, ctx.fit_saturated = fit
            f, s = variant_frame(sa, max_frames, name, p, min_amplitude, flat=plan["A"], context=ctx, frames=scored,
                                 noise_frames=unseen)
            variants.append(Variant(label, f, s * np.sqrt(len(scored)), name, dict(params), noise_m=s, correction=ctx))
        obj_source = None
        if objects:
            for sess, tag in ((sb, "B"), (sa, "A")):
                ids, names = object_id_map(sess)
                if ids is not None and ids.shape == shape:
                    regions = M.object_regions(ids, names, min_pixels=20) + regions
                    obj_source = tag
                    break
        regions = regions + BA.near_clipped_regions(health_a.saturated)
        # Validity relative to each object's own amplitude: a 1 % square is dark, not a shadow.
        own = [r.mask for r in regions if r.kind == "object"]
        for f in [ref] + [v.frame for v in variants]:
            _mask_shadows(f, min_relative_amplitude, own)
        freqs = getattr(sa, "freq_hz", None) if sa.has_raw else None
        wrap_m = M.wrap_period(freqs) if freqs is not None else None
        a_label = str(sa.device.get("model") or sa.device.get("name") or Path(a_path).name)
        b_label = str(sb.device.get("model") or sb.device.get("name") or Path(b_path).name)
        acquisition = {"a": sa.acquisition(), "b": sb.acquisition()}
        lens = twin_lens_camera(sa, sb)
        mismatches = acquisition_mismatches(acquisition["a"], acquisition["b"])
        for w in mismatches:
            say(f"warning: {w}")

    metrics: dict[str, Any] = {
        "software": f"tofhil {__version__}",
        "inputs": {"a": str(a_path), "b": str(b_path), "a_device": a_label, "b_device": b_label},
        "frames": {"a": len(scored), "b": n_b},
        # which of A's frames the corrections fitted on and which the figures are scored on
        "heldout": None if split is None else split.to_json(),
        # The camera settings of each side (a twin session records its full sensor configuration).
        "acquisition": acquisition,
        "acquisition_mismatches": mismatches,
        "settings": {"cell_size_m": cell_size, "threshold_m": threshold, "min_amplitude": min_amplitude,
                     "min_relative_amplitude": min_relative_amplitude, "wrap_m": wrap_m,
                     "object_regions_from": obj_source, "rois": list(rois), "masks": [str(p) for p in masks],
                     "cross_section": {"axis": section.axis, "index": section.index},
                     "roi_convention": "X0,Y0,X1,Y1 half-open (X1, Y1 exclusive)"},
        "depth_rmse_definition": M.DEPTH_RMSE,
        "reference_temporal_std_m_median": (float(np.nanmedian(ref_noise * np.sqrt(n_b)))
                                            if np.isfinite(ref_noise).any() else None),
        "averaging": "raw sessions: taps averaged over frames (after the tap calibration) before demodulation; "
                     "depth-only sessions: depth averaged",
        "tap_calibration": {"file": None if want is None else str(want), "from": origin or None,
                            "applied_here": {s: plan[s] is not None for s in plan}},
        "variants": {},
    }
    for f, h, path in ((ref, health_b, b_path), (fa, health_a, a_path)):
        if not M.frame_validity(f, h).any():
            raise TofhilError(f"has no valid pixel in the {min(max_frames, n_a if path == a_path else n_b)} frame(s) "
                              "compared (NaN, saturated, unlit or flagged invalid everywhere)", file=path,
                              field="depth/valid", expected="a capture with valid pixels in common with the other")
    for v in variants:
        say(f"metrics: {v.label}")
        with np.errstate(invalid="ignore"):
            noise_res = np.sqrt(np.nan_to_num(v.noise_m, nan=np.inf) ** 2 + np.nan_to_num(ref_noise) ** 2)
        noise_res[~np.isfinite(noise_res)] = np.nan  # A's noise unknown (one frame): no floor
        # "signal above noise" on each side with its own noise: a twin's pixel lit by no light of
        # its own has no phase to compare, however clean the capture's pixel is
        v.evaluation = M.evaluate(v.frame, ref, regions, wrap_m=wrap_m, health_a=health_a, health_b=health_b,
                                  cloud_regions=True, cell_size=cell_size, threshold=threshold,
                                  source=f"{a_path} vs {b_path}", noise_m=noise_res, freq_hz=freqs,
                                  own_noise_m=(v.noise_m, ref_noise))
        res = v.evaluation.to_json()
        res["temporal_std_m_median"] = (float(np.nanmedian(v.temporal_std_m))
                                        if np.isfinite(v.temporal_std_m).any() else None)
        res["method"] = v.method
        res["params"] = v.params
        res["notes"] = v.evaluation.validity_notes()
        if v.method is not None:  # before and after, per region, with the correction's own report
            res.update(BA.variant_report(v.label, v.correction, regions, metrics["variants"][MEASURED]["regions"],
                                         res["regions"]))
            res["notes"] += res["correction"]["notes"] + BA.worse_notes(v.label, res["before_after"])
        metrics["variants"][v.label] = res

    say("figures")
    figs = figures(variants, ref, section, cell_size)
    out.mkdir(parents=True, exist_ok=True)
    H.write_json(out / "metrics.json", metrics)
    write_report(out, metrics, variants, figs, lens)
    return M.json_safe(metrics)
