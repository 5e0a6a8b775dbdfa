"""``bench interference``: a second ToF camera's modulated light on the same target, the depth
error and precision with and without it, beside the twin's.

The second camera's light is extra light on the target: its mean irradiance ``E2`` (W/m^2 on
the target, measured with a radiometer, like a lamp's) adds offset and shot noise exactly as
ambient light does (the ``ambient`` effect, known to the twin). Its modulation correlates with
the device's demodulation at ``f1`` over the integration time ``T`` as

    (1/T) int_0^T exp(i (2 pi df t + psi)) dt = sinc(df T) exp(i (psi + pi df T)),   df = f2 - f1

(``np.sinc(x) = sin(pi x) / (pi x)``): at the same frequency (df = 0) the second camera adds a
phasor of its own phase ``psi`` (its clock against the device's) to the device's signal, of
the size its mean light would have if it were the device's own (``P2``, the pixel's power from
``E2``, times the same modulation contrast and waveform coefficient); at another frequency
(``df T`` >> 1, e.g. 1 MHz away at 125 us: df T = 125, an integer: exactly 0) it averages to
offset only. Unmodulated light (``f2 = 0``) is the far case. With ``r = g P2 / |S|`` (``g`` the
factor above) and ``psi' = psi + pi df T`` the phase reads ``atan2(r sin psi', 1 + r cos psi')``
more, a range error ``c / (4 pi f1)`` times that; the amplitude is ``|1 + r exp(i psi')|`` times
the device's own.

Modelled: the second camera's light as a uniform irradiance on the target (a floodlight from
beside the device: its path is the device's own), its phase ``psi`` held for a capture (two
cameras on one clock, or a capture shorter than their drift). Not modelled: the phase drifting
from frame to frame (two free-running clocks at the same nominal frequency: the error then
averages out of the mean and adds to the random error), the second camera's own beam shape,
position and path length, and its harmonics (its fundamental only).
"""

from __future__ import annotations

import math
import time
from typing import Any, Mapping

import numpy as np

from tofhil import C_M_PER_S
from tofhil.app.bench.base import BenchOptions, BenchResult, Figure, acquisition
from tofhil.app.bench.depth import (
    DISTANCE_PARAM, INTERFERER_FREQ, INTERFERER_PHASE, INTERFERER_W, _bench_effects, _depth_stack, _rig, agreement, as_procedure, twin_depths, twin_scene,
)
from tofhil.app.campaign import CampaignResult, Plan, parse_plan

#: The second camera's irradiance on the target by default (W/m^2): about a tenth of the
#: emulated TOFcam635's own at 1 m (2 W in a cos^2 beam: 3 W / (2 pi m^2) on the axis).
DEFAULT_W_M2 = 0.1


def coherent_factor(f1_hz: float, f2_hz: float, integration_time_s: float) -> complex:
    """What of the second camera's modulation survives the device's demodulation over one
    integration: ``sinc(df T) exp(i pi df T)`` (1 at the same frequency, 0 when ``df T`` is a
    non-zero integer); unmodulated light (``f2 = 0``) has none."""
    if f2_hz <= 0:
        return 0j
    x = (f2_hz - f1_hz) * integration_time_s
    return complex(np.sinc(x) * np.exp(1j * math.pi * x))


def predicted_range_error_m(r: np.ndarray | float, psi_rad: float, freq_hz: float) -> np.ndarray:
    """Closed form: the range error of a pixel whose own signal gets a phasor ``r`` times its
    size at phase ``psi`` relative to its own (``r`` may carry the complex coherent factor)."""
    z = 1.0 + np.asarray(r) * np.exp(1j * psi_rad)
    return C_M_PER_S / (4 * math.pi * freq_hz) * np.angle(z)


def _phasor_of(state: Mapping[str, Any], freq_hz: float, integration_time_s: float) -> complex:
    """``g exp(i psi)`` of the bench state (0 when no second camera or none that correlates)."""
    if float(state.get(INTERFERER_W, 0.0) or 0.0) <= 0:
        return 0j
    g = coherent_factor(freq_hz, float(state.get(INTERFERER_FREQ, 0.0)), integration_time_s)
    return g * complex(np.exp(1j * math.radians(float(state.get(INTERFERER_PHASE, 0.0)))))


# --------------------------------------------------------------------------- the emulator's source
class InterferedSource:
    """The emulated TOFcam635's frame source with the second camera's modulation added: ``lit``
    renders the bench with the second camera's mean light (as ambient light), ``dark`` without;
    their offset difference is the second camera's light at the pixel, ``B2`` (DN), its phasor
    ``m a1 B2 g exp(i (phi + psi))`` (``m`` the modulation contrast, ``a1`` the waveform's
    fundamental coefficient, ``phi`` the pixel's own phase: the light takes the device's path)."""

    def __init__(self, lit: Any, dark: Any, state: Mapping[str, Any], contrast: float) -> None:
        self.lit, self.dark, self.state, self.contrast = lit, dark, dict(state), float(contrast)
        self.camera = lit.camera
        self.rendered_by = (lit, dark)
        self.description = f"{lit.description}, a second camera's light"
        self._ref: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def _reference(self, freq_hz: float, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from tofhil.demod import offset, phasor
        from tofhil.frame_source import REFERENCE_INTEGRATION_TIME_S as TREF

        key = float(freq_hz)
        if key not in self._ref:
            lit = self.lit.taps(freq_hz, TREF, theta).astype(np.float64)
            dark = self.dark.taps(freq_hz, TREF, theta).astype(np.float64)
            s = phasor(lit, theta)
            self._ref[key] = (s / np.maximum(np.abs(s), 1e-12), offset(lit) - offset(dark))
        return self._ref[key]

    def taps(self, freq_hz: float, integration_time_s: float, theta_rad: Any) -> np.ndarray:
        from tofhil.frame_source import REFERENCE_INTEGRATION_TIME_S as TREF

        theta = np.asarray(theta_rad, dtype=np.float64)
        c = self.lit.taps(freq_hz, integration_time_s, theta).astype(np.float64)
        k = _phasor_of(self.state, freq_hz, integration_time_s)
        if k == 0:
            return c.astype(np.float32)
        unit, b2 = self._reference(freq_hz, theta)
        s2 = self.contrast * b2 * (integration_time_s / TREF) * k * unit
        return (c + np.real(s2[None] * np.exp(-1j * theta)[:, None, None])).astype(np.float32)

    def signal(self, freq_hz: float) -> Any:
        return self.lit.signal(freq_hz)

    def noise_model(self) -> Any:
        return self.lit.noise_model()

    def scene_text(self) -> str:
        return self.lit.scene_text()


def device_contrast(scene: Any) -> float:
    """Modulation contrast times the waveform's fundamental (what turns a light's mean power
    into its tap amplitude, for the device's own light and the second camera's alike)."""
    from tofhil.sim.sensor import waveform_from_scene

    return float(scene.sensor.modulation_contrast) * abs(waveform_from_scene(scene)[1])


# --------------------------------------------------------------------------- the twin's frames
def interfered_frames(scene: Any, effects: Mapping[str, Any] | None, state: Mapping[str, Any], frames: int,
                      seed: int, noise: bool = True) -> list[Any]:
    """Raw frames of ``scene`` (its ``effects`` including the second camera's mean light as
    ambient light) with the second camera's phasor added to the light on the sensor: ``P2 g
    exp(i (arg S + psi))`` at the fundamental, ``P2`` the pixel's power from ``E2`` (the
    ambient-light power the second camera's irradiance adds)."""
    from tofhil.sim.twin import Twin, signal_from_render, with_readout

    twin = Twin(scene, effects=effects)     # None: the scene's own block
    eff = dict(twin.base_effects)
    scene2, result = twin.render()
    sig = signal_from_render(scene2, result, twin.base_effects, twin.config)
    f = float(sig.freq_hz[0])
    k = _phasor_of(state, f, float(twin.config.integration_time_s))
    if k != 0:
        e2 = float(state.get(INTERFERER_W, 0.0))
        amb = dict(eff.get("ambient", {}))
        without = {**eff, "ambient": {**amb, "irradiance_w_m2": float(amb.get("irradiance_w_m2", 0.0)) - e2}}
        p2 = np.asarray(sig.ambient_w) - np.asarray(twin.signal(without).ambient_w)
        sig = sig.copy()
        h1 = sig.harmonics.index(1)
        s1 = sig.phasor_w[:, h1]
        for i, fi in enumerate(sig.freq_hz):
            ki = _phasor_of(state, float(fi), float(twin.config.integration_time_s))
            sig.phasor_w[i, h1] = s1[i] + p2 * ki * np.exp(1j * np.angle(s1[i]))
    sensor = twin.sensor(getattr(result, "camera", None) or scene2.camera)
    return [with_readout(sensor.expose(sig, seed=seed, frame_index=i, noise=noise), scene2, twin.base_effects,
                         twin.config) for i in range(frames)]


class InterferedHostScene:
    """What the DepthAI host pipeline sends with a second camera on the target: the twin's
    frames (:func:`interfered_frames`) of the bench scene with its hidden truth, demodulated by
    the core, as :class:`tofhil.sim.sources.TwinScene` sends them."""

    def __init__(self, scene_path: str, effects: Mapping[str, Any] | None, state: Mapping[str, Any],
                 realisations: int, seed: int) -> None:
        from tofhil.sim.sources import TwinScene

        self._base = TwinScene(scene=scene_path, realisations=realisations, seed=seed)
        self.effects, self.state = effects, dict(state)
        self.fps, self.drop_amplitude_of, self.n_frames = self._base.fps, (), None

    def camera_model(self) -> Any:
        return self._base.camera_model()

    def render_frames(self, camera: Any) -> list[dict[str, np.ndarray]]:
        from tofhil.demod import distance_to_phase
        from tofhil.depth import depth_from_raw
        from tofhil.sim.scene import load_scene

        out = []
        scene = load_scene(self._base.scene)
        for raw in interfered_frames(scene, self.effects, self.state, self._base.realisations, self._base.seed):
            d = depth_from_raw(raw)
            radial = np.where(d.valid, d.radial_m, 0.0)
            out.append({"radial_m": radial, "z_m": radial * camera.ray_z, "amplitude": np.nan_to_num(d.amplitude),
                        "intensity": np.nan_to_num(d.intensity),
                        "phase": distance_to_phase(radial, float(raw.freq_hz[0]))})
        return out


# --------------------------------------------------------------------------- the procedure
class Interference:
    NAME = "interference"
    SUMMARY = ("a second ToF camera's light on the target (the same modulation frequency at four phases, another "
               "frequency, unmodulated): depth error and precision with and without it, beside the twin's")

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, DISTANCE_PARAM, 1.0,
                    more={INTERFERER_W: 0.0, INTERFERER_FREQ: 0.0, INTERFERER_PHASE: 0.0})

    @staticmethod
    def device_freq_hz(rig: Any) -> float:
        """A depth-only device's modulation frequency: its bench scene's (the emulation renders
        it), else the DepthAI's base frequency (80 MHz)."""
        if getattr(rig, "scene", None) is not None:
            from tofhil.sim.scene import load_scene

            return float(load_scene(rig.scene).sensor.freq_hz[0])
        return 80e6

    @staticmethod
    def cases(opts: BenchOptions, f1_hz: float) -> list[tuple[str, float, float, float]]:
        """``(label, irradiance, frequency, phase)``: none, the same frequency at 0/90/180/270
        degrees, 1 MHz away, unmodulated."""
        e2 = float(opts.extra.get("interferer_w_m2", DEFAULT_W_M2))
        out = [("none", 0.0, 0.0, 0.0)]
        out += [(f"same{p}", e2, f1_hz, float(p)) for p in (0, 90, 180, 270)]
        out += [("other", e2, f1_hz + 1e6, 0.0), ("cw", e2, 0.0, 0.0)]
        return out

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        first, by = acquisition(opts, rig, 125)
        f1 = float(first["settings"].get("mod_freq_hz") or opts.mod_freq_hz or Interference.device_freq_hz(rig))
        d = float(opts.extra.get("interference_distance_m", 1.0))
        steps: list[dict[str, Any]] = [first]
        for label, e2, f2, psi in Interference.cases(opts, f1):
            what = ("no second camera" if e2 == 0 else
                    f"a second camera lighting the target with {e2:g} W/m² "
                    + (f"modulated at {f2 / 1e6:g} MHz, phase {psi:g} deg" if f2 > 0 else "unmodulated"))
            steps.append({"bench": {DISTANCE_PARAM: d, INTERFERER_W: e2, INTERFERER_FREQ: f2, INTERFERER_PHASE: psi},
                          "by": by, "message": f"flat target at {d:g} m; {what}"})
            steps.append({"capture": {"label": label, "frames": opts.frames}})
        return parse_plan({"name": Interference.NAME, "steps": steps}, f"<{Interference.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        return analyse_interference(campaign, rig, opts)


def _twin_frames(rig: Any, state: Mapping[str, Any], acq: Mapping[str, Any], frames: int, seed: int,
                 opts: BenchOptions) -> tuple[np.ndarray, np.ndarray]:
    from tofhil.depth import depth_from_raw

    scene = twin_scene(rig, state, acq)
    known = _bench_effects(rig.scene, state, opts, 0.0, hidden=False) or None
    return twin_depths(rig, [depth_from_raw(r) for r in interfered_frames(scene, known, state, frames, seed)],
                       acq.get("depth_kind", "z"))


def analyse_interference(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
    """Per capture the centre ROI's systematic and random error beside the twin's; the change
    each second camera makes against the capture without one (the interference error and the
    noise factor), measured and predicted."""
    from tofhil.eval.metrics.bench import centre_roi, depth_stack_stats

    seconds = {"twin": 0.0, "analysis": 0.0}
    rows: list[dict[str, Any]] = []
    twin_ok = getattr(rig, "scene", None) is not None
    for i, (label, rec) in enumerate(campaign.captures.items()):
        t0 = time.monotonic()
        state = rec["bench"]
        radial, valid, cam, acq = _depth_stack(campaign.session(label))
        roi = opts.roi or centre_roi(cam.shape)
        truth = float(state[DISTANCE_PARAM]) / cam.ray_z
        m = depth_stack_stats(radial, valid, truth, roi)
        row = {"label": label, "index": i, "interferer_w_m2": float(state.get(INTERFERER_W, 0.0)),
               "interferer_freq_hz": float(state.get(INTERFERER_FREQ, 0.0)),
               "interferer_phase_deg": float(state.get(INTERFERER_PHASE, 0.0)), "distance_m": float(state[DISTANCE_PARAM]),
               **{f"measured_{k}": v for k, v in m.to_dict().items()}}
        seconds["analysis"] += time.monotonic() - t0
        if twin_ok:
            t0 = time.monotonic()
            tr, tv = _twin_frames(rig, state, acq, max(opts.frames, 2), opts.seed + 6007 + i, opts)
            row.update({f"twin_{k}": v for k, v in depth_stack_stats(tr, tv, truth, roi).to_dict().items()})
            seconds["twin"] += time.monotonic() - t0
        rows.append(row)
    res = BenchResult(Interference.NAME, rig.device, [], curves={Interference.NAME: rows}, seconds=seconds)
    base = next((r for r in rows if r["interferer_w_m2"] == 0), None)
    if base is None:
        res.findings.append("no capture without the second camera: nothing to compare with")
        return res
    for r in rows:
        for pre in ("measured", "twin") if twin_ok else ("measured",):
            r[f"{pre}_interference_error_m"] = r[f"{pre}_systematic_m"] - base[f"{pre}_systematic_m"]
            r[f"{pre}_interference_error_se_m"] = math.hypot(r[f"{pre}_systematic_se_m"], base[f"{pre}_systematic_se_m"])
            a, b = base[f"{pre}_random_m"], r[f"{pre}_random_m"]
            r[f"{pre}_noise_factor"] = b / a if a > 0 else math.nan
            ra = base[f"{pre}_random_var_se_m2"] / (2 * a * a) if a > 0 else math.nan
            rb = r[f"{pre}_random_var_se_m2"] / (2 * b * b) if b > 0 else math.nan
            r[f"{pre}_noise_factor_se"] = r[f"{pre}_noise_factor"] * math.hypot(ra, rb)
    others = [r for r in rows if r is not base and math.isfinite(r["measured_interference_error_m"])]
    if others:
        w = max(others, key=lambda r: abs(r["measured_interference_error_m"]))
        res.figures.append(Figure("interference_error_m", abs(w["measured_interference_error_m"]),
                                  w["measured_interference_error_se_m"],
                                  abs(w.get("twin_interference_error_m", math.nan)),
                                  w.get("twin_interference_error_se_m", math.nan), note=f"capture {w['label']}"))
        n = max(others, key=lambda r: r["measured_noise_factor"])
        res.figures.append(Figure("interference_noise_factor", n["measured_noise_factor"], n["measured_noise_factor_se"],
                                  n.get("twin_noise_factor", math.nan), n.get("twin_noise_factor_se", math.nan),
                                  note=f"capture {n['label']}"))
    for r in others:
        twin = (f", twin {1e3 * r['twin_interference_error_m']:+.1f} mm and x {r['twin_noise_factor']:.2f}"
                if twin_ok else "")
        res.findings.append(f"{r['label']}: the second camera moves the range by {1e3 * r['measured_interference_error_m']:+.1f} "
                            f"+- {1e3 * r['measured_interference_error_se_m']:.1f} mm and the random error x "
                            f"{r['measured_noise_factor']:.2f}{twin}")
    if twin_ok:
        res.details["agreement"] = agreement(rows, "index")
        res.findings.extend(res.details["agreement"]["findings"])
    if opts.extra.get("diagnose"):
        res.findings.append("--diagnose: not run here (the twin's scene has no second camera; the diagnosis would "
                            "name its light as something else)")
    res.plots = lambda: _plots(rows, twin_ok)
    return res


def _plots(rows: list[dict[str, Any]], twin: bool) -> list[tuple[str, str | None, str]]:
    from tofhil.eval.reports.html import fig_uri, pyplot

    plt = pyplot()
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), layout="constrained")
    for ax, key, se_key, title, unit in ((axes[0], "interference_error_m", "interference_error_se_m",
                                          "range change against no second camera", 1e3),
                                         (axes[1], "noise_factor", "noise_factor_se", "random error / without", 1.0)):
        m = np.array([r.get(f"measured_{key}", np.nan) for r in rows]) * unit
        ax.errorbar(x - 0.1, m, yerr=2 * unit * np.nan_to_num([r.get(f"measured_{se_key}", 0.0) for r in rows]),
                    fmt="o", label="measured (2 s.e.)")
        if twin:
            p = np.array([r.get(f"twin_{key}", np.nan) for r in rows]) * unit
            ax.errorbar(x + 0.1, p, yerr=2 * unit * np.nan_to_num([r.get(f"twin_{se_key}", 0.0) for r in rows]),
                        fmt="s", color="C3", label="twin (2 s.e.)")
        ax.set_xticks(x)
        ax.set_xticklabels([r["label"] for r in rows])
        ax.set_ylabel("mm" if unit != 1.0 else "factor")
        ax.set_title(title)
        ax.legend(fontsize=8)
    return [("A second camera's light on the target", fig_uri(fig),
             "Per capture (same frequency at 0/90/180/270 degrees, 1 MHz away, unmodulated), the centre ROI's range "
             "change and random-error factor against the capture without a second camera, beside the twin's.")]


PROCEDURES = [as_procedure(Interference)]
