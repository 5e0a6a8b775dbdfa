"""``bench spheres``: the VDI/VDE 2634-2 length test -- sphere-spacing error and probing errors
(size, form) from sphere fits to the point cloud, beside the twin's."""

from __future__ import annotations

import math
import time
from typing import Any, Mapping

import numpy as np

from tofhil.app.bench.base import BenchOptions, BenchResult, Figure, acquisition
from tofhil.app.bench.depth import (
    _depth_stack, _nanmean, _rig, _split, _twin_stack,
    as_procedure,
)
from tofhil.app.campaign import CampaignResult, Plan, parse_plan
from tofhil.errors import TofhilError


# --------------------------------------------------------------------------- spheres (VDI/VDE 2634-2)
#: The bar's positions and orientations in the measuring volume (VDI/VDE 2634-2 asks for
#: several): name -> (lateral place of its middle as a share of the room the view leaves beside
#: the bar, -1 left .. 1 right; its turn about the optical axis, deg; its tilt in depth, deg).
POSITIONS: dict[str, tuple[float, float, float]] = {
    "centre": (0.0, 0.0, 0.0), "diagonal": (0.0, 20.0, 0.0), "depth": (0.0, 0.0, 30.0),
    "left": (-0.8, 0.0, 0.0), "right": (0.8, 0.0, 0.0)}
BAR = ("bar_x_m", "bar_y_m", "bar_ux", "bar_uy", "bar_uz")
#: The bar's lengths (sphere spacing, m): the sphere-spacing error is measured against length
#: (VDI/VDE 2634-2 asks for lengths across the volume; a range scale grows with length, a noise
#: does not). The longest leaves both spheres in the TOFcam635's 50 x 20 degree view at 1 m in
#: every position (the 20 degree turn included).
LENGTHS_M = (0.15, 0.3, 0.5)


def bar_state(name: str, d: float, camera: Any, spacing_m: float = 0.3, radius_m: float = 0.05) -> dict[str, float]:
    """The scene parameters of the bar at position ``name`` with its middle ``d`` from the
    camera: its unit direction from the turn and the tilt, its middle moved sideways by a
    share of what the view leaves beside the bar at that distance (so both spheres stay in it)."""
    share, turn, tilt = POSITIONS[name]
    a, t = math.radians(turn), math.radians(tilt)
    u = (math.cos(t) * math.cos(a), math.cos(t) * math.sin(a), math.sin(t))
    half = d * min(camera.cx + 0.5, camera.width - 0.5 - camera.cx) / camera.fx    # the view's half-width at d
    room = max(half - 0.5 * spacing_m * abs(u[0]) - 1.5 * radius_m, 0.0)
    return {"spheres_distance_m": float(d), "sphere_spacing_m": float(spacing_m), "bar_x_m": share * room,
            "bar_y_m": 0.0, "bar_ux": u[0], "bar_uy": u[1], "bar_uz": u[2]}


class Spheres:
    NAME = "spheres"
    SUMMARY = ("two spheres on a bar (VDI/VDE 2634-2) at several positions and orientations in the view and "
               "several bar lengths: sphere-spacing error (against length) and probing errors (size, form) from "
               "sphere fits, per position and overall, beside the twin's")

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, "spheres_distance_m", float(opts.extra.get("spheres_distances_m", (1.0,))[0]),
                    scene_default="spheres", more={"sphere_spacing_m": 0.3, "bar_x_m": 0.0, "bar_y_m": 0.0,
                                                   "bar_ux": 1.0, "bar_uy": 0.0, "bar_uz": 0.0})

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        first, by = acquisition(opts, rig, 125)
        cam = _camera(rig)
        steps: list[dict[str, Any]] = [first]
        names = opts.extra.get("spheres_positions") or tuple(POSITIONS)
        lengths = opts.extra.get("spheres_lengths_m") or LENGTHS_M
        for name in names:
            if name not in POSITIONS:
                raise TofhilError(f"no bar position {name!r}", field="spheres_positions",
                                  expected="some of " + ", ".join(POSITIONS))
        for d in opts.extra.get("spheres_distances_m") or (1.0,):
            for length in lengths:
                for name in names:
                    state = bar_state(name, float(d), cam, spacing_m=float(length))
                    where = (f"its middle {state['bar_x_m']:+.2f} m sideways, turned {POSITIONS[name][1]:g} deg "
                             f"about the optical axis, tilted {POSITIONS[name][2]:g} deg in depth")
                    steps.append({"bench": state, "by": by,
                                  "message": f"the {float(length):g} m sphere bar ({name}) {d:g} m from the camera: "
                                             f"{where}"})
                    steps.append({"capture": {"label": f"{name}-{float(length):g}m-{float(d):g}m",
                                              "frames": opts.frames}})
        return parse_plan({"name": Spheres.NAME, "steps": steps}, f"<{Spheres.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        from tofhil.sim.scene import load_scene

        seconds = {"twin": 0.0, "analysis": 0.0}
        rows: list[dict[str, Any]] = []
        for i, (label, rec) in enumerate(campaign.captures.items()):
            radial, valid, cam, acq = _depth_stack(campaign.session(label))
            params = load_scene(rig.scene, {"params": _split(rec["bench"])[0]}).params
            t0 = time.monotonic()
            row = {"label": label, "position": label.split("-", 1)[0],
                   "spheres_distance_m": float(rec["bench"]["spheres_distance_m"]),
                   "bar_length_m": float(params["sphere_spacing_m"]),
                   **{k: float(params[k]) for k in BAR},
                   **{f"measured_{k}": v for k, v in _sphere_figures(radial, valid, cam, params).items()}}
            seconds["analysis"] += time.monotonic() - t0
            t0 = time.monotonic()
            tr, tv = _twin_stack(rig, rec["bench"], acq, max(opts.frames, 2), opts.seed + 104729 + i, opts)
            row.update({f"twin_{k}": v for k, v in _sphere_figures(tr, tv, cam, params).items()})
            seconds["twin"] += time.monotonic() - t0
            rows.append(row)
        res = BenchResult(Spheres.NAME, rig.device, [], curves={Spheres.NAME: rows}, seconds=seconds)
        # VDI/VDE 2634-2: each error is the largest over the positions (of the bar, of the spheres)
        for name, key, absolute in (("sphere_spacing_error_m", "spacing_error_m", True),
                                    ("probing_error_size_m", "size_error_m", True), ("probing_error_form_m", "form_m", False)):
            w = max(rows, key=lambda r: abs(r[f"measured_{key}"]) if absolute else r[f"measured_{key}"])
            res.figures.append(Figure(name, w[f"measured_{key}"], w.get(f"measured_{key}_se", math.nan),
                                      w[f"twin_{key}"], w.get(f"twin_{key}_se", math.nan),
                                      note=f"the largest over {len(rows)} captures: {w['label']}"))
        zs = []
        for r in rows:
            z = ((r["measured_spacing_error_m"] - r["twin_spacing_error_m"])
                 / math.hypot(r["measured_spacing_error_m_se"], r["twin_spacing_error_m_se"]))
            zs.append(z)
            verdict = "agrees with the twin" if abs(z) < 3 else "differs from the twin"
            res.findings.append(
                f"{r['label']}: sphere spacing {1e3 * r['measured_spacing_m']:.1f} mm (true "
                f"{1e3 * r['measured_true_spacing_m']:.1f}), error {1e3 * r['measured_spacing_error_m']:+.2f} +- "
                f"{1e3 * r['measured_spacing_error_m_se']:.2f} mm, twin {1e3 * r['twin_spacing_error_m']:+.2f} mm "
                f"({verdict}, {z:+.1f} sigma); probing size {1e3 * r['measured_size_error_m']:+.1f} mm "
                f"(twin {1e3 * r['twin_size_error_m']:+.1f}), form {1e3 * r['measured_form_m']:.1f} mm "
                f"(twin {1e3 * r['twin_form_m']:.1f})")
        if all(math.isfinite(z) for z in zs):
            from scipy.stats import norm, t

            from tofhil.app.bench.depth import FALSE_ALARM, _chi2_sf

            # each z is a t statistic: its standard errors come from the spread over a few frames'
            # fits (Welch-Satterthwaite degrees of freedom); mapped to a normal quantile first, so
            # that few frames do not make the chi-square test cry wolf
            nz = []
            for r, z in zip(rows, zs):
                nz.append(float(norm.isf(t.sf(z, _welch_dof(r)))))
            chi2 = float(np.sum(np.square(nz)))
            p = _chi2_sf(chi2, len(zs))
            res.details["agreement"] = {"spacing": {"chi2": chi2, "dof": len(zs), "p": p, "t": zs, "z": nz}}
            res.findings.append(f"over the {len(zs)} captures the sphere-spacing errors "
                                + ("agree with the twin's" if p >= FALSE_ALARM else "differ from the twin's")
                                + f" (chi2 {chi2:.1f} for {len(zs)}, p = {p:.2g})")
        by_length, growth = against_length(rows)
        res.curves["spheres-by-length"] = by_length
        for r in by_length:
            res.findings.append(
                f"bar length {r['bar_length_m']:g} m: sphere-spacing error {1e3 * r['measured_spacing_error_m']:+.2f} "
                f"+- {1e3 * r['measured_spacing_error_m_se']:.2f} mm (the largest over {r['positions']} positions: "
                f"{r['label']}), twin {1e3 * r['twin_spacing_error_m']:+.2f} +- {1e3 * r['twin_spacing_error_m_se']:.2f} "
                f"mm; beyond the twin's, over the positions: {1e3 * r['difference_m']:+.2f} +- "
                f"{1e3 * r['difference_m_se']:.2f} mm")
        if growth is not None:
            res.details["against_length"] = growth
            res.findings.append(growth["text"])
        res.plots = lambda: _length_plot(rows, by_length)
        return res


def against_length(rows: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """The sphere-spacing error against the bar's length: per length the largest over the
    positions (VDI/VDE 2634-2) beside the twin's, and the difference from the twin's averaged over
    the positions (inverse-variance weights); and how the difference grows with length -- a
    weighted line through the origin, ``b L``: a range scale ``k`` reads every length ``(1 + k)``
    times (``b = k``), a range offset ``delta`` at the bar's distance ``D`` about ``delta / D``
    for a bar across the view, a noise not at all. None with fewer than two lengths."""
    out: list[dict[str, Any]] = []
    diff = np.array([r["measured_spacing_error_m"] - r["twin_spacing_error_m"] for r in rows])
    se = np.array([math.hypot(r["measured_spacing_error_m_se"], r["twin_spacing_error_m_se"]) for r in rows])
    length = np.array([r["bar_length_m"] for r in rows])
    for lv in sorted(set(length.tolist())):
        at = [r for r in rows if r["bar_length_m"] == lv]
        w = max(at, key=lambda r: abs(r["measured_spacing_error_m"]))
        m = (length == lv) & np.isfinite(diff) & (se > 0)
        wt = 1.0 / se[m] ** 2
        out.append({"bar_length_m": lv, "positions": len(at), "label": w["label"],
                    **{f"{k}_spacing_error_m{x}": w[f"{k}_spacing_error_m{x}"] for k in ("measured", "twin")
                       for x in ("", "_se")},
                    "difference_m": float(np.sum(wt * diff[m]) / np.sum(wt)) if m.any() else math.nan,
                    "difference_m_se": float(1.0 / math.sqrt(np.sum(wt))) if m.any() else math.nan})
    ok = np.isfinite(diff) & (se > 0)
    if len(out) < 2 or ok.sum() < 2:
        return out, None
    from scipy.stats import t as student

    from tofhil.app.bench.depth import FALSE_ALARM

    w = 1.0 / se[ok] ** 2
    b = float(np.sum(w * length[ok] * diff[ok]) / np.sum(w * length[ok] ** 2))
    sb = float(1.0 / math.sqrt(np.sum(w * length[ok] ** 2)))
    # the standard errors come from a few frames' jackknife: the slope's ratio is a t statistic,
    # taken with the fewest Welch-Satterthwaite degrees of freedom of its captures (over 20 seeds
    # of 5 frames its spread was 1.05 and 1.40 x a normal one's)
    nu = min(_welch_dof(r) for r, k in zip(rows, ok) if k)
    p = float(2 * student.sf(abs(b) / sb, nu))
    text = (f"the sphere-spacing error beyond the twin's grows by {b * 1e3:+.2f} +- {sb * 1e3:.2f} mm per metre of "
            "bar length " + ("(beyond noise, p = %.1e: a range scale of %+.2f %% reads every length so much longer; "
                             "a range offset at the bar's distance D about D times as much)" % (p, 100 * b)
                             if p < FALSE_ALARM else f"(within noise, p = {p:.2f})"))
    return out, {"per_m": b, "per_m_se": sb, "dof": nu, "p": p, "text": text}


def _welch_dof(r: Mapping[str, Any]) -> float:
    """Welch-Satterthwaite degrees of freedom of a capture's measured-minus-twin spacing error."""
    a2, b2 = r["measured_spacing_error_m_se"] ** 2, r["twin_spacing_error_m_se"] ** 2
    return (a2 + b2) ** 2 / (a2 ** 2 / max(r["measured_frames"] - 1, 1) + b2 ** 2 / max(r["twin_frames"] - 1, 1))


def _length_plot(rows: list[dict[str, Any]], by_length: list[dict[str, Any]]) -> list[tuple[str, str | None, str]]:
    from tofhil.eval.reports.html import fig_uri, pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.2), layout="constrained")
    names = sorted({r["position"] for r in rows}, key=lambda n: list(POSITIONS).index(n) if n in POSITIONS else 99)
    span = max((r["bar_length_m"] for r in rows), default=1.0)
    for j, name in enumerate(names):
        at = sorted((r for r in rows if r["position"] == name), key=lambda r: r["bar_length_m"])
        x = np.array([r["bar_length_m"] for r in at]) + 0.012 * span * (j - (len(names) - 1) / 2)
        ax.errorbar(x, [1e3 * r["measured_spacing_error_m"] for r in at],
                    yerr=[2e3 * r["measured_spacing_error_m_se"] for r in at], fmt="o", color=f"C{j}",
                    label=f"{name}: measured (2 s.e.)")
        ax.plot(x, [1e3 * r["twin_spacing_error_m"] for r in at], "x", color=f"C{j}", ms=8)
    lv = [r["bar_length_m"] for r in by_length]
    ax.plot(lv, [1e3 * np.mean([r["twin_spacing_error_m"] for r in rows if r["bar_length_m"] == v]) for v in lv],
            "k:", lw=1, label="twin (x); its mean over the positions")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("bar length (sphere spacing, m)")
    ax.set_ylabel("sphere-spacing error (mm)")
    ax.legend(fontsize=8)
    return [("Sphere-spacing error against bar length", fig_uri(fig),
             "Each position's measured spacing error (markers, 2 standard errors) and the twin's prediction for the "
             "same bar (x), at each bar length.")]


def _camera(rig: Any) -> Any:
    """The camera the bench's captures will have: the emulated TOFcam635's, else the scene's."""
    from tofhil.camera import load_camera_preset
    from tofhil.sim.scene import load_scene

    if rig.device.startswith("emulator"):
        from tofhil.sim.sources import TOFCAM635_PRESET

        return load_camera_preset(TOFCAM635_PRESET)
    return load_scene(getattr(rig, "scene", None) or "spheres").camera


def _sphere_figures(radial: np.ndarray, valid: np.ndarray, cam: Any, params: Mapping[str, Any]) -> dict[str, Any]:
    """Sphere fits on each sphere's cap (pixels within 80 % of its projected radius, valid in
    every frame; the mean of the frames): spacing, its error, the probing errors (VDI/VDE 2634-2
    PS: fitted minus true diameter / 2 here as a radius error; PF: range of residuals). The
    standard errors come from fits to the single frames (their spread over the frames / sqrt N)."""
    from tofhil.eval.metrics.bench import fit_sphere

    d = float(params["spheres_distance_m"])
    sp = float(params["sphere_spacing_m"])
    r_true = float(params["sphere_radius_m"])
    mid = np.array([float(params.get("bar_x_m", 0.0)), float(params.get("bar_y_m", 0.0)), d])
    u = np.array([float(params.get(k, v)) for k, v in (("bar_ux", 1.0), ("bar_uy", 0.0), ("bar_uz", 0.0))])
    ok = np.all(valid, axis=0)
    mean = _nanmean(radial, valid)
    out: dict[str, Any] = {"true_spacing_m": sp}
    fits = []
    for centre in (mid - 0.5 * sp * u, mid + 0.5 * sp * u):
        pu, pv = cam.project(centre[None])[0]
        rad_px = 0.8 * r_true * cam.fx / (centre[2] - r_true)
        vv, uu = np.mgrid[0:cam.height, 0:cam.width]
        cap = ok & ((uu - pu) ** 2 + (vv - pv) ** 2 <= rad_px ** 2)
        if cap.sum() < 10:
            raise TofhilError(f"a sphere covers {int(cap.sum())} valid pixels", field="spheres_distance_m",
                              expected="spheres large enough in the view (closer, or bigger spheres)")
        n = radial.shape[0]
        # the jackknife over frames: the fit to the mean of all frames but one, for each frame
        # (fits to single frames understate the mean-fit's spread: on 9 px caps with 30-40 mm of
        # noise a single frame's fit is far from linear in its data)
        rest = [(mean[cap] * n - radial[k][cap]) / (n - 1) for k in range(n)] if n > 1 else []
        fits.append((fit_sphere(cam.rays[cap] * mean[cap][:, None]),
                     [fit_sphere(cam.rays[cap] * r[:, None]) for r in rest]))
    (a, a_fr), (b, b_fr) = fits
    spacing = float(np.linalg.norm(np.subtract(a.centre, b.centre)))
    per_frame_spacing = [float(np.linalg.norm(np.subtract(x.centre, y.centre))) for x, y in zip(a_fr, b_fr)]
    per_frame_size = [0.5 * (x.radius_m + y.radius_m) - r_true for x, y in zip(a_fr, b_fr)]

    def se(vals: list[float]) -> float:
        v = np.asarray(vals)
        return float(math.sqrt((n - 1) / n * np.sum((v - v.mean()) ** 2))) if n > 1 else math.nan

    out.update({"spacing_m": spacing, "spacing_error_m": spacing - sp, "spacing_error_m_se": se(per_frame_spacing),
                "size_error_m": 0.5 * (a.radius_m + b.radius_m) - r_true, "size_error_m_se": se(per_frame_size),
                "form_m": max(a.form_m, b.form_m), "points": a.points + b.points, "frames": n})
    return out


PROCEDURES = [as_procedure(Spheres)]
