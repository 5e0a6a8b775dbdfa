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
class Spheres:
    NAME = "spheres"
    SUMMARY = ("two spheres on a bar (VDI/VDE 2634-2): sphere-spacing error and probing errors (size, form) "
               "from sphere fits to the point cloud, beside the twin's")

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, "spheres_distance_m", float(opts.extra.get("spheres_distances_m", (1.0,))[0]),
                    scene_default="spheres")

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        first, by = acquisition(opts, rig, 125)
        steps: list[dict[str, Any]] = [first]
        for d in opts.extra.get("spheres_distances_m") or (1.0,):
            steps.append({"bench": {"spheres_distance_m": float(d)}, "by": by,
                          "message": f"the sphere bar across the view, its spheres {d:g} m from the camera"})
            steps.append({"capture": {"label": f"spheres{float(d):g}m", "frames": opts.frames}})
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
            row = {"label": label, "spheres_distance_m": float(rec["bench"]["spheres_distance_m"]),
                   **{f"measured_{k}": v for k, v in _sphere_figures(radial, valid, cam, params).items()}}
            seconds["analysis"] += time.monotonic() - t0
            t0 = time.monotonic()
            tr, tv = _twin_stack(rig, rec["bench"], acq, max(opts.frames, 2), opts.seed + 104729 + i, opts)
            row.update({f"twin_{k}": v for k, v in _sphere_figures(tr, tv, cam, params).items()})
            seconds["twin"] += time.monotonic() - t0
            rows.append(row)
        res = BenchResult(Spheres.NAME, rig.device, [], curves={Spheres.NAME: rows}, seconds=seconds)
        worst = max(rows, key=lambda r: abs(r["measured_spacing_error_m"]))
        for name, key in (("sphere_spacing_error_m", "spacing_error_m"), ("probing_error_size_m", "size_error_m"),
                          ("probing_error_form_m", "form_m")):
            res.figures.append(Figure(name, worst[f"measured_{key}"], worst.get(f"measured_{key}_se", math.nan),
                                      worst[f"twin_{key}"], worst.get(f"twin_{key}_se", math.nan),
                                      note=f"at {worst['spheres_distance_m']:g} m"))
        for r in rows:
            z = ((r["measured_spacing_error_m"] - r["twin_spacing_error_m"])
                 / math.hypot(r["measured_spacing_error_m_se"], r["twin_spacing_error_m_se"]))
            verdict = "agrees with the twin" if abs(z) < 3 else "differs from the twin"
            res.findings.append(
                f"{r['label']}: sphere spacing {1e3 * r['measured_spacing_m']:.1f} mm (true "
                f"{1e3 * r['measured_true_spacing_m']:.1f}), error {1e3 * r['measured_spacing_error_m']:+.2f} +- "
                f"{1e3 * r['measured_spacing_error_m_se']:.2f} mm, twin {1e3 * r['twin_spacing_error_m']:+.2f} mm "
                f"({verdict}, {z:+.1f} sigma); probing size {1e3 * r['measured_size_error_m']:+.1f} mm "
                f"(twin {1e3 * r['twin_size_error_m']:+.1f}), form {1e3 * r['measured_form_m']:.1f} mm "
                f"(twin {1e3 * r['twin_form_m']:.1f})")
        return res


def _sphere_figures(radial: np.ndarray, valid: np.ndarray, cam: Any, params: Mapping[str, Any]) -> dict[str, Any]:
    """Sphere fits on each sphere's cap (pixels within 80 % of its projected radius, valid in
    every frame; the mean of the frames): spacing, its error, the probing errors (VDI/VDE 2634-2
    PS: fitted minus true diameter / 2 here as a radius error; PF: range of residuals). The
    standard errors come from fits to the single frames (their spread over the frames / sqrt N)."""
    from tofhil.eval.metrics.bench import fit_sphere

    d = float(params["spheres_distance_m"])
    sp = float(params["sphere_spacing_m"])
    r_true = float(params["sphere_radius_m"])
    ok = np.all(valid, axis=0)
    mean = _nanmean(radial, valid)
    out: dict[str, Any] = {"true_spacing_m": sp}
    per_frame_spacing, per_frame_size = [], []
    fits = []
    for sx in (-sp / 2, sp / 2):
        u, v = cam.project(np.array([[sx, 0.0, d]]))[0]
        rad_px = 0.8 * r_true * cam.fx / (d - r_true)
        vv, uu = np.mgrid[0:cam.height, 0:cam.width]
        cap = ok & ((uu - u) ** 2 + (vv - v) ** 2 <= rad_px ** 2)
        if cap.sum() < 10:
            raise TofhilError(f"a sphere covers {int(cap.sum())} valid pixels", field="spheres_distance_m",
                              expected="spheres large enough in the view (closer, or bigger spheres)")
        fits.append((fit_sphere(cam.rays[cap] * mean[cap][:, None]),
                     [fit_sphere(cam.rays[cap] * radial[k][cap][:, None]) for k in range(radial.shape[0])]))
    (a, a_fr), (b, b_fr) = fits
    spacing = float(np.linalg.norm(np.subtract(a.centre, b.centre)))
    n = radial.shape[0]
    per_frame_spacing = [float(np.linalg.norm(np.subtract(x.centre, y.centre))) for x, y in zip(a_fr, b_fr)]
    per_frame_size = [0.5 * (x.radius_m + y.radius_m) - r_true for x, y in zip(a_fr, b_fr)]

    def se(vals: list[float]) -> float:
        return float(np.std(vals, ddof=1) / math.sqrt(n)) if n > 1 else math.nan

    out.update({"spacing_m": spacing, "spacing_error_m": spacing - sp, "spacing_error_m_se": se(per_frame_spacing),
                "size_error_m": 0.5 * (a.radius_m + b.radius_m) - r_true, "size_error_m_se": se(per_frame_size),
                "form_m": max(a.form_m, b.form_m), "points": a.points + b.points})
    return out


PROCEDURES = [as_procedure(Spheres)]
