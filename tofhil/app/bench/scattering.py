"""Light that arrives by another path than the direct one: ``bench dark-squares`` (the stray-light
series: lens scatter onto a dark square) and ``bench multipath-corner`` (inter-reflection in a
corner), each against the twin's prediction, with the cause named from its signature."""

from __future__ import annotations

import math
import time
from typing import Any, Mapping

import numpy as np

from tofhil.app.bench.base import BenchOptions, BenchResult, Figure, acquisition
from tofhil.app.bench.depth import (
    DISTANCE_PARAM, FALSE_ALARM, _depth_stack, _nanmean, _nested_fits, _rig, _twin_stack,
    analyse_series, as_procedure,
)
from tofhil.app.campaign import CampaignResult, Plan, parse_plan
from tofhil.errors import TofhilError


# --------------------------------------------------------------------------- stray light: dark squares
class DarkSquares:
    NAME = "dark-squares"
    SUMMARY = ("the stray-light series: a dark square on the wall at reflectances down to 2 % of the wall's; the "
               "depth error on the square beside the twin's; an error growing as 1/reflectance is named stray light")
    REFLECTANCES = (0.5, 0.2, 0.1, 0.05, 0.02)

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, DISTANCE_PARAM, 1.0, scene_default="dark_square",
                    more={"square_reflectance": DarkSquares.REFLECTANCES[0]})

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        first, by = acquisition(opts, rig, 375)
        d = float(opts.extra.get("square_distance_m", 1.0))
        steps: list[dict[str, Any]] = [first]
        for rho in opts.extra.get("square_reflectances") or DarkSquares.REFLECTANCES:
            steps.append({"bench": {DISTANCE_PARAM: d, "square_reflectance": float(rho)},
                          "by": by,
                          "message": f"wall at {d:g} m; the square of {100 * rho:g} % of the wall's reflectance"})
            steps.append({"capture": {"label": f"sq{float(rho):g}", "frames": opts.frames}})
        return parse_plan({"name": DarkSquares.NAME, "steps": steps}, f"<{DarkSquares.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        return analyse_series(DarkSquares.NAME, campaign, rig, opts, "square_reflectance",
                              namer=name_reflectance_error, region=_square_region)


def _square_region(cam: Any, state: Mapping[str, Any]) -> tuple[tuple[int, int, int, int], float]:
    """The inner 60 % of the centred square (``square_size_m``, default 0.2 m, 1 mm in front of
    the wall, as the bundled ``dark_square`` scene has it): its ROI and depth offset."""
    d = float(state[DISTANCE_PARAM]) - 0.001
    half = 0.6 * 0.5 * float(state.get("square_size_m", 0.2)) / d
    hx, hy = max(1, int(half * cam.fx)), max(1, int(half * cam.fy))
    cx, cy = int(round(cam.cx)), int(round(cam.cy))
    return (max(cx - hx, 0), max(cy - hy, 0), min(cx + hx + 1, cam.width), min(cy + hy + 1, cam.height)), 0.001


def name_reflectance_error(rho: np.ndarray, delta: np.ndarray, se: np.ndarray) -> dict[str, Any]:
    """The depth error on a dark target against its reflectance: a constant (a range offset) or
    one growing as ``1 / reflectance`` (light scattered from the bright surroundings onto the
    target: its phasor adds to a direct signal that falls with the reflectance -- stray light)."""
    fits = _nested_fits(delta, se, {"offset": np.ones((len(rho), 1)),
                                    "stray_light": np.column_stack([np.ones_like(rho), 1.0 / rho])})
    if fits["p_extra"] < FALSE_ALARM and len(rho) >= 3:
        a, b = fits["stray_light"]["params"]
        sa, sb = fits["stray_light"]["sigma"]
        kind, chosen = "stray light", "stray_light"
        text = (f"stray light: the error on the square grows as 1/reflectance ({b * 1e3:+.2f} +- {sb * 1e3:.2f} mm x "
                f"wall/square reflectance, {a * 1e3:+.2f} +- {sa * 1e3:.2f} mm without it): light scattered in the "
                "lens from the bright wall onto the dark square, which the twin lacks")
        if abs(a) > 3 * sa:
            text += (f"; the constant {a * 1e3:+.1f} mm is a range error the twin lacks everywhere (the wall's "
                     "systematic error shows it too: accuracy-vs-distance names it)")
    else:
        (a,), (sa,) = fits["offset"]["params"], fits["offset"]["sigma"]
        kind, chosen = "range offset", "offset"
        text = f"a constant range offset of {a * 1e3:+.2f} +- {sa * 1e3:.2f} mm on the square"
    if fits[chosen]["p"] < FALSE_ALARM:
        kind = "unexplained"
        text = (f"neither a constant nor a 1/reflectance error explains it (best: {text}; chi2 "
                f"{fits[chosen]['chi2']:.1f} for {fits[chosen]['dof']} dof): run with --diagnose")
    return {"kind": kind, "text": text, "fits": fits, "chosen": chosen}


# --------------------------------------------------------------------------- multipath corner
class MultipathCorner:
    NAME = "multipath-corner"
    SUMMARY = ("a room corner seen along its diagonal: the depth error of its walls (light bouncing between them "
               "reads farther) against the twin's multipath, as a factor on the twin's error map")
    PARAM = "camera_distance_m"

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, MultipathCorner.PARAM, float(opts.distances_m[0]), scene_default="corner")

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        # 125 us: the emulated TOFcam635 renders there and scales other exposures linearly, its
        # fixed offsets too (at 250 us the factor reads 0.993 +- 0.002 with nothing hidden)
        first, by = acquisition(opts, rig, 125)
        steps: list[dict[str, Any]] = [first]
        for d in opts.extra.get("corner_distances_m") or (1.2,):
            steps.append({"bench": {MultipathCorner.PARAM: float(d)}, "by": by,
                          "message": f"camera on the corner's diagonal, {d:g} m from its apex, looking at it"})
            steps.append({"capture": {"label": f"corner{float(d):g}m", "frames": opts.frames}})
        return parse_plan({"name": MultipathCorner.NAME, "steps": steps}, f"<{MultipathCorner.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        seconds = {"twin": 0.0, "analysis": 0.0}
        rows: list[dict[str, Any]] = []
        maps: list[tuple[str, np.ndarray, np.ndarray]] = []
        for label, rec in campaign.captures.items():
            radial, valid, cam, acq = _depth_stack(campaign.session(label))
            t0 = time.monotonic()
            # the twin, noise-free, with its multipath and without (the geometric truth it knows)
            with_mp, _ = _twin_stack(rig, rec["bench"], acq, 1, 0, opts, noise=False)
            direct, _ = _twin_stack(rig, rec["bench"], acq, 1, 0, opts, noise=False,
                                    effects={"multipath": {"scale": 0.0}})
            seconds["twin"] += time.monotonic() - t0
            t0 = time.monotonic()
            truth, pred = direct[0], with_mp[0] - direct[0]
            ok = np.all(valid, axis=0) & np.isfinite(truth) & np.isfinite(pred)
            n = radial.shape[0]
            meas = _nanmean(radial, valid) - truth
            se = np.sqrt(np.nanvar(np.where(valid, radial, np.nan), axis=0, ddof=1) / n) if n > 1 else None
            if se is None or ok.sum() < 10:
                raise TofhilError("too few frames or pixels on the corner", field="--frames",
                                  expected="2 frames or more, the corner in view")
            x, y = pred[ok], meas[ok]
            # measured error = k * the twin's multipath error + c: k = 1 when the twin's multipath is
            # right. Ordinary least squares, its standard error from the residuals' own spread (per-pixel
            # weights from a few frames' variances made the stated sigma 2-3 x too small over seeds)
            design = np.column_stack([x, np.ones_like(x)])
            coef, *_ = np.linalg.lstsq(design, y, rcond=None)
            resid = y - design @ coef
            cov = np.linalg.inv(design.T @ design) * float(resid @ resid) / max(len(y) - 2, 1)
            sk = math.sqrt(cov[0, 0])
            red = float(np.mean((resid / np.maximum(se[ok], 1e-6)) ** 2))
            rows.append({"label": label, MultipathCorner.PARAM: float(rec["bench"][MultipathCorner.PARAM]),
                         "measured_error_m": float(np.mean(y)), "twin_error_m": float(np.mean(x)),
                         "measured_error_p95_m": float(np.percentile(y, 95)), "twin_error_p95_m": float(np.percentile(x, 95)),
                         "factor": float(coef[0]), "factor_sigma": sk, "offset_m": float(coef[1]),
                         "reduced_chi2": red, "pixels": int(ok.sum())})
            maps.append((label, np.where(ok, meas, np.nan), np.where(ok, pred, np.nan)))
            seconds["analysis"] += time.monotonic() - t0
        res = BenchResult(MultipathCorner.NAME, rig.device, [], curves={MultipathCorner.NAME: rows}, seconds=seconds)
        worst = max(rows, key=lambda r: abs(r["measured_error_m"]))
        res.figures = [Figure("multipath_error_m", worst["measured_error_m"], predicted=worst["twin_error_m"],
                           note=f"mean over the corner at {worst[MultipathCorner.PARAM]:g} m"),
                       Figure("multipath_factor", worst["factor"], worst["factor_sigma"], 1.0, 0.0,
                           note="measured error / the twin's multipath error")]
        for r in rows:
            z = (r["factor"] - 1.0) / r["factor_sigma"]
            if abs(z) < 3:
                res.findings.append(f"{r['label']}: the walls' depth error is the twin's multipath ({1e3 * r['measured_error_m']:.1f} "
                                    f"mm mean, twin {1e3 * r['twin_error_m']:.1f} mm; factor {r['factor']:.3f} +- "
                                    f"{r['factor_sigma']:.3f})")
            else:
                res.findings.append(f"{r['label']}: multipath {r['factor']:.2f} +- {r['factor_sigma']:.2f} x the twin's "
                                    f"({1e3 * r['measured_error_m']:.1f} mm mean against {1e3 * r['twin_error_m']:.1f} mm): "
                                    "the walls reflect more (or less) into each other than the twin's materials say "
                                    "(reflectance, a glossy finish) -- fit them with tofhil diagnose (multipath)")
        res.plots = lambda: _corner_plot(maps)
        return res


def _corner_plot(maps: list[tuple[str, np.ndarray, np.ndarray]]) -> list[tuple[str, str | None, str]]:
    from tofhil.eval.reports.html import fig_uri, pyplot

    plt = pyplot()
    label, meas, pred = maps[0]
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.6), layout="constrained")
    hi = float(np.nanpercentile(np.abs(np.concatenate([meas.ravel(), pred.ravel()])), 98)) * 1e3
    for ax, img, title in ((axes[0], meas, "measured - truth"), (axes[1], pred, "twin's multipath error")):
        im = ax.imshow(img * 1e3, cmap="magma", vmin=0, vmax=hi)
        ax.set_title(f"{title} ({label})")
        fig.colorbar(im, ax=ax, label="mm")
    h = meas.shape[0] // 2
    axes[2].plot(meas[h] * 1e3, ".", ms=4, label="measured, middle row")
    axes[2].plot(pred[h] * 1e3, "-", color="C3", label="twin")
    axes[2].set_xlabel("column (pixel)")
    axes[2].set_ylabel("depth error (mm)")
    axes[2].legend(fontsize=8)
    return [("Multipath in the corner", fig_uri(fig), "The depth error of the walls against the geometric truth "
             "(the twin's direct-only distance), beside the twin's multipath error for the same view.")]


PROCEDURES = [as_procedure(DarkSquares), as_procedure(MultipathCorner)]
