"""``bench photon-transfer``: flat-field and dark captures over a series of integration times,
the EMVA 1288 quantities (``tofhil.eval.calibration.photon_transfer``) with uncertainties,
written as the scene's ``sensor:`` block; the twin's photon-transfer curve beside them.

On the emulated TOFcam635 the bench is a flat field (``configs/bench/tofcam635_flat_field.yaml``
or ``emulator:FILE`` with the same keys): the emulator switches its light on and off. On a real
camera the operator is asked to. The twin's prediction is the sensor block of ``--scene`` (a
flat-field bench file or a scene; default: the emulated bench's own).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from tofhil.app.bench.base import BenchOptions, BenchResult, Figure
from tofhil.app.campaign import CampaignResult, Plan, parse_plan
from tofhil.errors import TofhilError

NAME = "photon-transfer"
SUMMARY = ("flat-field and dark captures over integration times: EMVA 1288 conversion gain, read noise, "
           "full well, dark current, DSNU, PRNU, linearity, as a sensor: block")
#: Exposures (us): flats through the linear range into saturation, darks across the same range.
FLAT_US = (50, 100, 200, 300, 400, 500, 600, 700, 800, 900, 1000, 1200, 1400, 2000, 2400)
DARK_US = (50, 500, 1000, 1500, 2000, 2400)


def make_rig(device: str, opts: BenchOptions) -> Any:
    from tofhil.app.bench.rigs import DeviceRig, EmulatedTofCamRig, flat_field_bench, flat_field_source

    scheme, _, rest = device.partition(":")
    if scheme.startswith("depthai"):
        raise TofhilError(f"photon transfer needs raw taps; {device} delivers depth only", field="--device",
                          expected="a raw-tap camera (emulator, usb, serial:PORT)")
    if scheme == "emulator":
        sensor, light, text = flat_field_bench(rest or None)
        rig = EmulatedTofCamRig(lambda p: flat_field_source(sensor, p), light, seed=opts.seed, scene_text=text,
                                device=device)
        rig.sensor = sensor
        return rig
    return DeviceRig(device, prompt=opts.prompt)


def twin_sensor(rig: Any, opts: BenchOptions) -> Any:
    """The sensor the twin predicts with: ``--scene`` (a bench file or a scene), else the bench's."""
    from tofhil.app.bench.rigs import flat_field_bench

    if opts.scene:
        from tofhil.yamlio import load_yaml_file

        data = load_yaml_file(opts.scene) if Path(opts.scene).is_file() else None
        if isinstance(data, dict) and "flat_field" in data:
            return flat_field_bench(opts.scene)[0]
        from tofhil.sim.scene import load_scene

        return load_scene(opts.scene).sensor
    sensor = getattr(rig, "sensor", None)
    if sensor is None:
        raise TofhilError("the twin needs a sensor block to predict the photon-transfer curve", field="--scene",
                          expected="a scene or flat-field bench file with a sensor: block")
    return sensor


def make_plan(opts: BenchOptions, rig: Any) -> Plan:
    # per frequency: every one the device offers unless one is asked for
    freqs = (opts.extra.get("freqs_hz") or ([opts.mod_freq_hz] if opts.mod_freq_hz else None)
             or list(rig.capabilities.mod_freqs_hz or [None]))
    emulated = "emulator" in rig.capabilities.bench_by
    by = "emulator" if emulated else "prompt"
    amp = getattr(rig, "defaults", {}).get("light_amplitude_dn", 1.0)
    steps: list[dict[str, Any]] = []
    for f in freqs:
        tag = f"{f / 1e6:g}MHz" if f else "default"
        steps.append({"settings": {"mode": "dcs", **({"mod_freq_hz": f} if f else {})}})
        steps.append({"bench": {"light_amplitude_dn": 0.0} if emulated else {"light": "off"}, "by": by,
                      "message": "cover the lens (dark captures)"})
        for t in DARK_US:
            steps.append({"settings": {"integration_time_us": t}})
            steps.append({"capture": {"label": f"dark-{tag}-{t}us", "frames": opts.frames}})
        steps.append({"bench": {"light_amplitude_dn": amp} if emulated else {"light": "on"}, "by": by,
                      "message": "uncover the lens in front of the flat field (flat captures)"})
        for t in FLAT_US:
            steps.append({"settings": {"integration_time_us": t}})
            steps.append({"capture": {"label": f"flat-{tag}-{t}us", "frames": opts.frames}})
    return parse_plan({"name": NAME, "steps": steps}, f"<{NAME} plan>")


def _frames(path: Path) -> tuple[np.ndarray, Any]:
    from tofhil.session import open_session

    with open_session(path) as s:
        taps = np.stack([s.raw_frame(i).taps[0] for i in range(s.n_frames)])
        return taps, s.integration_time_s


def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
    import time

    from tofhil.eval.calibration.photon_transfer import PtcCapture, photon_transfer, predicted_variance

    t0 = time.monotonic()
    sensor = twin_sensor(rig, opts)
    by_freq: dict[str, list[PtcCapture]] = {}
    for label in campaign.captures:
        kind, tag, _ = label.split("-", 2)
        taps, t_int = _frames(campaign.session(label))
        by_freq.setdefault(tag, []).append(PtcCapture(float(t_int), kind == "flat", taps, label))
    results = {tag: photon_transfer(caps, modulation_contrast=sensor.modulation_contrast)
               for tag, caps in by_freq.items()}
    tag0 = next(iter(results))
    ptc = results[tag0]
    truth = {"conversion_gain_dn_per_e": sensor.conversion_gain_dn_per_e, "read_noise_e": sensor.read_noise_e,
             "full_well_e": sensor.full_well_e, "dark_current_e_per_s": sensor.dark_current_e_per_s,
             "dsnu_e": sensor.fixed_pattern.dsnu_e, "prnu": sensor.fixed_pattern.prnu, "linearity_error_pct": 0.0}
    figures = [Figure(name, est.value, est.sigma, predicted=truth[name], predicted_sigma=0.0)
               for name, est in ptc.quantities().items()]
    curves: dict[str, list[dict[str, Any]]] = {"photon_transfer": []}
    for tag, res in results.items():
        diff = res.readout == "differential"
        for c in res.captures:
            pred = float(predicted_variance(sensor, np.array(c.amplitude_dn), np.array(c.integration_time_s),
                                            differential=diff))
            curves["photon_transfer"].append({"frequency": tag, "label": c.label, "flat": c.flat,
                                              "integration_time_s": c.integration_time_s,
                                              "signal_mean_dn": c.mean_dn, "amplitude_dn": c.amplitude_dn,
                                              "variance_dn2": c.var_dn2, "variance_se_dn2": c.var_se_dn2,
                                              "predicted_variance_dn2": pred, "used_in_fit": c.used})
    findings = list(ptc.notes)
    for tag, r in results.items():
        if tag != tag0:
            findings.extend(f"{tag}: {n}" for n in r.notes if not n.startswith("differential taps"))
            k0, k1 = ptc.conversion_gain_dn_per_e, r.conversion_gain_dn_per_e
            z = (k1.value - k0.value) / math.hypot(k0.sigma, k1.sigma)
            findings.append(f"{tag}: conversion gain {k1.value:.4g} +- {k1.sigma:.2g} DN/e, read noise "
                            f"{r.read_noise_e.value:.3g} +- {r.read_noise_e.sigma:.2g} e ({z:+.1f} sigma from {tag0}'s gain)")
    curves["per_tap"] = [{"frequency": tag, **t} for tag, r in results.items() for t in r.fit["per_tap"]]
    for f in figures:
        if f.name == "linearity_error_pct" or not (math.isfinite(f.value) and math.isfinite(f.sigma) and f.sigma > 0):
            continue
        z = (f.value - f.predicted) / f.sigma
        if abs(z) > 3:
            findings.append(f"{f.name}: measured {f.value:.4g} +- {f.sigma:.2g}, the twin's sensor block says "
                            f"{f.predicted:.4g} ({z:+.1f} sigma): the twin's sensor block is wrong there")
    block = ptc.sensor_block(sensor.to_dict())
    out = campaign.out_dir
    import yaml

    (out / "sensor.yaml").write_text(
        "# measured by tofhil bench photon-transfer (EMVA 1288); paste as a scene's sensor: block\n"
        + yaml.safe_dump({"sensor": _plain(block)}, sort_keys=False), encoding="utf-8")
    files = {"sensor": "sensor.yaml"}
    from tofhil.eval.calibration.taps import TapCalibration

    for tag, r in results.items():
        # the tap calibration (tofhil.eval.calibration.taps): per-pixel dark offsets of every tap,
        # per-tap relative gains from each tap's own photon-transfer slope
        g = r.tap_gains()
        if r.dark_offset_dn is not None and g.size == r.dark_offset_dn.shape[0]:
            cal = TapCalibration(r.dark_offset_dn[None], np.broadcast_to(g[None, :, None, None],
                                                                          (1, *r.dark_offset_dn.shape)).copy(),
                                 info={"source": "tofhil bench photon-transfer", "frequency": tag,
                                       "readout": r.readout})
            files[f"tap_calibration_{tag}"] = cal.save(out / f"tap_calibration_{tag}.npz", force=True).name
    res = BenchResult(NAME, rig.device, figures, curves=curves, findings=findings,
                      files=files,
                      details={tag: r.to_dict() for tag, r in results.items()})
    res.plots = lambda: _plots(results, sensor)
    res.seconds["analysis"] = time.monotonic() - t0
    return res


def _plain(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


def _plots(results: dict[str, Any], sensor: Any) -> list[tuple[str, str | None, str]]:
    from tofhil.eval.calibration.photon_transfer import predicted_variance
    from tofhil.eval.reports.html import fig_uri, pyplot

    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), layout="constrained")
    for tag, res in results.items():
        diff = res.readout == "differential"
        fl = [c for c in res.captures if c.flat]
        dk = [c for c in res.captures if not c.flat]
        x = np.array([c.amplitude_dn if diff else c.mean_dn for c in fl])
        ax = axes[0]
        ax.errorbar(x, [c.var_dn2 for c in fl], yerr=[2 * c.var_se_dn2 for c in fl], fmt="o", ms=4,
                    label=f"measured, flat ({tag})")
        used = [c for c in fl if c.used]
        ax.plot([c.amplitude_dn if diff else c.mean_dn for c in used], [c.var_dn2 for c in used], "o", mfc="none",
                ms=9, color="k", label="in the fit")
        xs = np.linspace(0, x.max(), 100)
        ts = np.interp(xs, x, [c.integration_time_s for c in fl])
        ax.plot(xs, predicted_variance(sensor, xs, ts, differential=diff), "-", color="C3", label="twin (sensor block)")
        ax.set_xlabel("signal: modulation amplitude (DN)" if diff else "mean signal (DN)")
        ax.set_ylabel("temporal variance of a tap (DN²)")
        ax.set_title("photon transfer")
        ax.legend(fontsize=8)
        ax = axes[1]
        t = np.array([c.integration_time_s for c in dk]) * 1e6
        ax.errorbar(t, [c.var_dn2 for c in dk], yerr=[2 * c.var_se_dn2 for c in dk], fmt="o", label="measured")
        tt = np.linspace(0, t.max(), 50)
        ax.plot(tt, predicted_variance(sensor, 0 * tt, tt * 1e-6, differential=diff), "-", color="C3", label="twin")
        b, g = res.fit["beta"], res.fit["gamma"]
        ax.plot(tt, b * tt * 1e-6 + g, "--", color="k", label="fit")
        ax.set_xlabel("integration time (µs)")
        ax.set_ylabel("dark temporal variance (DN²)")
        ax.set_title("dark noise vs exposure (read noise, dark current)")
        ax.legend(fontsize=8)
        ax = axes[2]
        tf = np.array([c.integration_time_s for c in fl]) * 1e6
        lp = np.asarray(res.fit["linear_fit"])
        dev = 100 * (x - np.polyval(lp, tf * 1e-6)) / np.polyval(lp, tf * 1e-6)
        ax.plot(tf, np.clip(dev, -1e9, 1e9), "o-", label="deviation from the linear fit")
        ax.axhline(0, color="k", lw=0.6)
        for c, tv, dv in zip(fl, tf, dev):
            if not c.used:
                ax.plot(tv, dv, "x", color="C3", ms=9)
        ax.set_xlabel("integration time (µs)")
        ax.set_ylabel("linearity deviation (%)")
        ax.set_title("linearity (x: saturated / not used)")
        # the scale of the linear range (saturated points would squash it): those beyond are drawn at the edge
        span = max(0.25, 1.5 * float(np.abs(dev[[c.used for c in fl]]).max()))
        for tv, dv in zip(tf, dev):
            if abs(dv) > span:
                ax.annotate(f"{dv:.0f} %", (tv, np.sign(dv) * span * 0.92), color="C3", fontsize=8, ha="center")
        ax.set_ylim(-span, span)
        ax.legend(fontsize=8)
        break  # one frequency per figure row is enough for the page; every frequency is in the JSON
    return [("Photon transfer, dark noise and linearity", fig_uri(fig),
             "Left: each tap's temporal variance against the signal (error bars 2 s.e.), the twin's curve from "
             "its sensor block; middle: dark variance against exposure (slope: dark current; intercept: read "
             "noise); right: the signal's deviation from a straight line (the linearity error).")]
