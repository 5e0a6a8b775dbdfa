"""The stray-light study on the twin: thesis methods against the calibrated PSF (a study,
not library code: run by ``straylight_methods.py`` beside it and the acceptance test).

Cases are the bundled ``dark_square_card`` scene (white wall at 1 m, a dark square in the
middle, a white card 0.17 m from the lens) for square reflectances from 50 % down to 1 %
of the wall's, each simulated through the full sensor model twice from one render: with
a stray-light PSF (the "measurement") and without it (the twin's stray-light-free
reference, with the same fixed-pattern offsets). The stray-light depth error of a case is
the mean absolute difference of the two depth images over the dark square's pixels (the
object id of the square in the render); a correction's error is the same with the
corrected measurement.

The calibrated PSF is fitted ONCE on a different scene and applied unchanged to every
case. Thesis methods 1 and 2 are given every advantage: their parameters are searched per
case for the smallest error in the square (their "best w" and "best sigma").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy.optimize import minimize_scalar

from tofhil.demod import phasor, phase_to_distance, wrapped_phase
from tofhil.eval.corrections import psf_calibration as pc
from tofhil.eval.corrections import straylight as sl
from tofhil.eval.calibration.taps import TapCalibration, calibrate_taps
from tofhil.sim.straylight import StrayLightPSF

#: The optics of the study's "camera": a narrow and two wide lobes, a veil and a ghost
#: (fractions of light; sigmas in pixels of the 160 x 120 sensor). Energy-conserving.
STUDY_PSF: dict[str, Any] = {"gaussians": [[0.02, 3.0, 3.0], [0.03, 15.0, 12.0], [0.02, 60.0, 50.0]],
                             "veil": 0.01, "ghost_weight": 0.005, "ghost_sigma_px": 4.0}

REFLECTANCES: tuple[float, ...] = (0.5, 0.2, 0.1, 0.05, 0.02, 0.01)

#: Sensor overrides for every capture of the study: an ADC pedestal. The bundled scenes'
#: sensors have ``black_level_dn: 0``, so taps below the offset clip at 0 DN; the 1 % square
#: carries < 1 DN of signal, and its stray-light-free reference would be clipped (a
#: non-linearity no stray-light correction can undo, and one real ADCs avoid by a pedestal).
STUDY_SENSOR: dict[str, Any] = {"black_level_dn": 64.0}


@dataclass
class Capture:
    """Mean taps ``[F, K, H, W]`` of one scene with and without stray light, and truth.

    ``s_meas`` / ``s_ref`` are the complex signals after the tap calibration ``flat`` (if
    set): the same pre-processing for the measurement and its stray-light-free twin, so
    their difference is the stray light alone.
    """

    name: str
    taps_meas: np.ndarray
    taps_ref: np.ndarray
    theta_rad: np.ndarray
    freq_hz: np.ndarray
    object_id: np.ndarray
    object_names: list[str]
    cx: float
    cy: float
    params: dict[str, Any] = field(default_factory=dict)
    flat: TapCalibration | None = None

    def _signal(self, taps: np.ndarray) -> np.ndarray:
        return phasor(self.flat.apply(taps) if self.flat is not None else taps, self.theta_rad)

    @property
    def s_meas(self) -> np.ndarray:
        return self._signal(self.taps_meas)

    @property
    def s_ref(self) -> np.ndarray:
        return self._signal(self.taps_ref)

    def mask(self, object_name: str) -> np.ndarray:
        return self.object_id == self.object_names.index(object_name)


def _mean_taps(scene: Any, result: Any, effects: Mapping[str, Any], *, noise: bool, frames: int,
               seed: int) -> tuple[np.ndarray, np.ndarray]:
    from tofhil.sim.pipeline import forward

    acc = None
    for i in range(frames):
        raw = forward(scene, result, effects, noise=noise, seed=seed, frame_index=i)
        taps = raw.taps.astype(np.float64)
        acc = taps if acc is None else acc + taps
    return acc / frames, raw.theta_rad


def simulate_capture(scene_name: str, params: Mapping[str, Any] | None = None,
                     psf: Mapping[str, Any] | None = None, *, noise: bool = False, frames: int = 1,
                     seed: int = 0, sensor: Mapping[str, Any] | None = STUDY_SENSOR) -> Capture:
    """Render a bundled scene once and expose it with and without the stray-light effect.

    The measurement (with stray light) is the mean of ``frames`` exposures, noisy when
    ``noise``; the stray-light-free reference is the twin's noise-free expectation.
    """
    from tofhil.sim.pipeline import prepare_render
    from tofhil.sim.scene import load_scene

    ov: dict[str, Any] = {"sensor": dict(sensor)} if sensor else {}
    if params:
        ov["params"] = dict(params)
    scene = load_scene(scene_name, overrides=ov or None)
    scene2, result = prepare_render(scene, {})
    eff = {"stray_light": dict(STUDY_PSF if psf is None else psf)}
    t_meas, theta = _mean_taps(scene2, result, eff, noise=noise, frames=frames, seed=seed)
    t_ref, _ = _mean_taps(scene2, result, {}, noise=False, frames=1, seed=seed)
    cam = result.camera or scene2.camera
    return Capture(scene_name, t_meas, t_ref, theta, np.asarray(scene2.freq_hz), np.asarray(result.object_id),
                   [o.name for o in scene2.objects], float(cam.cx), float(cam.cy), dict(params or {}))


def calibrate_flat(*, noise: bool = False, frames: int = 1, seed: int = 0,
                   sensor: Mapping[str, Any] | None = STUDY_SENSOR) -> TapCalibration:
    """Tap calibration from two emitter-off captures of the ``wall`` scene: dark (no light)
    and flat (unmodulated ambient light on the wall). The emitter cannot be switched off in
    a scene file, so it is dimmed to 1e-12 W (nothing measurable)."""
    from tofhil.sim.pipeline import prepare_render
    from tofhil.sim.scene import load_scene

    out = []
    for ambient in (0.0, 5.0):
        ov: dict[str, Any] = {"emitter": {"power_w": 1e-12}, "ambient_irradiance_w_m2": ambient}
        if sensor:
            ov["sensor"] = dict(sensor)
        scene = load_scene("wall", overrides=ov)
        scene2, result = prepare_render(scene, {})
        out.append(_mean_taps(scene2, result, {}, noise=noise, frames=frames, seed=seed + int(ambient)))
    (dark, theta), (flat, _) = out
    return calibrate_taps(flat, theta, dark)


def distance(s: np.ndarray, freq_hz: np.ndarray) -> np.ndarray:
    """Radial distance of the first frequency (the study's scenes lie within one ambiguity range)."""
    return phase_to_distance(wrapped_phase(np.asarray(s)[0]), freq_hz[0])


def square_error(cap: Capture, s_corr: np.ndarray, region: str = "square") -> float:
    """Mean |d(S_corr) - d(S_ref)| over the region's pixels (m)."""
    m = cap.mask(region)
    d = distance(s_corr, cap.freq_hz)[m]
    d0 = distance(cap.s_ref, cap.freq_hz)[m]
    return float(np.mean(np.abs(d - d0)))


def best_uniform(cap: Capture, region: str = "square") -> tuple[float, float]:
    """Thesis method 1 at its best weight for this case: (w, error)."""
    n = cap.s_meas.shape[-1] * cap.s_meas.shape[-2]
    f = lambda lw: square_error(cap, sl.subtract_uniform(cap.s_meas, 10 ** lw), region)  # noqa: E731
    grid = np.linspace(np.log10(1e-4 / n), np.log10(0.5 / n), 41)
    errs = [f(g) for g in grid]
    i = int(np.argmin(errs))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    r = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3})
    return (float(10 ** r.x), float(r.fun)) if r.fun < errs[i] else (float(10 ** grid[i]), float(errs[i]))


def best_gaussian(cap: Capture, sigmas: Sequence[float] = tuple(2.0 * np.sqrt(2) ** np.arange(11)), mu: float = 0.0,
                  region: str = "square") -> tuple[float, float, float]:
    """Thesis method 2 at its best (sigma, w) for this case (sigma_h = sigma_v): (sigma, w, error)."""
    best = (float("nan"), float("nan"), float("inf"))
    for sg in sigmas:
        f = lambda w: square_error(cap, sl.inverse_filter_gaussian(cap.s_meas, sg, sg, w, mu), region)  # noqa: E731
        grid = np.linspace(0.0, 0.6, 13)
        errs = [f(w) for w in grid]
        i = int(np.argmin(errs))
        r = minimize_scalar(f, bounds=(grid[max(i - 1, 0)], grid[min(i + 1, 12)]), method="bounded",
                            options={"xatol": 1e-4})
        w, e = (float(r.x), float(r.fun)) if r.fun < errs[i] else (float(grid[i]), float(errs[i]))
        if e < best[2]:
            best = (float(sg), w, e)
    return best


def calibrate(kind: str = "reference", psf: Mapping[str, Any] | None = None,
              flat: TapCalibration | None = None, sensor: Mapping[str, Any] | None = STUDY_SENSOR,
              noise: bool = False, frames: int = 1) -> StrayLightPSF:
    """The one calibration used for every case, on scenes that are NOT the test cases.

    ``reference``: ``wall_card`` (wall and card, no square) with its stray-light-free twin.
    ``target``: a card on a dark background (the ``wall_card`` scene with a black wall),
    moved to the other side of the view, with no twin at all.
    """
    if kind == "reference":
        cap = simulate_capture("wall_card", None, psf, sensor=sensor, noise=noise, frames=frames, seed=11)
        cap.flat = flat
        return pc.calibrate_psf(cap.s_meas, cap.s_ref, cap.cx, cap.cy)
    if kind == "target":
        cap = simulate_capture("wall_card", {"wall_reflectance": 0.0, "card_offset_x_m": -0.05,
                                             "card_distance_m": 0.3}, psf, sensor=sensor, noise=noise,
                               frames=frames, seed=12)
        cap.flat = flat
        return pc.calibrate_psf_target(cap.s_meas, cap.cx, cap.cy)
    raise ValueError(f"unknown calibration kind {kind!r}")


def run_study(reflectances: Sequence[float] = REFLECTANCES, calibrations: Sequence[str] = ("reference", "target"),
              thesis: bool = True, psf: Mapping[str, Any] | None = None, flat: bool = True,
              sensor: Mapping[str, Any] | None = STUDY_SENSOR, noise: bool = False, frames: int = 1,
              log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Every case, every method: errors in the square (m) and the fraction removed.

    With ``flat`` every signal (calibration, cases, references) is tap-calibrated first
    (:func:`calibrate_flat`); the calibrated PSF is then also reported without it, to show
    what the tap gains cost. With ``noise`` every capture (tap calibration, PSF calibration,
    cases) is the mean of ``frames`` noisy exposures; references stay the noise-free twin.
    """
    say = log or (lambda s: None)
    tapcal = None
    if flat:
        say("tap calibration (dark + flat captures of the wall, emitter off)")
        tapcal = calibrate_flat(sensor=sensor, noise=noise, frames=frames, seed=13)
    psfs = {}
    for kind in calibrations:
        say(f"calibrating the PSF ({kind})")
        psfs[kind] = calibrate(kind, psf, tapcal, sensor, noise, frames)
    raw_psf = (calibrate("reference", psf, None, sensor, noise, frames)
               if flat and "reference" in calibrations else None)
    rows = []
    caps = []
    for rho in reflectances:
        say(f"case: square reflectance {rho:g} of the wall")
        cap = simulate_capture("dark_square_card", {"square_reflectance": rho}, psf, sensor=sensor, noise=noise,
                               frames=frames, seed=int(1000 * rho))
        if raw_psf is not None:
            before_raw = square_error(cap, cap.s_meas)
            e = square_error(cap, sl.deconvolve(cap.s_meas, raw_psf, center_px=(cap.cx, cap.cy)))
            no_flat = {"error_m": e, "removed": 1.0 - e / before_raw, "error_before_m": before_raw}
        cap.flat = tapcal
        before = square_error(cap, cap.s_meas)
        row: dict[str, Any] = {"square_reflectance": rho, "error_before_m": before}
        s_meas = cap.s_meas
        for kind, p in psfs.items():
            e = square_error(cap, sl.deconvolve(s_meas, p, center_px=(cap.cx, cap.cy)))
            row[f"psf_{kind}"] = {"error_m": e, "removed": 1.0 - e / before}
        if raw_psf is not None:
            row["psf_reference_without_tap_calibration"] = no_flat
        if thesis:
            w, e = best_uniform(cap)
            row["uniform_best"] = {"w": w, "error_m": e, "removed": 1.0 - e / before}
            sg, w2, e2 = best_gaussian(cap)
            row["gaussian_best"] = {"sigma_px": sg, "w": w2, "error_m": e2, "removed": 1.0 - e2 / before}
        rows.append(row)
        caps.append(cap)
    out: dict[str, Any] = {"psf": dict(STUDY_PSF if psf is None else psf), "tap_calibration": flat,
                           "sensor_overrides": dict(sensor or {}), "noise": noise, "frames": frames,
                           "cases": rows, "calibrations": {k: p.info for k, p in psfs.items()}}
    if thesis:
        # One weight for all cases, as a user of method 1 would have to choose it.
        n = caps[0].s_meas.shape[-1] * caps[0].s_meas.shape[-2]

        def total(lw: float) -> float:
            return float(np.mean([square_error(c, sl.subtract_uniform(c.s_meas, 10 ** lw)) / r["error_before_m"]
                                  for c, r in zip(caps, rows)]))

        r = minimize_scalar(total, bounds=(np.log10(1e-4 / n), np.log10(0.5 / n)), method="bounded")
        w_all = float(10 ** r.x)
        out["uniform_single_w"] = {"w": w_all, "removed": [1.0 - square_error(c, sl.subtract_uniform(c.s_meas, w_all))
                                                           / row["error_before_m"] for c, row in zip(caps, rows)]}
    return out
