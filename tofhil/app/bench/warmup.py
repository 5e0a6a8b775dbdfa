"""``bench warm-up``: range and amplitude from power-on against time and the recorded chip
temperature; the drift per degree (the twin has no thermal model: it predicts none) and when
the range is stable."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from tofhil.app.bench.base import BenchOptions, BenchResult, Figure, acquisition
from tofhil.app.bench.depth import (
    DISTANCE_PARAM, FALSE_ALARM, _depth_stack, _nested_fits, _rig, as_procedure,
)
from tofhil.app.campaign import CampaignResult, Plan, parse_plan


# --------------------------------------------------------------------------- warm-up
class WarmUp:
    NAME = "warm-up"
    SUMMARY = ("range and amplitude against time and the recorded chip temperature from power-on: the drift per "
               "degree against the twin's (none), and when the range is stable")
    CAPTURES = 12
    INTERVAL_S = 10.0

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, DISTANCE_PARAM, float(opts.extra.get("warmup_distance_m", 1.0)))

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        first, by = acquisition(opts, rig, 125)
        d = float(opts.extra.get("warmup_distance_m", 1.0))
        steps: list[dict[str, Any]] = [first,
                                       {"bench": {DISTANCE_PARAM: d}, "by": by,
                                        "message": f"flat target at {d:g} m; power the camera on now"}]
        n = int(opts.extra.get("warmup_captures", WarmUp.CAPTURES))
        for i in range(n):
            if i:
                steps.append({"wait": float(opts.extra.get("warmup_interval_s", WarmUp.INTERVAL_S))})
            steps.append({"capture": {"label": f"t{i:03d}", "frames": opts.frames}})
        return parse_plan({"name": WarmUp.NAME, "steps": steps}, f"<{WarmUp.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        from tofhil.eval.metrics.bench import centre_roi, depth_stack_stats
        from tofhil.session import open_session

        t0 = time.monotonic()
        rows: list[dict[str, Any]] = []
        first = None
        for label, rec in campaign.captures.items():
            radial, valid, cam, acq = _depth_stack(campaign.session(label))
            with open_session(campaign.session(label)) as s:
                parts = [s.raw_frame(i) if s.has_raw else s.depth_frame(i) for i in range(s.n_frames)]
            temp = float(np.nanmean([f.temperature_c for f in parts]))
            t_s = float(rec["finished_unix_s"]) - float(rec["seconds"]) / 2   # the capture's middle
            first = t_s if first is None else first
            roi = opts.roi or centre_roi(cam.shape)
            d_true = float(rec["bench"][DISTANCE_PARAM])
            m = depth_stack_stats(radial, valid, d_true / cam.ray_z, roi)
            amp = np.nanmean([_amplitude(f)[roi[1]:roi[3], roi[0]:roi[2]] for f in parts])
            rows.append({"label": label, "time_s": t_s - first, "temperature_c": temp, "distance_m": d_true,
                         "measured_systematic_m": m.systematic_m, "measured_systematic_se_m": m.systematic_se_m,
                         "measured_random_m": m.random_m, "amplitude": float(amp)})
        res = BenchResult(WarmUp.NAME, rig.device, [], curves={WarmUp.NAME: rows},
                          seconds={"analysis": time.monotonic() - t0})
        res.findings, fig = warmup_findings(rows, float(opts.extra.get("stable_m", 0.001)))
        res.figures = fig
        res.plots = lambda: _warmup_plot(rows)
        return res


def _amplitude(frame: Any) -> np.ndarray:
    """A raw frame's modulation amplitude at its first frequency, or a depth frame's amplitude."""
    if hasattr(frame, "taps"):
        from tofhil.demod import phasor

        return np.abs(phasor(np.asarray(frame.taps[0], dtype=np.float64), frame.theta_rad))
    return np.asarray(frame.amplitude if frame.amplitude is not None else np.full(frame.distance_m.shape, np.nan),
                      dtype=np.float64)


def warmup_findings(rows: list[dict[str, Any]], stable_m: float) -> tuple[list[str], list[Figure]]:
    """The range's drift per degree (weighted fit against temperature; the twin has no thermal
    model, so it predicts none) and when the range settles to within ``stable_m`` of its final
    value (for the rest of the run)."""
    temp = np.array([r["temperature_c"] for r in rows])
    sysm = np.array([r["measured_systematic_m"] for r in rows])
    se = np.array([r["measured_systematic_se_m"] for r in rows])
    t = np.array([r["time_s"] for r in rows])
    findings: list[str] = []
    figs: list[Figure] = []
    ok = np.isfinite(sysm) & np.isfinite(temp) & np.isfinite(se) & (se > 0)
    if ok.sum() >= 3 and np.ptp(temp[ok]) > 0:
        fits = _nested_fits(sysm[ok], se[ok], {"constant": np.ones((ok.sum(), 1)),
                                               "drift": np.column_stack([np.ones(ok.sum()), temp[ok] - temp[ok][0]])})
        b, sb = fits["drift"]["params"][1], fits["drift"]["sigma"][1]
        figs.append(Figure("warmup_drift_m_per_c", b, sb, predicted=0.0, predicted_sigma=0.0,
                           note=f"over {temp[ok].min():.2f}..{temp[ok].max():.2f} degC"))
        if fits["p_extra"] < FALSE_ALARM:
            findings.append(f"the range drifts with temperature: {b * 1e3:+.2f} +- {sb * 1e3:.2f} mm per degC over "
                            f"{temp[ok].min():.2f}..{temp[ok].max():.2f} degC (p = {fits['p_extra']:.1e}); the twin "
                            "has no thermal model and predicts none: a temperature compensation is missing")
        else:
            findings.append(f"no drift with temperature beyond noise ({b * 1e3:+.2f} +- {sb * 1e3:.2f} mm per degC "
                            f"over {temp[ok].min():.2f}..{temp[ok].max():.2f} degC), as the twin predicts")
    else:
        findings.append("too few captures or no temperature change: no drift can be measured")
    # stable from capture i: the rest (3 captures at least) lie within the tolerance of their mean
    # and show no trend in time (the chi-square-difference test at the false-alarm rate)
    stable_i = None
    for i in range(max(len(rows) - 2, 0)):
        rest = slice(i, None)
        if not ok[rest].all():
            continue
        flat = np.all(np.abs(sysm[rest] - sysm[rest].mean()) <= stable_m + 2 * se[rest])
        trend = _nested_fits(sysm[rest], se[rest], {"constant": np.ones((len(t[rest]), 1)),
                                                    "trend": np.column_stack([np.ones(len(t[rest])), t[rest]])})
        if flat and trend["p_extra"] >= FALSE_ALARM:
            stable_i = i
            break
    if stable_i is not None:
        figs.append(Figure("warmup_time_s", float(t[stable_i]), note=f"at {temp[stable_i]:.2f} degC"))
        findings.append(f"range stable (within {stable_m * 1e3:g} mm, no trend) from {t[stable_i]:.0f} s, "
                        f"{temp[stable_i]:.2f} degC")
    else:
        findings.append(f"range not stable within {stable_m * 1e3:g} mm by the end ({t[-1]:.0f} s): warm up longer")
    return findings, figs


def _warmup_plot(rows: list[dict[str, Any]]) -> list[tuple[str, str | None, str]]:
    from tofhil.eval.reports.html import fig_uri, pyplot

    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.0), layout="constrained")
    t = [r["time_s"] for r in rows]
    axes[0].plot(t, [r["temperature_c"] for r in rows], "o-")
    axes[0].set_xlabel("time (s)")
    axes[0].set_ylabel("chip temperature (°C)")
    axes[0].set_title("temperature")
    axes[1].errorbar([r["temperature_c"] for r in rows], [1e3 * r["measured_systematic_m"] for r in rows],
                     yerr=[2e3 * r["measured_systematic_se_m"] for r in rows], fmt="o", label="measured (2 s.e.)")
    axes[1].axhline(1e3 * rows[0]["measured_systematic_m"], color="C3", lw=1, label="twin: no thermal drift")
    axes[1].set_xlabel("chip temperature (°C)")
    axes[1].set_ylabel("systematic error, centre ROI (mm)")
    axes[1].set_title("range against temperature")
    axes[1].legend(fontsize=8)
    axes[2].plot(t, [r["amplitude"] for r in rows], "o-")
    axes[2].set_xlabel("time (s)")
    axes[2].set_ylabel("amplitude, centre ROI (DN)")
    axes[2].set_title("amplitude")
    return [("Warm-up", fig_uri(fig), "Range and amplitude from power-on against time and the recorded chip "
             "temperature; the twin has no thermal model (its line: no drift from the first capture).")]


PROCEDURES = [as_procedure(WarmUp)]
