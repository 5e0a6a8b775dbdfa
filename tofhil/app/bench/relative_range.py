"""``bench relative-range``: the relative-range test of ASTM E2938-15 on an emulated bench.

A sphere target is put at a reference position and at test positions on the same line of sight
(E2938: both points on a line through the instrument's origin, so the origin need not be known
and a constant range offset cancels); several lines of sight cross the view. At each position N
frames; the sphere's centre is fitted to the mean frame (``fit_sphere``). The system's relative
range is the distance between the fitted centres at the reference and at a test position; the
reference instrument's is the distance between the commanded positions (the emulated stage: the
scene's parameters). Relative-range error = the difference; its standard uncertainty from the
jackknife over the frames (reference and test frames paired), expanded with Student's t (95 %);
the twin fits its own frames of the same bench, and predicts the error beside it.
"""

from __future__ import annotations

import math
import time
from typing import Any, Mapping

import numpy as np

from tofhil.app.bench.base import BenchOptions, BenchResult, Figure, acquisition
from tofhil.app.bench.depth import _depth_stack, _nanmean, _rig, _split, _twin_stack, as_procedure
from tofhil.app.campaign import CampaignResult, Plan, parse_plan
from tofhil.errors import TofhilError

SCENE = "range_sphere"
#: The scene parameter the emulated bench moves (and a hidden ``range_scale`` reads as distance).
DEPTH_PARAM = "target_z_m"
#: Ranges (m) along each line of sight: the first is the reference position, the rest the test
#: positions (E2938 puts the second target on the same side of the instrument as the first).
RANGES_M = (1.0, 1.5, 2.0, 2.5)
#: Lines of sight: azimuths about the camera's vertical axis (deg), across the TOFcam635's 50 deg view.
AZIMUTHS_DEG = (0.0, -15.0, 15.0)
#: A sphere fit needs this many valid pixels on the target's cap (fewer: the plan cannot do it).
MIN_CAP_PIXELS = 20
#: Coverage of the expanded uncertainty (two-sided; the factor is Student's t for the frames' dof).
COVERAGE = 0.95


def target_state(azimuth_deg: float, range_m: float) -> dict[str, float]:
    """The sphere's centre ``range_m`` from the camera along the line of sight at ``azimuth_deg``."""
    a = math.radians(azimuth_deg)
    return {"target_x_m": range_m * math.sin(a), "target_y_m": 0.0, DEPTH_PARAM: range_m * math.cos(a)}


def _label(azimuth_deg: float, range_m: float) -> str:
    # (a plan's labels are letters, digits, '-', '_' and '.': the azimuth's sign spelt out)
    return f"az{'m' if azimuth_deg < 0 else ''}{abs(azimuth_deg):g}-{range_m:g}m"


def _positions(opts: BenchOptions) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The plan's ranges and azimuths; a position the bench cannot do names its field."""
    ranges = tuple(float(r) for r in (opts.extra.get("relative_ranges_m") or
                                      (opts.distances_m if opts.distances_m != BenchOptions().distances_m else RANGES_M)))
    az = tuple(float(a) for a in (opts.extra.get("relative_range_azimuths_deg") or AZIMUTHS_DEG))
    if len(ranges) < 2 or len(set(ranges)) != len(ranges):
        raise TofhilError(f"--distances {','.join(f'{r:g}' for r in ranges)}", field="--distances",
                          expected="a reference range and one or more different test ranges (m)")
    for r in ranges:
        if not 0.3 <= r <= 7.0:   # the sphere must stay clear of the camera and within the 20 MHz ambiguity
            raise TofhilError(f"a target at {r:g} m", field="--distances",
                              expected="ranges from 0.3 to 7 m (the emulated stage)")
    for a in az:
        if not abs(a) <= 20.0:    # the sphere must stay in the 50 deg view at every range
            raise TofhilError(f"relative_range_azimuths_deg: {a:g} deg", field="relative_range_azimuths_deg",
                              expected="azimuths within +-20 deg (the TOFcam635's view)")
    return ranges, az


class RelativeRange:
    NAME = "relative-range"
    SUMMARY = ("ASTM E2938 relative range: a sphere at a reference and at test positions on lines of sight across "
               "the view; fitted-centre distances against the stage's, errors with expanded uncertainty beside the "
               "twin's (--distances: reference, then test ranges)")

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, DEPTH_PARAM, RANGES_M[0], scene_default=SCENE,
                    more={"target_x_m": 0.0, "target_y_m": 0.0})

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        ranges, azimuths = _positions(opts)
        if opts.frames < 2:
            raise TofhilError(f"--frames {opts.frames}", field="--frames",
                              expected="2 or more (the uncertainty comes from the frames' spread)")
        first, by = acquisition(opts, rig, 125)
        steps: list[dict[str, Any]] = [first]
        for a in azimuths:
            for i, r in enumerate(ranges):
                role = "reference" if i == 0 else "test"
                steps.append({"bench": target_state(a, r), "by": by,
                              "message": f"sphere target ({role} position) {r:g} m from the camera on the line of "
                                         f"sight {a:+g} deg; measure its centre with the reference instrument"})
                steps.append({"capture": {"label": _label(a, r), "frames": opts.frames}})
        return parse_plan({"name": RelativeRange.NAME, "steps": steps}, f"<{RelativeRange.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        from tofhil.sim.scene import load_scene

        ranges, azimuths = _positions(opts)
        seconds = {"twin": 0.0, "analysis": 0.0}
        fits: dict[str, dict[str, Any]] = {}
        for i, (label, rec) in enumerate(campaign.captures.items()):
            radial, valid, cam, acq = _depth_stack(campaign.session(label))
            params = load_scene(rig.scene, {"params": _split(rec["bench"])[0]}).params
            t0 = time.monotonic()
            fits[label] = {"measured": sphere_centres(radial, valid, cam, params)}
            seconds["analysis"] += time.monotonic() - t0
            t0 = time.monotonic()
            tr, tv = _twin_stack(rig, rec["bench"], acq, opts.frames, opts.seed + 7919 + i, opts)
            fits[label]["twin"] = sphere_centres(tr, tv, cam, params)
            seconds["twin"] += time.monotonic() - t0
        rows, jk = [], []
        for a in azimuths:
            ref = fits[_label(a, ranges[0])]
            for r in ranges[1:]:
                row, j = pair_row(a, ranges[0], r, ref, fits[_label(a, r)])
                rows.append(row)
                jk.append(j)
        res = BenchResult(RelativeRange.NAME, rig.device, [], curves={RelativeRange.NAME: rows}, seconds=seconds)
        worst = max(rows, key=lambda x: abs(x["measured_error_m"]))
        res.figures.append(Figure("range_error_e2938_m", abs(worst["measured_error_m"]), worst["measured_error_m_se"],
                                  abs(worst["twin_error_m"]), worst["twin_error_m_se"],
                                  note=f"the largest over {len(rows)} position pairs: {worst['pair']}"))
        for x in rows:
            res.findings.append(
                f"{x['pair']}: relative range {1e3 * x['measured_range_m']:.1f} mm (reference instrument "
                f"{1e3 * x['true_range_m']:.1f}), error {1e3 * x['measured_error_m']:+.2f} +- "
                f"{1e3 * x['measured_error_m_U']:.2f} mm (U, {100 * COVERAGE:g} %), twin {1e3 * x['twin_error_m']:+.2f} "
                f"+- {1e3 * x['twin_error_m_U']:.2f} mm ({x['agreement']}, {x['z']:+.1f} sigma)")
        res.details["agreement"] = agreement(rows, np.array(jk))
        res.findings.append(res.details["agreement"]["text"])
        res.plots = lambda: _plot(rows)
        return res


def sphere_centres(radial: np.ndarray, valid: np.ndarray, cam: Any, params: Mapping[str, Any]) -> dict[str, Any]:
    """The sphere's centre fitted to the mean frame's cap (pixels within 80 % of its projected
    radius, valid in every frame), and the jackknife's centres (the mean of all frames but one)."""
    from tofhil.eval.metrics.bench import fit_sphere

    c_true = np.array([float(params["target_x_m"]), float(params["target_y_m"]), float(params[DEPTH_PARAM])])
    r_true = float(params["sphere_radius_m"])
    pu, pv = cam.project(c_true[None])[0]
    rad_px = 0.8 * r_true * cam.fx / (c_true[2] - r_true)
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    cap = np.all(valid, axis=0) & ((uu - pu) ** 2 + (vv - pv) ** 2 <= rad_px ** 2)
    if cap.sum() < MIN_CAP_PIXELS:
        raise TofhilError(f"the sphere at {np.linalg.norm(c_true):.2f} m covers {int(cap.sum())} valid pixels",
                          field="--distances", expected=f"ranges where the target covers >= {MIN_CAP_PIXELS} pixels "
                          "(closer, or a bigger sphere: sphere_radius_m)")
    n = radial.shape[0]
    mean = _nanmean(radial, valid)
    rest = [(mean[cap] * n - radial[k][cap]) / (n - 1) for k in range(n)]
    fit = fit_sphere(cam.rays[cap] * mean[cap][:, None], radius=r_true)
    return {"centre": np.asarray(fit.centre, float), "true": c_true, "frames": n, "points": int(cap.sum()),
            "jackknife": [np.asarray(fit_sphere(cam.rays[cap] * x[:, None], radius=r_true).centre, float)
                          for x in rest]}


def _error(ref: Mapping[str, Any], test: Mapping[str, Any]) -> tuple[float, float, float, np.ndarray]:
    """System's relative range, its error against the commanded positions' distance, the error's
    standard uncertainty (jackknife over paired frames) and the jackknife's errors."""
    true = float(np.linalg.norm(test["true"] - ref["true"]))
    got = float(np.linalg.norm(test["centre"] - ref["centre"]))
    jk = np.array([np.linalg.norm(t - r) for r, t in zip(ref["jackknife"], test["jackknife"])])
    n = len(jk)
    se = float(math.sqrt((n - 1) / n * np.sum((jk - jk.mean()) ** 2)))
    return got, got - true, se, jk - true


def pair_row(azimuth_deg: float, r_ref: float, r_test: float, ref: Mapping[str, Any],
             test: Mapping[str, Any]) -> tuple[dict[str, Any], np.ndarray]:
    """One reference-test pair: the measured and the twin's relative range, error, standard and
    expanded uncertainty, and their agreement (z of the difference); and the jackknife's
    measured-minus-twin errors (frame k left out of every capture)."""
    from scipy.stats import t as student

    row: dict[str, Any] = {"pair": f"{_label(azimuth_deg, r_ref)} -> {_label(azimuth_deg, r_test)}",
                           "azimuth_deg": azimuth_deg, "reference_range_m": r_ref, "test_range_m": r_test,
                           "true_range_m": float(np.linalg.norm(test["measured"]["true"] - ref["measured"]["true"])),
                           "points": min(test["measured"]["points"], ref["measured"]["points"])}
    jks = {}
    for who in ("measured", "twin"):
        got, err, se, jks[who] = _error(ref[who], test[who])
        dof = len(jks[who]) - 1
        row.update({f"{who}_range_m": got, f"{who}_error_m": err, f"{who}_error_m_se": se, f"{who}_dof": dof,
                    f"{who}_error_m_U": float(student.ppf(0.5 + COVERAGE / 2, max(dof, 1))) * se})
    z = (row["measured_error_m"] - row["twin_error_m"]) / math.hypot(row["measured_error_m_se"], row["twin_error_m_se"])
    row["z"] = z
    row["agreement"] = "agrees with the twin" if abs(z) < 3 else "differs from the twin"
    n = min(len(jks["measured"]), len(jks["twin"]))
    return row, jks["measured"][:n] - jks["twin"][:n]


def agreement(rows: list[dict[str, Any]], jk: np.ndarray) -> dict[str, Any]:
    """How the measured errors beyond the twin's grow with the range difference: a weighted line
    through the origin, ``k * delta_range`` (a modulation-frequency error k reads every length
    (1 + k) times; a constant range offset cancels in a relative range, E2938's point). The
    slope's standard error is the jackknife's over the frames (``jk [pairs, frames]``: the pairs
    of a line of sight share its reference capture, so their errors are correlated)."""
    from scipy.stats import norm
    from scipy.stats import t as student

    from tofhil.app.bench.depth import FALSE_ALARM, _chi2_sf

    # pair by pair: each z is a t statistic (jackknife standard errors over few frames), mapped to
    # a normal quantile first so that few frames do not make the chi-square test cry wolf
    nz = [float(norm.isf(student.sf(r["z"], max(min(r["measured_dof"], r["twin_dof"]), 1)))) for r in rows]
    chi2 = float(np.sum(np.square(nz)))
    p_pairs = _chi2_sf(chi2, len(rows))
    diff = np.array([r["measured_error_m"] - r["twin_error_m"] for r in rows])
    se = np.array([math.hypot(r["measured_error_m_se"], r["twin_error_m_se"]) for r in rows])
    dr = np.array([r["true_range_m"] for r in rows])
    w = 1.0 / se ** 2
    k = float(np.sum(w * dr * diff) / np.sum(w * dr ** 2))
    kj = (w * dr) @ jk / np.sum(w * dr ** 2)
    n = jk.shape[1]
    sk = float(math.sqrt((n - 1) / n * np.sum((kj - kj.mean()) ** 2)))
    # a jackknife over n frames: the ratio is a t statistic with n - 1 dof
    nu = n - 1
    p = float(2 * student.sf(abs(k) / sk, max(nu, 1)))
    text = (f"the relative-range error beyond the twin's grows by {k * 1e3:+.2f} +- {sk * 1e3:.2f} mm per metre of "
            "range difference " + (f"(beyond noise, p = {p:.1e}: a range scale of {100 * k:+.2f} %, e.g. a "
                                   "modulation-frequency error)" if p < FALSE_ALARM else f"(within noise, p = {p:.2f})"))
    text += ("; pair by pair the errors " + ("agree with the twin's" if p_pairs >= FALSE_ALARM else "differ from the twin's")
             + f" (chi2 {chi2:.1f} for {len(rows)}, p = {p_pairs:.2g})")
    return {"per_m": k, "per_m_se": sk, "dof": nu, "p": p, "chi2": chi2, "pairs": len(rows), "p_pairs": p_pairs,
            "text": text}


def _plot(rows: list[dict[str, Any]]) -> list[tuple[str, str | None, str]]:
    from tofhil.eval.reports.html import fig_uri, pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.2), layout="constrained")
    az = sorted({r["azimuth_deg"] for r in rows})
    span = max(r["true_range_m"] for r in rows)
    for j, a in enumerate(az):
        at = sorted((r for r in rows if r["azimuth_deg"] == a), key=lambda r: r["true_range_m"])
        x = np.array([r["true_range_m"] for r in at]) + 0.01 * span * (j - (len(az) - 1) / 2)
        ax.errorbar(x, [1e3 * r["measured_error_m"] for r in at], yerr=[1e3 * r["measured_error_m_U"] for r in at],
                    fmt="o", color=f"C{j}", label=f"line of sight {a:+g} deg: measured (U, {100 * COVERAGE:g} %)")
        ax.plot(x, [1e3 * r["twin_error_m"] for r in at], "x", color=f"C{j}", ms=8)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("reference instrument's relative range (m)")
    ax.set_ylabel("relative-range error (mm)")
    ax.legend(fontsize=8)
    return [("Relative-range error (ASTM E2938)", fig_uri(fig),
             "Each test position's relative-range error against the reference position on its line of sight "
             "(markers, expanded uncertainty) and the twin's prediction for the same bench (x).")]


PROCEDURES = [as_procedure(RelativeRange)]
