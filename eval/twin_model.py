"""The simulator twin as a forward model for diagnosis: effect parameters -> predicted data.

Wraps the twin's own pipeline (``tofhil.sim.pipeline``): scene-stage effects re-render
(cached per parameter set), render-, signal- and pixel-stage effects act on a cached render,
and the sensor turns the light into noise-free taps, from which the same channels as the
measurement are formed (``S`` per frequency, and the tap offset when it is used). The twin is
set to the session's camera, frequencies, tap phases and integration time.

``DIAGNOSIS_LIBRARY`` lists which parameters of each effect diagnosis fits, their bounds,
optimiser scales and multi-start points; it is the single place to tune what diagnosis can
find. Parameters not listed keep their "off" values (a random per-pixel delay pattern, for
example, cannot be predicted without its seed, so only the clock gradients are fitted).
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from typing import Any, Mapping

import numpy as np

from tofhil.demod import phasor
from tofhil.eval.heldout import HeldOutData, depth_from_signal
from tofhil.eval.selection import EffectParams, EffectSpec, FitParam
from tofhil.sim.effects import EFFECTS, ORDER, parse_effects

# Parameter -> (lo, hi, optimiser scale); the off value comes from the effect library.
_P = dict[str, tuple[float, float, float]]

#: What diagnosis fits, per effect. ``log10_`` parameters are fitted on a log scale.
DIAGNOSIS_LIBRARY: dict[str, tuple[_P, tuple[dict[str, float], ...]]] = {
    "stray_light": ({"weight": (0.0, 0.3, 0.01), "sigma_px": (0.5, 300.0, 5.0), "veil": (0.0, 0.2, 0.002)},
                    ({"weight": 0.02, "sigma_px": 4.0}, {"weight": 0.02, "sigma_px": 15.0},
                     {"weight": 0.02, "sigma_px": 50.0}, {"veil": 0.01})),
    "multipath": ({"scale": (0.0, 3.0, 0.1)}, ({"scale": 1.0},)),
    "wiggling": ({"h3_amplitude": (0.0, 0.5, 0.01), "h3_phase_rad": (-math.pi, math.pi, 0.3)},
                 ({"h3_amplitude": 0.03, "h3_phase_rad": -2.0}, {"h3_amplitude": 0.03, "h3_phase_rad": 0.0},
                  {"h3_amplitude": 0.03, "h3_phase_rad": 2.0})),
    "range_offset": ({"path_m": (-2.0, 2.0, 0.01)}, ()),
    "fixed_pattern": ({"row_delay_s": (-2e-11, 2e-11, 1e-13), "col_delay_s": (-2e-11, 2e-11, 1e-13)}, ()),
    "amplitude_dependent": ({"error_m": (-0.5, 0.5, 0.01), "log10_amplitude_e": (0.0, 6.0, 0.2)},
                            ({"error_m": 0.02, "log10_amplitude_e": 2.5}, {"error_m": 0.02, "log10_amplitude_e": 3.5},
                             {"error_m": -0.02, "log10_amplitude_e": 3.0})),
    "lens_distortion": ({"k1": (-0.5, 0.5, 0.01), "k2": (-0.5, 0.5, 0.01)},
                        ({"k1": -0.1}, {"k1": 0.1}, {"k1": -0.25}, {"k1": 0.25})),
    "ambient": ({"irradiance_w_m2": (0.0, 2000.0, 1.0)}, ({"irradiance_w_m2": 5.0},)),
    "reflectance": ({"scale": (0.05, 20.0, 0.02)}, ()),
    "pose": ({"rx": (-0.05, 0.05, 1e-3), "ry": (-0.05, 0.05, 1e-3), "rz": (-0.05, 0.05, 1e-3),
              "tx": (-0.1, 0.1, 1e-3), "ty": (-0.1, 0.1, 1e-3), "tz": (-0.1, 0.1, 1e-3)}, ()),
}
assert set(DIAGNOSIS_LIBRARY) == set(ORDER)


def _off_value(effect: str, name: str) -> float:
    if name.startswith("log10_"):
        return math.log10(EFFECTS[effect].params[name[6:]].off)
    return EFFECTS[effect].params[name].off


def to_effect_values(effect: str, fitted: Mapping[str, float]) -> dict[str, float]:
    """Fitted parameters -> the effect's own parameter names (undo log scales)."""
    out: dict[str, float] = {}
    for k, v in fitted.items():
        if k.startswith("log10_"):
            out[k[6:]] = float(10.0 ** v)
        else:
            out[k] = float(v)
    return out


def session_setup_for(scene: Any, data: HeldOutData) -> Any:
    """The camera + sensor configuration of the session (``tofhil.sim.session_setup``): the
    session's recorded sensor configuration when it has one, else the session's frequencies,
    tap phases, integration time and camera with the rest from the scene."""
    from tofhil.sim.session_setup import session_setup

    return session_setup(scene.sensor, camera=data.camera, freq_hz=data.freq_hz, theta_rad=data.theta_rad,
                         integration_time_s=data.integration_time_s, recorded=data.sensor_config,
                         source=data.source)


def session_scene(scene: Any, data: HeldOutData) -> Any:
    """The scene set to the session's camera and sensor (see :func:`session_setup_for`)."""
    from tofhil.sim.session_setup import scene_for_setup

    return scene_for_setup(scene, session_setup_for(scene, data))


class TwinModel:
    """Predicts the measured channels for a set of extra effects on top of the base scene."""

    def __init__(self, scene: Any, data: HeldOutData, *, render_kwargs: Mapping[str, Any] | None = None,
                 cache_size: int = 8) -> None:
        from tofhil.sim.pipeline import sensor_config
        from tofhil.sim.sensor import SensorModel

        self.setup = session_setup_for(scene, data)
        self.scene = session_scene(scene, data)
        self.data = data
        self.base_effects = dict(self.scene.effects)
        self.base_bounces = int(self.scene.render.bounces)
        self.render_kwargs = dict(render_kwargs or {})
        if "harmonics" not in self.render_kwargs:
            # Render the 3rd harmonic explicitly: synthesising it from the fundamental is exact
            # only for single-path pixels, and wrong once stray light or multipath mixes paths
            # (the harmonic of a mixture is not the mixture of harmonics).
            from tofhil.sim.sensor import waveform_from_scene

            self.render_kwargs["harmonics"] = tuple(sorted(set(waveform_from_scene(scene)) | {1, 3}))
        self._renders: OrderedDict[tuple, tuple[Any, Any]] = OrderedDict()
        self._cache_size = cache_size
        # one sensor for all predictions (its fixed pattern is drawn once)
        self.sensor = SensorModel(sensor_config(self.scene), self.scene.camera)
        self._unit_ambient: np.ndarray | None = None
        self.extra_starts: dict[str, list[dict[str, float]]] = {}
        self.evaluations = 0

    # ---------------------------------------------------------------- library
    def library(self) -> dict[str, EffectSpec]:
        lib = {}
        for name in ORDER:
            ranges, starts = DIAGNOSIS_LIBRARY[name]
            params = []
            for pname, (lo, hi, scale) in ranges.items():
                off = self._base_value(name, pname)
                params.append(FitParam(pname, off, lo, hi, scale))
            lib[name] = EffectSpec(tuple(params), tuple(starts) + tuple(self.extra_starts.get(name, ())))
        return lib

    def align_pose(self, max_distance_m: float = 0.05) -> dict[str, float] | None:
        """A starting pose from point-to-plane ICP of the measured cloud onto the twin's.

        With the twin camera at P and the real one at P @ D, a point seen by both satisfies
        p_twin = D p_meas, so the ICP transform (measured -> twin) is the pose effect's D.
        Pixel-residual fits alone stall here: at depth edges the misfit changes in steps as
        samples cross the edge, and rotations trade off against translations.
        """
        from scipy.spatial.transform import Rotation

        from tofhil.eval.matching import icp

        nf = self.data.n_freq
        pred = self.predict({})
        mask = self.data.usable
        d_meas = depth_from_signal(self.data.s_train[:nf], self.data.freq_hz)
        d_twin = depth_from_signal(pred[:nf], self.data.freq_hz)
        cam = self.data.camera
        p_meas, p_twin = cam.points(d_meas, valid=mask), cam.points(d_twin, valid=mask)
        if len(p_meas) < 50 or len(p_twin) < 50:
            return None
        t = icp(p_meas, p_twin, max_distance_m).transformation
        rv = Rotation.from_matrix(t[:3, :3]).as_rotvec()
        start = {"rx": rv[0], "ry": rv[1], "rz": rv[2], "tx": t[0, 3], "ty": t[1, 3], "tz": t[2, 3]}
        lo_hi = DIAGNOSIS_LIBRARY["pose"][0]
        start = {k: float(np.clip(v, lo_hi[k][0], lo_hi[k][1])) for k, v in start.items()}
        # ICP's lateral components (x, y, roll) are poorly constrained when the view is mostly
        # one plane facing the camera; offer the start without them too and let the fit choose.
        self.extra_starts["pose"] = [start, dict(start, tx=0.0, ty=0.0, rz=0.0)]
        return start

    def _base_value(self, effect: str, pname: str) -> float:
        """Where a parameter starts: the base scene's value if it models the effect, else off."""
        base = self.base_effects.get(effect)
        if effect == "multipath" and pname == "scale" and base is None:
            return 1.0 if self.base_bounces > 0 else 0.0
        if base is not None:
            key = pname[6:] if pname.startswith("log10_") else pname
            if key in base:
                v = float(base[key])
                return math.log10(v) if pname.startswith("log10_") else v
        return _off_value(effect, pname)

    # ---------------------------------------------------------------- model
    def effects_for(self, active: EffectParams) -> dict[str, dict[str, Any]]:
        """The full effect set: the base scene's effects, overridden by the fitted ones."""
        eff: dict[str, dict[str, Any]] = {k: dict(v) for k, v in self.base_effects.items()}
        for name, fitted in active.items():
            # an effect the base lacks starts from its off values (not its "switched on"
            # defaults): parameters diagnosis does not fit must change nothing
            merged = dict(eff.get(name) or EFFECTS[name].off_values())
            merged.update(to_effect_values(name, fitted))
            eff[name] = merged
        needs_indirect = self.base_bounces > 0 or "multipath" in active
        if needs_indirect and "multipath" not in eff:
            eff["multipath"] = {"scale": 1.0 if self.base_bounces > 0 else 0.0}
        if needs_indirect:
            eff["multipath"].setdefault("bounces", max(2, self.base_bounces))
        return parse_effects(eff, source=self.scene.source)

    # Scene-stage effects that only scale light are applied to a cached render: the
    # reflectance scales the direct light by s and the (two-bounce dominated) indirect light
    # by s^2, ambient power is linear in the irradiance. Pose and lens distortion change the
    # geometry and re-render. The extended scene is re-rendered exactly for the final figures.
    _GEOMETRIC = ("pose", "lens_distortion")

    def _render(self, effects: Mapping[str, Mapping[str, Any]]) -> tuple[Any, Any]:
        from tofhil.sim.effects import apply_scene_effects
        from tofhil.sim.pipeline import render_arguments
        from tofhil.sim.render import render

        geo = {n: effects[n] for n in self._GEOMETRIC if n in effects}
        indirect = "multipath" in effects
        key = (tuple((n, tuple(sorted((k, repr(x)) for k, x in v.items()))) for n, v in geo.items()), indirect)
        hit = self._renders.get(key)
        if hit is None:
            # the base scene's own scene-stage effects are rendered in exactly
            render_effects = {n: v for n, v in self.base_effects.items() if EFFECTS[n].stage == "scene"}
            render_effects.update(geo)
            if indirect:
                render_effects["multipath"] = dict(effects["multipath"])
            render_effects = parse_effects(render_effects, source=self.scene.source)
            scene2 = apply_scene_effects(self.scene, render_effects)
            cache = self.scene.__dict__.get("_geometry_cache")
            if cache is not None:  # same objects: keep the Embree scene (only camera/materials moved)
                scene2.__dict__["_geometry_cache"] = cache
            result = render(scene2, **render_arguments(scene2, render_effects, self.render_kwargs))
            if "_geometry_cache" in scene2.__dict__ and "_geometry_cache" not in self.scene.__dict__:
                self.scene.__dict__["_geometry_cache"] = scene2.__dict__["_geometry_cache"]
            hit = (scene2, result)
            self._renders[key] = hit
            if len(self._renders) > self._cache_size:
                self._renders.popitem(last=False)
        else:
            self._renders.move_to_end(key)
        scene2, result = hit
        return scene2, self._scale_light(scene2, result, effects)

    def _factor(self, effects: Mapping[str, Mapping[str, Any]], name: str, key: str, neutral: float) -> float:
        return float(effects.get(name, {}).get(key, neutral))

    def _scale_light(self, scene2: Any, result: Any, effects: Mapping[str, Mapping[str, Any]]) -> Any:
        s = (self._factor(effects, "reflectance", "scale", 1.0)
             / self._factor(self.base_effects, "reflectance", "scale", 1.0))
        extra_ambient = (self._factor(effects, "ambient", "irradiance_w_m2", 0.0)
                         - self._factor(self.base_effects, "ambient", "irradiance_w_m2", 0.0))
        if s == 1.0 and extra_ambient == 0.0:
            return result
        changes: dict[str, Any] = {}
        if extra_ambient != 0.0:
            changes["ambient_power_w"] = result.ambient_power_w + extra_ambient * self._ambient_per_irradiance(scene2, result)
        ambient = changes.get("ambient_power_w", result.ambient_power_w)
        if s != 1.0:
            if result.phasor_direct is not None and result.phasor_indirect is not None:
                d, i = result.phasor_direct * s, result.phasor_indirect * (s * s)
                changes.update(phasor_direct=d, phasor_indirect=i, phasor=d + i)
                freq = np.asarray(result.freq_hz)
                h1 = tuple(result.harmonics).index(1)
                zero = np.flatnonzero(freq == 0.0)
                p_direct = (result.phasor_direct[zero[0], h1].real if zero.size
                            else np.minimum(np.abs(result.phasor_direct[0, h1]), result.power_w))
                changes["power_w"] = s * p_direct + s * s * (result.power_w - p_direct)
            else:
                changes.update(phasor=result.phasor * s, power_w=result.power_w * s)
            changes["ambient_power_w"] = ambient * s
        return dataclasses.replace(result, **changes)

    def _ambient_per_irradiance(self, scene2: Any, result: Any) -> np.ndarray:
        """Ambient power on each pixel per W/m^2 of ambient irradiance (the renderer is linear in it)."""
        e0 = float(scene2.ambient_irradiance_w_m2)
        if e0 > 0:
            return result.ambient_power_w / e0
        if self._unit_ambient is None:
            from tofhil.sim.render import render

            lit = dataclasses.replace(scene2, ambient_irradiance_w_m2=1.0)
            cache = scene2.__dict__.get("_geometry_cache")
            if cache is not None:
                lit.__dict__["_geometry_cache"] = cache
            kw = dict(self.render_kwargs)
            kw.update(freq_hz=[float(f) for f in self.data.freq_hz], bounces=0)
            self._unit_ambient = render(lit, **kw).ambient_power_w
        return self._unit_ambient

    def taps(self, active: EffectParams) -> tuple[np.ndarray, Any, Any]:
        """Noise-free taps ``[F, K, H, W]`` (DN), the rendered scene and its render."""
        from tofhil.sim.pipeline import optical_signal

        eff = self.effects_for(active)
        scene2, result = self._render(eff)
        signal = optical_signal(scene2, result, eff)
        return self.sensor.taps_dn(signal, noise=False).astype(np.float64), scene2, result

    def predict(self, active: EffectParams) -> np.ndarray:
        """Predicted channels ``[C, H, W]`` (S per frequency, then the offset if used)."""
        self.evaluations += 1
        taps, _, _ = self.taps(active)
        s = phasor(taps, self.data.theta_rad)
        if self.data.offset_channel:
            s = np.concatenate([s, taps.mean(axis=(0, 1))[None].astype(np.complex128)])
        return s

    def base_render(self) -> Any:
        return self._render(self.effects_for({}))[1]

    def extended_effects_block(self, active: EffectParams) -> dict[str, dict[str, Any]]:
        """The effects block of the extended scene (base effects plus the fitted ones)."""
        from tofhil.sim.effects import effects_to_block

        return effects_to_block(self.effects_for(active))
