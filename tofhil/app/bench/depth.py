"""Depth procedures (accuracy and precision against distance, ambient light, flatness and fill
rate) and what the other depth-based families (``scattering``, ``spheres``, ``warmup``) share:
the emulated benches of a scene, reading captures, the twin's frames for the same settings,
``analyse_series`` along a bench parameter and the agreement tests.

``accuracy-vs-distance``: a flat target (a wall) perpendicular to the optical axis at a series
of distances, N frames each. Systematic error = the mean of N frames minus the ground truth
(the plane's radial distance ``D / ray_z``), random error = the temporal standard deviation;
on a centre ROI and over the whole field (the median pixel). The twin renders the same scene
with the same settings (frequency, exposure, camera) and noise, and gives the same figures:
its prediction band. Where measured and predicted disagree beyond noise (a chi-square test at
a 1 % false-alarm rate), the difference against distance is fitted by the range errors a
camera has -- a constant offset (an electronic delay), one growing with distance (a
modulation-frequency error) -- and the one the data need is named.

``ambient``: the same along the ambient light on the target, and the noise factor.

``flatness``: one capture (one frame is enough; frames >= 2 add the precision) of a flat
target: the RMS and peak-to-valley residual of a fitted plane, and the fill rate, on a region
(``--roi``; default the centre fifth). Runs on recorded sessions (``replay:S.h5``), e.g. the
real captures imported with ``tofhil import``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, Mapping

import numpy as np

from tofhil.app.bench.base import BenchOptions, BenchResult, Figure, acquisition
from tofhil.app.campaign import CampaignResult, Plan, parse_plan
from tofhil.errors import TofhilError

#: Chi-square tests' false-alarm rate (agreement with the twin, the choice of a cause).
FALSE_ALARM = 0.01
DEFAULT_SCENE = "wall"
DISTANCE_PARAM = "wall_distance_m"


# --------------------------------------------------------------------------- emulated benches
def _bench_scene_file(scene: str, params: Mapping[str, Any], effects: Mapping[str, Any] | None,
                      work: Path, device_overrides: Mapping[str, Any] | None = None) -> Path:
    """The bench's scene in the state ``params`` (with ``effects`` as its own, hidden from the
    twin) as a file, for the emulators that load scenes by path."""
    import copy
    import hashlib
    import json

    from tofhil.sim.scene import load_scene, scene_to_yaml

    over: dict[str, Any] = {"params": dict(params), **copy.deepcopy(dict(device_overrides or {}))}
    if effects:
        over["effects"] = dict(effects)
    key = hashlib.sha256(json.dumps([scene, over], sort_keys=True, default=str).encode()).hexdigest()[:12]
    work.mkdir(parents=True, exist_ok=True)
    path = work / f"bench-{key}.yaml"
    if not path.exists():
        path.write_text(scene_to_yaml(load_scene(scene, over)), encoding="utf-8")
    return path


def hidden_effects(hidden: Mapping[str, Any], distance_m: float) -> dict[str, Any]:
    """The emulator's hidden truth at one distance: ``emulator: true`` the emulated camera's
    own (stray light, wiggling, fixed pattern: docs/drivers.md), ``hidden`` effects as given, and
    ``range_scale: EPS`` as a range error growing with distance (``d -> d (1 + EPS)``, as a
    modulation-frequency error makes it): a ``range_offset`` of optical path ``2 EPS D``."""
    out: dict[str, Any] = {}
    if hidden.get("emulator"):  # the emulated camera's own hidden truth (tofhil capture --device emulator)
        from tofhil.sim.sources import HIDDEN_TRUTH_EFFECTS

        out.update({k: dict(v) for k, v in HIDDEN_TRUTH_EFFECTS.items()})
    out.update({k: dict(v) for k, v in hidden.items() if k not in ("range_scale", "emulator", THERMAL, FREQ_ERROR)})
    eps = float(hidden.get("range_scale", 0.0))
    if eps:
        prev = float(out.get("range_offset", {}).get("path_m", 0.0))
        out["range_offset"] = {"path_m": prev + 2.0 * eps * distance_m}
    return out


def _work_dir(opts: BenchOptions) -> Path:
    work = opts.extra.get("work_dir")
    if work is None:
        import tempfile

        work = tempfile.mkdtemp(prefix="tofhil-bench-")
        opts.extra["work_dir"] = work
    return Path(work)


#: A hidden truth of the warm-up procedure: the range drifting with the chip temperature (m/degC).
THERMAL = "thermal_drift_m_per_c"
#: A hidden truth of the emulated TOFcam635: its modulation frequency is ``1 + K`` times the one it
#: demodulates with, so every path (every pixel, every bounce) reads ``1 + K`` times its length:
#: a range scale over the whole volume (``range_scale`` is an offset at the bench's distance).
FREQ_ERROR = "mod_freq_error"
#: Bench parameters that are not the scene's own ``params:``: the ambient light on the target
#: (W/m^2, the ``ambient`` effect: a lamp or the sun, known to the twin, not hidden).
AMBIENT = "ambient_w_m2"
#: A second ToF camera lighting the target (``bench interference``): its mean irradiance on the
#: target (W/m^2), its modulation frequency (Hz, 0 unmodulated) and its phase against the
#: device's (degrees). Its mean light is ambient light to the twin; its modulation is added by
#: ``tofhil.app.bench.interference``.
INTERFERER_W = "interferer_w_m2"
INTERFERER_FREQ = "interferer_freq_hz"
INTERFERER_PHASE = "interferer_phase_deg"
_NOT_SCENE = (AMBIENT, INTERFERER_W, INTERFERER_FREQ, INTERFERER_PHASE)


def _split(state: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """A bench state -> the scene's parameters and the bench's known effects (the ambient light,
    a second camera's mean light among it)."""
    params = {k: v for k, v in state.items() if k not in _NOT_SCENE}
    amb = float(state.get(AMBIENT, 0.0) or 0.0) + float(state.get(INTERFERER_W, 0.0) or 0.0)
    return params, ({"ambient": {"irradiance_w_m2": amb}} if amb > 0 else {})


def _interfered(state: Mapping[str, Any]) -> bool:
    return float(state.get(INTERFERER_W, 0.0) or 0.0) > 0 and float(state.get(INTERFERER_FREQ, 0.0) or 0.0) > 0


def _rig(device: str, opts: BenchOptions, param: str, default: float, *, scene_default: str = DEFAULT_SCENE,
         more: Mapping[str, float] | None = None) -> Any:
    from tofhil.app.bench.rigs import DeviceRig, EmulatedDepthAIRig, EmulatedTofCamRig
    from tofhil.sim.scene import load_scene

    scheme, _, rest = device.partition(":")
    scene = opts.scene or (rest if scheme in ("emulator", "depthai-sim") and rest else scene_default)
    work = _work_dir(opts)
    defaults = {param: default, AMBIENT: 0.0, **(more or {})}

    def twin_text(state: Mapping[str, Any]) -> str:
        """What a session records as its scene: the twin's (the bench's known light, no hidden truth)."""
        from tofhil.sim.scene import scene_to_yaml

        params, _ = _split(state)
        over: dict[str, Any] = {"params": params}
        known = _bench_effects(scene, state, opts, 0.0, hidden=False)
        if known:
            over["effects"] = known
        return scene_to_yaml(load_scene(scene, over))

    if scheme == "emulator":
        from tofhil.sim.sources import TOFCAM635_OVERRIDES, SimulatedSource

        holder: dict[str, Any] = {}

        def simulated(path: Path, state: Mapping[str, Any]) -> Any:
            src = SimulatedSource(path, effects=_bench_effects(scene, state, opts, float(state[param])))
            if opts.hidden.get(FREQ_ERROR):
                from tofhil.app.bench.rigs import FrequencyError

                src = FrequencyError(src, float(opts.hidden[FREQ_ERROR]))
            return src

        def source(p: Mapping[str, Any]) -> Any:
            params, _ = _split(p)
            path = _bench_scene_file(scene, params, None, work, TOFCAM635_OVERRIDES)
            src = simulated(path, p)
            if _interfered(p):  # a second camera's modulation on top of its mean light
                from tofhil.app.bench.interference import InterferedSource, device_contrast

                dark = {k: v for k, v in p.items() if k != INTERFERER_W}
                src = InterferedSource(src, simulated(path, dark), p, device_contrast(src.scene))
            if opts.hidden.get(THERMAL):
                from tofhil.app.bench.rigs import ThermalDrift

                # the emulator's chip temperature when each frame is taken (it starts at 31 degC)
                src = ThermalDrift(src, lambda: holder["rig"].emulator.temperature_c(), opts.hidden[THERMAL], 31.0)
            return src

        rig = EmulatedTofCamRig(source, defaults, seed=opts.seed, scene_text=twin_text, device=device)
        holder["rig"] = rig
    elif scheme == "depthai-sim":
        if opts.hidden.get(THERMAL):
            raise TofhilError(f"--hidden {THERMAL}: the DepthAI emulation reports no temperature", field="--hidden",
                              expected="the emulated TOFcam635 (emulator) for a thermal drift")
        if opts.hidden.get(FREQ_ERROR):
            raise TofhilError(f"--hidden {FREQ_ERROR}: the DepthAI emulation sends depth, not the light it demodulates",
                              field="--hidden", expected="the emulated TOFcam635 (emulator) for a modulation-frequency "
                              "error, or range_scale=EPS")
        from tofhil.sim.sources import TwinScene

        def host(p: Mapping[str, Any]) -> Any:
            d = float(p[param])
            params, _ = _split(p)
            path = _bench_scene_file(scene, params, _bench_effects(scene, p, opts, d) or None, work)
            # every bench state its own noise (a stable hash of the state: distances, ambient light,
            # a second camera, the sphere bar's position ...)
            seed = opts.seed + _state_seed(p)
            if _interfered(p):
                from tofhil.app.bench.interference import InterferedHostScene

                return InterferedHostScene(str(path), None, p, opts.frames, seed)
            return TwinScene(scene=str(path), realisations=opts.frames, seed=seed)

        rig = EmulatedDepthAIRig(host, defaults, scene_text=twin_text, device=device)
    else:
        return DeviceRig(device, prompt=opts.prompt)
    rig.scene = scene
    return rig


def _state_seed(state: Mapping[str, Any]) -> int:
    import hashlib
    import json

    key = json.dumps({k: float(v) for k, v in state.items()}, sort_keys=True)
    return int(hashlib.sha256(key.encode()).hexdigest()[:6], 16)


def _bench_effects(scene: str, state: Mapping[str, Any], opts: BenchOptions, d: float,
                   hidden: bool = True) -> dict[str, Any]:
    """The bench's effects: the scene's own, the known bench light (ambient), then (for the
    emulator, not the twin) the hidden truth at this distance; empty when there is none of
    the last two (the scene's own block applies)."""
    params, known = _split(state)
    extra = {**known, **(hidden_effects(opts.hidden, d) if hidden else {})}
    if not extra:
        return {}
    from tofhil.sim.pipeline import resolve_effects
    from tofhil.sim.scene import load_scene

    own = resolve_effects(load_scene(scene, {"params": params}), None)
    return {**own, **extra}


# --------------------------------------------------------------------------- reading captures
def _nanmean(radial: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per-pixel mean over the frames where the pixel is valid (NaN where it never is)."""
    n = valid.sum(axis=0)
    total = np.where(valid, radial, 0.0).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _depth_stack(path: Path) -> tuple[np.ndarray, np.ndarray, Any, dict[str, Any]]:
    """``radial [N, H, W]``, ``valid [N, H, W]``, the camera and the acquisition of a session
    (raw taps demodulated by the core, as ``tofhil depth``); a depth-only session's acquisition
    is the kind of distance its device sent (``{"depth_kind": "radial" | "z"}``: what its
    millimetres round, :func:`twin_depths`)."""
    from tofhil.depth import depth_from_raw
    from tofhil.session import open_session

    with open_session(path) as s:
        frames = [depth_from_raw(s.raw_frame(i)) if s.has_raw else s.depth_frame(i) for i in range(s.n_frames)]
        acq = s.acquisition() if s.has_raw else {"depth_kind": frames[0].kind}
    d = np.stack([np.where(f.valid, f.distance_m if f.kind == "radial" else f.camera.z_to_radial(f.distance_m),
                           np.nan) for f in frames])
    return d, np.stack([f.valid for f in frames]), frames[0].camera, acq


def twin_scene(rig: Any, state: Mapping[str, Any], acq: Mapping[str, Any]) -> Any:
    """The twin's scene of a bench state: the rig's scene with the state's parameters and, for
    the emulated TOFcam635, the device's overrides at the capture's frequencies and exposure."""
    import copy

    from tofhil.sim.scene import load_scene

    params, _ = _split(state)
    over: dict[str, Any] = {"params": dict(params)}
    if rig.device.startswith("emulator"):
        from tofhil.sim.sources import TOFCAM635_OVERRIDES

        over.update(copy.deepcopy(TOFCAM635_OVERRIDES))
        over["sensor"] = {**over["sensor"], "freq_hz": [float(f) for f in acq["freq_hz"]],
                          "integration_time_s": float(acq["integration_time_s"])}
    return load_scene(rig.scene, over)


def _twin_stack(rig: Any, state: Mapping[str, Any], acq: Mapping[str, Any], frames: int,
                seed: int, opts: BenchOptions, *, noise: bool = True,
                effects: Mapping[str, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The twin's frames of the same bench (the scene and the bench's known light, without
    the hidden truth) with the capture's acquisition settings, demodulated like the capture."""
    from tofhil.depth import depth_from_raw
    from tofhil.sim.pipeline import simulate

    scene = twin_scene(rig, state, acq)
    known = _bench_effects(rig.scene, state, opts, 0.0, hidden=False)
    if effects:
        from tofhil.sim.pipeline import resolve_effects

        known = {**(known or resolve_effects(scene, None)), **effects}
    raws = simulate(scene, frames=frames, seed=seed, noise=noise, effects=known or None)
    return twin_depths(rig, [depth_from_raw(r) for r in raws], acq.get("depth_kind", "z"))


def twin_depths(rig: Any, deps: list[Any], kind: str = "z") -> tuple[np.ndarray, np.ndarray]:
    """``radial [N, H, W]`` (NaN where invalid) and ``valid`` of the twin's demodulated frames, as
    the device would report them: a depth-only device (DepthAI) sends whole millimetres of
    ``kind`` (the capture's: radial distance, or z with its optical correction on) and 0 for
    "no data", so a pixel the twin puts at 0 m (a phase of exactly 0: the few-DN taps of a very
    dark target quantise it there) is invalid there too. The kind matters: rounding the radial
    distance to whole mm biases a wall's ROI mean by up to 0.08 mm (+0.045 mm at 1.3 m, -0.078
    mm at 1.9 m on the ``wall`` scene, however many frames: the taps' whole-DN levels beat with
    the mm grid, the same for every pixel of the ROI), rounding z (a grid differing pixel by
    pixel in radial distance) does not."""
    d = np.stack([np.where(f.valid, f.distance_m, np.nan) for f in deps])
    v = np.stack([f.valid for f in deps])
    if "dcs" not in getattr(getattr(rig, "capabilities", None), "modes", ("dcs",)):
        per_m = deps[0].camera.ray_z if kind == "z" else 1.0        # radial -> the kind on the wire
        mm = np.rint(np.nan_to_num(d) * per_m * 1000.0)             # whole mm on the wire
        v = v & (mm > 0)
        d = np.where(v, mm * 1e-3 / per_m, np.nan)
    return d, v


# --------------------------------------------------------------------------- accuracy vs distance
class Accuracy:
    NAME = "accuracy-vs-distance"
    SUMMARY = ("a flat wall at a series of distances, N frames each: systematic error (mean - truth) and random "
               "error (temporal std), centre ROI and whole field, with the twin's prediction band")

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, DISTANCE_PARAM, opts.distances_m[0])

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        first, by = acquisition(opts, rig, 125)
        steps: list[dict[str, Any]] = [first]
        for d in opts.distances_m:
            steps.append({"bench": {DISTANCE_PARAM: float(d)}, "by": by,
                          "message": f"put the flat target perpendicular to the optical axis at {d:g} m"})
            if opts.extra.get("settle_s"):
                steps.append({"wait": float(opts.extra["settle_s"])})
            steps.append({"capture": {"label": f"d{d:.3f}m", "frames": opts.frames}})
        return parse_plan({"name": Accuracy.NAME, "steps": steps}, f"<{Accuracy.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        return analyse_series(Accuracy.NAME, campaign, rig, opts, "distance_m", namer=name_range_error)


def analyse_series(name: str, campaign: CampaignResult, rig: Any, opts: BenchOptions, axis: str, *,
                   namer: Callable[[np.ndarray, np.ndarray, np.ndarray], dict[str, Any]] | None = None,
                   region: Callable[[Any, Mapping[str, Any]], tuple[tuple[int, int, int, int], float]] | None = None
                   ) -> BenchResult:
    """Accuracy and precision of each capture of a flat target, beside the twin's, along ``axis``
    (a bench parameter: ``distance_m``, ``ambient_w_m2``, ``square_reflectance``). ``namer``
    names the cause of a systematic disagreement from its shape along the axis; ``region(camera,
    bench state)`` gives the ROI and the target's depth offset from the wall (default: the
    centre ROI on the wall)."""
    from tofhil.eval.metrics.bench import centre_roi, depth_stack_stats, plane_flatness

    seconds = {"twin": 0.0, "analysis": 0.0}
    rows: list[dict[str, Any]] = []
    twin_ok = getattr(rig, "scene", None) is not None
    for i, (label, rec) in enumerate(campaign.captures.items()):
        t0 = time.monotonic()
        d_true = float(rec["bench"][DISTANCE_PARAM])
        radial, valid, cam, acq = _depth_stack(campaign.session(label))
        if region is not None:
            roi, in_front = region(cam, rec["bench"])
        else:
            roi, in_front = opts.roi or centre_roi(cam.shape), 0.0
        truth = (d_true - in_front) / cam.ray_z
        m = depth_stack_stats(radial, valid, truth, roi)
        mean = _nanmean(radial, valid)
        fl = plane_flatness(cam.points(np.nan_to_num(mean), valid=np.all(valid, axis=0)))
        seconds["analysis"] += time.monotonic() - t0
        row = {"label": label, "distance_m": d_true, AMBIENT: float(rec["bench"].get(AMBIENT, 0.0)),
               **({axis: float(rec["bench"][axis])} if axis not in ("distance_m", AMBIENT) else {}),
               **{f"measured_{k}": v for k, v in m.to_dict().items()}, "measured_flatness_rms_m": fl.rms_m}
        if twin_ok:
            t0 = time.monotonic()
            tr, tv = _twin_stack(rig, rec["bench"], acq, max(opts.frames, 2), opts.seed + 7919 + i, opts)
            p = depth_stack_stats(tr, tv, truth, roi)
            tmean = _nanmean(tr, tv)
            tfl = plane_flatness(cam.points(np.nan_to_num(tmean), valid=np.all(tv, axis=0)))
            row.update({f"twin_{k}": v for k, v in p.to_dict().items()})
            row["twin_flatness_rms_m"] = tfl.rms_m
            seconds["twin"] += time.monotonic() - t0
        rows.append(row)
    res = BenchResult(name, rig.device, [], curves={name: rows}, seconds=seconds)
    res.figures = _accuracy_figures(rows, axis)
    if twin_ok:
        res.details["agreement"] = agreement(rows, axis, namer)
        res.findings = res.details["agreement"]["findings"]
    else:
        res.findings = ["no twin scene (--scene) for this device: the measured figures stand alone"]
    ag = res.details.get("agreement", {})
    if opts.extra.get("diagnose") and twin_ok and ag.get("cause") is not None:
        t0 = time.monotonic()
        try:
            res.details["diagnosis"] = diagnose_worst(campaign, rig, opts, rows, ag)
        except TofhilError as exc:  # the captures and figures stand; say why no diagnosis
            res.details["diagnosis"] = {"error": str(exc), "text": f"the diagnosis could not run: {exc}"}
        res.findings.append(res.details["diagnosis"]["text"])
        seconds["diagnose"] = time.monotonic() - t0
    if axis == "distance_m" and len(rows) >= 2:
        res.figures.append(_relative_range(rows))
    if axis == AMBIENT:
        res.figures.append(_ambient_factor(rows))
        f = res.figures[-1]
        at = max((r for r in rows if math.isfinite(r["measured_random_m"])), key=lambda r: r[AMBIENT],
                 default=rows[-1])[AMBIENT]
        res.findings.append(f"background-light rejection: the random error at {at:g} W/m² is "
                            f"{f.value:.2f} x that without ambient light (the twin predicts {f.predicted:.2f} x)")
    res.plots = lambda: _accuracy_plots(rows, twin_ok, axis)
    return res


def diagnose_worst(campaign: CampaignResult, rig: Any, opts: BenchOptions, rows: list[dict[str, Any]],
                   ag: dict[str, Any]) -> dict[str, Any]:
    """Run the diagnosis (``tofhil.eval.diagnose``) on the capture that differs most from the
    twin, against the twin's scene for that capture (``diagnosis/twin_scene.yaml``)."""
    import copy

    from tofhil.eval.diagnose.run import diagnose
    from tofhil.sim.scene import load_scene
    from tofhil.sim.session_setup import write_twin_scene

    usable = [r for r in rows if math.isfinite(r.get("measured_systematic_m", math.nan))
              and math.isfinite(r.get("twin_systematic_m", math.nan))]
    # the largest difference in millimetres (not in sigmas: the nearest capture is the most precise)
    row = max(usable, key=lambda r: abs(r["measured_systematic_m"] - r["twin_systematic_m"]))
    label = row["label"]
    state = campaign.captures[label]["bench"]
    params, _ = _split(state)
    over: dict[str, Any] = {"params": params}
    if rig.device.startswith("emulator"):
        from tofhil.sim.sources import TOFCAM635_OVERRIDES

        over.update(copy.deepcopy(TOFCAM635_OVERRIDES))
    known = _bench_effects(rig.scene, state, opts, 0.0, hidden=False)
    if known:
        over["effects"] = known
    out = campaign.out_dir / "diagnosis"
    out.mkdir(exist_ok=True)
    twin, _ = write_twin_scene(load_scene(rig.scene, over), campaign.session(label), out / "twin_scene.yaml")
    r = diagnose(campaign.session(label), twin, max_effects=int(opts.extra.get("diagnose_max_effects", 2)))
    verdict = r.verdict.text if r.verdict is not None else str(r.cause)
    diff_mm = 1e3 * (row["measured_systematic_m"] - row["twin_systematic_m"])
    text = f"diagnosis of capture {label} (the largest difference from the twin, {diff_mm:+.1f} mm): {verdict}"
    if r.params:
        text += "; fitted " + "; ".join(f"{e} " + ", ".join(f"{k} = {v:.4g}" for k, v in p.items())
                                        for e, p in r.params.items())
    return {"capture": label, "causes": list(r.causes), "params": r.params, "verdict": verdict, "text": text,
            "twin_scene": str(out / "twin_scene.yaml")}


def _relative_range(rows: list[dict[str, Any]]) -> Figure:
    """Relative-range error (ASTM E2938's idea: range differences against a reference position):
    ``(measured_i - measured_ref) - (true_i - true_ref)`` = the systematic errors' difference,
    the nearest distance the reference; the largest over the others, with its standard error."""
    ok = [r for r in rows if math.isfinite(r["measured_systematic_m"])]
    if len(ok) < 2:
        return Figure("relative_range_error_m", math.nan)
    ref = min(ok, key=lambda r: r["distance_m"])

    def rel(pre: str, r: dict[str, Any]) -> tuple[float, float]:
        v = r[f"{pre}_systematic_m"] - ref[f"{pre}_systematic_m"]
        return v, math.hypot(r[f"{pre}_systematic_se_m"], ref[f"{pre}_systematic_se_m"])

    worst = max((r for r in ok if r is not ref), key=lambda r: abs(rel("measured", r)[0]))
    v, s = rel("measured", worst)
    pv, ps = rel("twin", worst) if "twin_systematic_m" in worst else (math.nan, math.nan)
    return Figure("relative_range_error_m", abs(v), s, abs(pv), ps,
                  note=f"{worst['distance_m']:g} m against {ref['distance_m']:g} m")


def _ambient_factor(rows: list[dict[str, Any]]) -> Figure:
    """Random error at the brightest ambient over that at the darkest, with its uncertainty
    (among the levels where the ROI has pixels valid in every frame: a sensor saturated by the
    ambient light has none)."""
    usable = [r for r in rows if math.isfinite(r["measured_random_m"])] or rows
    lo, hi = min(usable, key=lambda r: r[AMBIENT]), max(usable, key=lambda r: r[AMBIENT])

    def ratio(pre: str) -> tuple[float, float]:
        a, b = lo[f"{pre}_random_m"], hi[f"{pre}_random_m"]
        if not (a > 0 and b > 0):
            return math.nan, math.nan
        # relative s.e. of a std from its variance's: s.e.(s^2) / (2 s^2)
        ra = lo[f"{pre}_random_var_se_m2"] / (2 * a * a)
        rb = hi[f"{pre}_random_var_se_m2"] / (2 * b * b)
        return b / a, b / a * math.hypot(ra, rb)

    v, s = ratio("measured")
    pv, ps = ratio("twin") if "twin_random_m" in hi else (math.nan, math.nan)
    return Figure("ambient_noise_factor", v, s, pv, ps, note=f"{hi[AMBIENT]:g} W/m² against {lo[AMBIENT]:g}")


def _accuracy_figures(rows: list[dict[str, Any]], axis: str = "distance_m") -> list[Figure]:
    unit = {"distance_m": "m", AMBIENT: "W/m²"}.get(axis, "")

    def worst(key: str, se_key: str | None, absolute: bool = True) -> Figure:
        vals = np.array([r[f"measured_{key}"] for r in rows], dtype=float)
        i = int(np.nanargmax(np.abs(vals) if absolute else vals))
        se = rows[i].get(f"measured_{se_key}", math.nan) if se_key else math.nan
        pred = rows[i].get(f"twin_{key}", math.nan)
        pse = rows[i].get(f"twin_{se_key}", math.nan) if se_key else math.nan
        return Figure("", float(abs(vals[i]) if absolute else vals[i]), float(se),
                      float(abs(pred) if absolute else pred), float(pse), note=f"at {rows[i][axis]:g} {unit}")

    out = []
    for name, key, se, ab in (("systematic_error_m", "systematic_m", "systematic_se_m", True),
                              ("random_error_m", "random_m", None, False),
                              ("systematic_error_field_m", "systematic_field_m", None, True),
                              ("random_error_field_m", "random_field_m", None, False)):
        f = worst(key, se, ab)
        f.name = name
        if name == "random_error_m":
            i = int(np.nanargmax([r["measured_random_m"] for r in rows]))
            s = rows[i]["measured_random_m"]
            f.sigma = rows[i]["measured_random_var_se_m2"] / (2 * s) if s > 0 else math.nan
        out.append(f)
    fill = min(r["measured_fill_rate_roi"] for r in rows)
    out.append(Figure("fill_rate", fill, predicted=min(r.get("twin_fill_rate_roi", math.nan) for r in rows)))
    fl = max(r["measured_flatness_rms_m"] for r in rows)
    out.append(Figure("flatness_rms_m", fl, predicted=max(r.get("twin_flatness_rms_m", math.nan) for r in rows)))
    return out


def _chi2_sf(x: float, dof: int) -> float:
    from scipy.stats import chi2

    return float(chi2.sf(x, dof))


def agreement(rows: list[dict[str, Any]], axis: str = "distance_m",
              namer: Callable[[np.ndarray, np.ndarray, np.ndarray], dict[str, Any]] | None = None) -> dict[str, Any]:
    """Measured against the twin over the distances: the systematic error's difference (its
    noise: both standard errors) and the random error's (its variance's standard errors), each
    a chi-square test; where the systematic one fails, the range error that explains it."""
    keys = ("measured_systematic_m", "twin_systematic_m", "measured_random_m", "twin_random_m")
    usable = [r for r in rows if all(math.isfinite(r[k]) for k in keys)]
    left_out = [r[axis] for r in rows if r not in usable]
    if not usable:
        return {"cause": None, "findings": ["no distance has valid pixels in the ROI in every frame (saturated or "
                                            "too dark): nothing to compare with the twin"]}
    rows = usable
    d = np.array([r[axis] for r in rows])
    delta = np.array([r["measured_systematic_m"] - r["twin_systematic_m"] for r in rows])
    se = np.hypot([r["measured_systematic_se_m"] for r in rows], [r["twin_systematic_se_m"] for r in rows])
    z = delta / se
    chi2_sys = float(np.sum(z ** 2))
    p_sys = _chi2_sf(chi2_sys, len(d))
    v_m = np.array([r["measured_random_m"] ** 2 for r in rows])
    v_p = np.array([r["twin_random_m"] ** 2 for r in rows])
    sv = np.hypot([r["measured_random_var_se_m2"] for r in rows], [r["twin_random_var_se_m2"] for r in rows])
    zr = (v_m - v_p) / sv
    chi2_rand = float(np.sum(zr ** 2))
    p_rand = _chi2_sf(chi2_rand, len(d))
    out: dict[str, Any] = {"systematic": {"chi2": chi2_sys, "dof": len(d), "p": p_sys, "z": z.tolist()},
                           "random": {"chi2": chi2_rand, "dof": len(d), "p": p_rand, "z": zr.tolist(),
                                      "ratio": (np.sqrt(v_m / v_p)).tolist()},
                           "false_alarm": FALSE_ALARM}
    findings = []
    if p_sys >= FALSE_ALARM:
        findings.append(f"systematic error agrees with the twin within noise (chi2 {chi2_sys:.1f} for {len(d)} "
                        f"captures, p = {p_sys:.2f})")
        out["cause"] = None
    elif namer is None:
        out["cause"] = {"kind": "unexplained", "text": "run tofhil diagnose on the sessions with the twin's scene"}
        findings.append(f"systematic error differs from the twin (chi2 {chi2_sys:.1f} for {len(d)} captures, "
                        f"p = {p_sys:.1e}): {out['cause']['text']}")
    else:
        cause = namer(d, delta, se)
        out["cause"] = cause
        findings.append(f"systematic error differs from the twin (chi2 {chi2_sys:.1f} for {len(d)} captures, "
                        f"p = {p_sys:.1e}): {cause['text']}")
    if p_rand >= FALSE_ALARM:
        findings.append(f"random error agrees with the twin within noise (chi2 {chi2_rand:.1f}, p = {p_rand:.2f})")
    else:
        ratio = float(np.sqrt(np.mean(v_m / v_p)))
        findings.append(f"random error differs from the twin: measured / predicted = {ratio:.3f} on average "
                        f"(chi2 {chi2_rand:.1f}, p = {p_rand:.1e}): the twin's noise model (read noise, gain, "
                        "ambient; bench photon-transfer measures it) or a signal the twin lacks (it changes the "
                        "amplitude the noise is relative to)")
    if left_out:
        findings.append("left out (no pixel of the ROI valid in every frame: saturated or too dark): "
                        + ", ".join(f"{x:g} {_AXIS_UNIT.get(axis, '')}".strip() for x in left_out))
    out["findings"] = findings
    return out


def name_range_error(d: np.ndarray, delta: np.ndarray, se: np.ndarray) -> dict[str, Any]:
    """The simplest range error that explains ``delta(d)`` within its noise: a constant offset
    (``a``), or one growing with distance (``a + b d``); the linear term is taken only when a
    chi-square-difference test at the false-alarm rate wants it."""
    w = 1.0 / se
    fits = {}
    for name, x in (("offset", np.ones((len(d), 1))), ("scale", np.column_stack([np.ones_like(d), d]))):
        p, *_ = np.linalg.lstsq(x * w[:, None], delta * w, rcond=None)
        cov = np.linalg.inv((x * w[:, None]).T @ (x * w[:, None]))
        chi2 = float(np.sum(((x @ p - delta) * w) ** 2))
        fits[name] = {"params": p.tolist(), "sigma": np.sqrt(np.diag(cov)).tolist(), "chi2": chi2,
                      "dof": len(d) - x.shape[1], "p": _chi2_sf(chi2, len(d) - x.shape[1])}
    gain = fits["offset"]["chi2"] - fits["scale"]["chi2"]
    p_gain = _chi2_sf(gain, 1)
    if p_gain < FALSE_ALARM and len(d) >= 3:
        a, b = fits["scale"]["params"]
        sa, sb = fits["scale"]["sigma"]
        kind = "range error growing with distance"
        text = (f"a range error growing with distance: {b * 1e3:+.2f} +- {sb * 1e3:.2f} mm per metre "
                f"({b * 100:+.3f} % of the distance; e.g. a modulation-frequency error), {a * 1e3:+.2f} +- "
                f"{sa * 1e3:.2f} mm at 0 m")
        chosen = "scale"
    else:
        (a,), (sa,) = fits["offset"]["params"], fits["offset"]["sigma"]
        kind = "range offset"
        text = f"a constant range offset of {a * 1e3:+.2f} +- {sa * 1e3:.2f} mm (e.g. an electronic delay)"
        chosen = "offset"
    if fits[chosen]["p"] < FALSE_ALARM:
        kind = "unexplained"
        text = (f"no range offset or scale explains it (best: {text}; chi2 {fits[chosen]['chi2']:.1f} for "
                f"{fits[chosen]['dof']} dof): run tofhil diagnose on the sessions with the twin's scene")
    return {"kind": kind, "text": text, "fits": fits, "chosen": chosen, "p_linear_term": p_gain}


_AXIS_UNIT = {"distance_m": "m", AMBIENT: "W/m²", "square_reflectance": "of the wall's reflectance"}
_AXIS_LABEL = {"distance_m": "target distance (m)", AMBIENT: "ambient irradiance on the target (W/m²)",
               "square_reflectance": "square reflectance relative to the wall"}


def _accuracy_plots(rows: list[dict[str, Any]], twin: bool, axis: str = "distance_m") -> list[tuple[str, str | None, str]]:
    from tofhil.eval.reports.html import fig_uri, pyplot

    plt = pyplot()
    d = np.array([r[axis] for r in rows])
    where = "the square" if axis == "square_reflectance" else "centre ROI"
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), layout="constrained")
    for ax, key, se_of, title in ((axes[0], "systematic_m", "systematic_se_m", "systematic error (mean - truth)"),
                                  (axes[1], "random_m", None, "random error (temporal std)")):
        m = np.array([r[f"measured_{key}"] for r in rows]) * 1e3
        if se_of:
            ax.errorbar(d, m, yerr=2e3 * np.array([r[f"measured_{se_of}"] for r in rows]), fmt="o-",
                        label=f"measured, {where} (2 s.e.)")
        else:
            ax.plot(d, m, "o-", label=f"measured, {where}")
        field = "systematic_field_m" if se_of else "random_field_m"
        ax.plot(d, np.array([r[f"measured_{field}"] for r in rows]) * 1e3, "s--", ms=4, label="measured, field median")
        if twin:
            p = np.array([r[f"twin_{key}"] for r in rows]) * 1e3
            if se_of:
                band = 2e3 * np.hypot([r[f"twin_{se_of}"] for r in rows], [r[f"measured_{se_of}"] for r in rows])
            else:
                band = 2e3 * np.array([r["twin_random_var_se_m2"] / (2 * max(r["twin_random_m"], 1e-12)) for r in rows])
            ax.fill_between(d, p - band, p + band, color="C3", alpha=0.25, label="twin: predicted band (2 sigma)")
            ax.plot(d, p, "-", color="C3", lw=1)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(_AXIS_LABEL.get(axis, axis))
        if axis == "square_reflectance":   # log axis, ticks at the squares themselves (no crowded minor labels)
            ax.set_xscale("log")
            ax.set_xticks(d)
            ax.set_xticklabels([f"{100 * v:g} %" for v in d])
            ax.minorticks_off()
        ax.set_ylabel("mm")
        ax.set_title(title)
        ax.legend(fontsize=8)
    what = {"distance_m": "distance", AMBIENT: "ambient light"}.get(axis, "the square's reflectance")
    roi = "the square (inner 60 %)" if axis == "square_reflectance" else "centre ROI"
    return [(f"Accuracy and precision against {what}", fig_uri(fig),
             f"{roi[0].upper() + roi[1:]} (markers) and the whole field's median pixel (dashed) against the twin's prediction for "
             "the same settings (band: 2 sigma of the noise of both).")]


# --------------------------------------------------------------------------- ambient light
class Ambient:
    NAME = "ambient"
    SUMMARY = ("precision against ambient light (a lamp or the sun on the target, W/m²): random and systematic "
               "error at each level beside the twin's, and the background-light rejection (noise factor)")
    LEVELS_W_M2 = (0.0, 2.0, 5.0, 10.0, 20.0)

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, DISTANCE_PARAM, opts.distances_m[0])

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        first, by = acquisition(opts, rig, 125)
        d = float(opts.extra.get("ambient_distance_m", 1.0))
        steps: list[dict[str, Any]] = [first]
        for a in opts.extra.get("ambient_w_m2") or Ambient.LEVELS_W_M2:
            steps.append({"bench": {DISTANCE_PARAM: d, AMBIENT: float(a)}, "by": by,
                          "message": f"flat target at {d:g} m; set the lamp to {a:g} W/m² on the target (radiometer)"})
            steps.append({"capture": {"label": f"amb{float(a):g}", "frames": opts.frames}})
        return parse_plan({"name": Ambient.NAME, "steps": steps}, f"<{Ambient.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        return analyse_series(Ambient.NAME, campaign, rig, opts, AMBIENT)


def _nested_fits(delta: np.ndarray, se: np.ndarray, designs: dict[str, np.ndarray]) -> dict[str, Any]:
    """Weighted least squares of ``delta`` on each design (the second nests the first), and the
    chi-square-difference test of the second's extra column (``p_extra``)."""
    w = 1.0 / se
    fits: dict[str, Any] = {}
    for name, x in designs.items():
        p, *_ = np.linalg.lstsq(x * w[:, None], delta * w, rcond=None)
        cov = np.linalg.inv((x * w[:, None]).T @ (x * w[:, None]))
        chi2 = float(np.sum(((x @ p - delta) * w) ** 2))
        fits[name] = {"params": p.tolist(), "sigma": np.sqrt(np.diag(cov)).tolist(), "chi2": chi2,
                      "dof": len(delta) - x.shape[1], "p": _chi2_sf(chi2, len(delta) - x.shape[1])}
    a, b = list(designs)
    fits["p_extra"] = _chi2_sf(max(fits[a]["chi2"] - fits[b]["chi2"], 0.0), 1)
    return fits


# --------------------------------------------------------------------------- flatness / fill rate
class FlatnessProc:
    NAME = "flatness"
    SUMMARY = ("one capture of a flat target: plane-fit residual (RMS, peak-to-valley), fill rate, precision "
               "when frames >= 2 (on recorded sessions too: --device replay:S.h5)")

    @staticmethod
    def make_rig(device: str, opts: BenchOptions) -> Any:
        return _rig(device, opts, DISTANCE_PARAM, opts.distances_m[0])

    @staticmethod
    def make_plan(opts: BenchOptions, rig: Any) -> Plan:
        frames = opts.frames
        if rig.device.startswith("replay:"):
            from tofhil.session import open_session

            with open_session(rig.device.split(":", 1)[1].split("?", 1)[0]) as s:
                frames = min(frames, s.n_frames)
        settings: dict[str, Any] = {"mode": "dcs" if rig.device.startswith("emulator") else "distance"}
        if rig.device.startswith("replay:"):
            settings["mode"] = "distance" if not _session_has_raw(rig.device) else "dcs"
        steps: list[dict[str, Any]] = [{"settings": settings}]
        if "emulator" in rig.capabilities.bench_by:
            steps.append({"bench": {DISTANCE_PARAM: float(opts.distances_m[0])}, "by": "emulator"})
        steps.append({"capture": {"label": "flat", "frames": frames}})
        return parse_plan({"name": FlatnessProc.NAME, "steps": steps}, f"<{FlatnessProc.NAME} plan>")

    @staticmethod
    def analyse(campaign: CampaignResult, rig: Any, opts: BenchOptions) -> BenchResult:
        from tofhil.eval.metrics.bench import centre_roi, fill_rate, plane_flatness

        t0 = time.monotonic()
        radial, valid, cam, _ = _depth_stack(campaign.session("flat"))
        roi = opts.roi or centre_roi(cam.shape)
        x0, y0, x1, y1 = roi
        mask = np.zeros(cam.shape, bool)
        mask[y0:y1, x0:x1] = True
        mean = _nanmean(radial, valid)
        all_valid = np.all(valid, axis=0)
        fl = plane_flatness(cam.points(np.nan_to_num(mean), valid=all_valid & mask))
        fr = fill_rate(all_valid, roi)
        figs = [Figure("flatness_rms_m", fl.rms_m), Figure("flatness_pv_m", fl.pv_m), Figure("fill_rate", fr)]
        n = radial.shape[0]
        rows = {"roi": list(roi), "frames": n, **{f"plane_{k}": v for k, v in fl.to_dict().items()}, "fill_rate": fr,
                "fill_rate_field": float(all_valid.mean())}
        findings = [f"plane fit over {fl.points} pixels of ROI {roi} ({fl.outliers} beyond 4 robust sigma left out): "
                    f"RMS {fl.rms_m * 1e3:.2f} mm, peak-to-valley {fl.pv_m * 1e3:.2f} mm at {fl.distance_m:.3f} m; "
                    f"fill rate {100 * fr:.1f} % (whole field {100 * all_valid.mean():.1f} %)"]
        if n >= 2:
            sd = np.nanstd(radial, axis=0, ddof=1)[mask & all_valid]
            prec = float(np.sqrt(np.mean(sd ** 2)))
            figs.append(Figure("precision_m", prec, prec / math.sqrt(2 * (n - 1) * max(sd.size, 1))))
            rows["precision_m"] = prec
        else:
            findings.append("one frame: the precision (temporal std) needs two frames or more")
        res = BenchResult(FlatnessProc.NAME, rig.device, figs, curves={"flatness": [rows]}, findings=findings,
                          seconds={"analysis": time.monotonic() - t0})
        res.plots = lambda: _flatness_plot(cam, mean, all_valid, roi, fl)
        return res


def _session_has_raw(device: str) -> bool:
    from tofhil.session import open_session

    with open_session(device.split(":", 1)[1].split("?", 1)[0]) as s:
        return bool(s.has_raw)


def _flatness_plot(cam: Any, mean: np.ndarray, valid: np.ndarray, roi: tuple[int, int, int, int],
                   fl: Any) -> list[tuple[str, str | None, str]]:
    from tofhil.eval.reports.html import fig_uri, pyplot, robust_range

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), layout="constrained")
    img = np.where(valid, mean, np.nan)
    lo, hi = robust_range([img[np.isfinite(img)]])
    im = axes[0].imshow(img, cmap="viridis", vmin=lo, vmax=hi)
    fig.colorbar(im, ax=axes[0], label="radial distance (m)")
    x0, y0, x1, y1 = roi
    axes[0].add_patch(plt.Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0, y1 - y0, fill=False, ec="r", lw=1.5))
    axes[0].set_title("mean depth, ROI in red")
    # the residual to the fitted plane over the ROI
    pts = cam.rays * np.nan_to_num(mean)[..., None]
    n = np.asarray(fl.normal)
    res = (pts @ n + fl.distance_m)
    sub = np.where(valid, res, np.nan)[y0:y1, x0:x1] * 1e3
    s = np.nanpercentile(np.abs(sub), 98) if np.isfinite(sub).any() else 1.0
    im = axes[1].imshow(sub, cmap="RdBu_r", vmin=-s, vmax=s)
    fig.colorbar(im, ax=axes[1], label="residual to the plane (mm)")
    axes[1].set_title(f"plane residual: RMS {fl.rms_m * 1e3:.2f} mm")
    return [("Flatness", fig_uri(fig), "The mean depth and, over the ROI, the orthogonal residual to the fitted plane.")]


def as_procedure(cls: type) -> SimpleNamespace:
    return SimpleNamespace(NAME=cls.NAME, SUMMARY=cls.SUMMARY, make_rig=cls.make_rig, make_plan=cls.make_plan,
                           analyse=cls.analyse)


PROCEDURES = [as_procedure(Accuracy), as_procedure(Ambient), as_procedure(FlatnessProc)]
