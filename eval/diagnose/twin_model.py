"""The held-out channels of the twin: effect parameters -> what diagnosis compares with data.

The forward model is the simulator's (:class:`tofhil.sim.twin.Twin`, set to the session's
camera, frequencies, tap phases and integration time); this module only says what is
measured: the noise-free taps are turned into the same channels as the measurement (``S``
per frequency, and the tap offset when it is used), on the session's pixels.

Which parameters diagnosis fits, their ranges, optimiser steps, log scales and multi-start
points are the effect library's ``Param`` fields (``tofhil.sim.effects``): :func:`fit_library`
reads them. A parameter without a fit range keeps its current value (a random per-pixel
delay pattern, for example, cannot be predicted without its seed, so only the clock
gradients are fitted). Log-scale parameters are fitted as ``log10_<name>``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping

import numpy as np

from tofhil.content_cache import LRUCache
from tofhil.demod import phasor
from tofhil.eval.diagnose.heldout import HeldOutData, depth_from_signal
from tofhil.eval.diagnose.selection import EffectParams, EffectSpec, FitParam
from tofhil.sim.effects import EFFECTS, ORDER, Param, ParsedEffects, PoseEffect, RangeOffsetMapEffect

LOG_PREFIX = "log10_"
#: Huber's constant for the profiled gain's M-estimate, in units of the log ratios' spread: 95 %
#: efficiency where the ratios scatter normally, a bounded pull from pixels the model misses.
HUBER_K = 1.345
#: Newton steps of that estimate (it converges in a few; the bound only guards a degenerate set).
MAX_GAIN_ITERATIONS = 50


def fitted_name(name: str, p: Param) -> str:
    return LOG_PREFIX + name if p.log else name


def to_fitted(p: Param, value: float) -> float:
    return math.log10(value) if p.log else float(value)


def to_effect_values(effect: str, fitted: Mapping[str, Any]) -> dict[str, Any]:
    """Fitted parameters -> the effect's own parameter names (undo log scales, wrap angles
    into their period); a closed-form fit's values (a map, its file) pass through."""
    out: dict[str, Any] = {}
    params = EFFECTS[effect].params if effect in EFFECTS else {}
    for k, v in fitted.items():
        if isinstance(v, (np.ndarray, str)):
            out[k] = v
        elif k.startswith(LOG_PREFIX):
            out[k[len(LOG_PREFIX):]] = float(10.0 ** v)
        elif k in params and params[k].periodic:
            p = params[k]
            out[k] = float(p.lo + (v - p.lo) % (p.hi - p.lo))
        else:
            out[k] = float(v)
    return out


def _spec(name: str, form: str, params: Mapping[str, Param], current: Callable[[str, str], float] | None,
          extra: list[dict[str, float]]) -> EffectSpec:
    fps = []
    for k, p in params.items():
        value = p.off if current is None else current(name, k)
        assert p.fit is not None
        lo, hi = p.fit
        if p.periodic:  # half a period beyond each end, so that a fit near the wrap can cross it
            lo, hi = lo - (hi - lo) / 2, hi + (hi - lo) / 2
        fps.append(FitParam(fitted_name(k, p), to_fitted(p, value), lo, hi, p.step, periodic=p.periodic))
    first = {fitted_name(k, p): to_fitted(p, p.start) for k, p in params.items() if p.start is not None}
    starts: list[dict[str, float]] = [first] if first else []
    for k, p in params.items():
        for v in p.starts:
            starts.append({**first, fitted_name(k, p): to_fitted(p, v)})
    names = {fp.name for fp in fps}
    starts += [s for s in extra if set(s) <= names]
    eff = EFFECTS[name]
    rough = None
    if form and eff.roughness(form, {}) is not None:
        def rough(values: Mapping[str, float]) -> np.ndarray:
            return eff.roughness(form, to_effect_values(name, values))
    return EffectSpec(tuple(fps), tuple(starts), form=form, roughness=rough)


def fit_library(current: Callable[[str, str], float] | None = None,
                extra_starts: Mapping[str, list[dict[str, float]]] | None = None,
                n_taps: int | None = None, n_freq: int | None = None) -> dict[str, EffectSpec]:
    """What diagnosis fits, per effect, from the ``Param`` table: each fitted parameter's
    current value (``current(effect, param)``, default its off value), range and step, and
    the multi-start points (``Param.start`` for all, then each ``Param.starts`` value in
    turn with the others at their start), plus ``extra_starts`` (e.g. from an alignment).

    Each effect's simple form, with its flexible forms (``Effect.forms``) attached; with
    ``n_taps`` given, parameters those taps cannot see (a harmonic that does not alias onto
    the fundamental) are left out, and a form left without parameters is dropped."""
    lib = {}
    for name in ORDER:
        eff = EFFECTS[name]
        extra = list((extra_starts or {}).get(name, ()))
        specs = [_spec(name, form, eff.form_params(form, n_taps, n_freq), current, extra)
                 for form in ("", *eff.forms)]
        if eff.params and n_freq is not None and not any(
                eff.form_params(form, n_taps, n_freq) for form in ("", *eff.forms)):
            continue  # nothing of it acts on these data (a second frequency's phase, one frequency)
        # (a form whose parameters these taps cannot see is dropped; the first form left is the
        # simplest the data can show: 3 taps see the 5th and 7th harmonics, not the 3rd)
        specs = [s for s in specs if s.params] or specs[:1]
        lib[name] = dataclasses.replace(specs[0], forms=tuple(specs[1:]), closed_form=CLOSED_FORM.get(name),
                                        generic=eff.generic)
    return lib


def _fit_offset_map(model: Any, data: HeldOutData, current: EffectParams,
                    penalty_per_dof: float) -> tuple[dict[str, Any], float, dict[str, Any]]:
    from tofhil.eval.diagnose.linear_forms import fit_offset_map

    m = fit_offset_map(model, data, current, penalty_per_dof)
    return {"values": m.map_m}, m.dof, m.summary()


#: Effects fitted in closed form rather than by the optimiser (``EffectSpec.closed_form``).
CLOSED_FORM = {RangeOffsetMapEffect.name: _fit_offset_map}


def session_setup_for(scene: Any, data: HeldOutData) -> Any:
    """The camera + sensor configuration of the session (``tofhil.sim.session_setup``): the
    session's recorded sensor configuration when it has one, else the session's frequencies,
    tap phases, integration time and camera with the rest from the scene."""
    from tofhil.sim.session_setup import session_setup

    setup = session_setup(scene.sensor, camera=data.camera, freq_hz=data.freq_hz, theta_rad=data.theta_rad,
                          integration_time_s=data.integration_time_s, recorded=data.sensor_config,
                          source=data.source)
    fp = setup.sensor.fixed_pattern
    if data.bin_px > 1 and data.sensor_shape is not None and (fp.prnu > 0 or fp.dsnu_e > 0) and fp.binned is None:
        # the binned data hold each bin's mean of the sensor's pattern: the twin's pixels too
        fp = dataclasses.replace(fp, binned=(data.bin_px, *data.sensor_shape))
        setup = dataclasses.replace(setup, sensor=dataclasses.replace(setup.sensor, fixed_pattern=fp))
    return setup


#: Most render samples per bin of a binned diagnosis (see :func:`session_scene`).
MAX_BIN_SAMPLES = 48
#: The bytes of renders a diagnosis keeps (a cost bound, it decides nothing). Every round tests
#: each scene-stage form's signature by rendering the same perturbations of its off values,
#: whole frames once stray light is in the model: at 170 x 170 bins a round's cycle is about
#: 50 renders of 2 MB, which a budget of 8 renders rendered again every round (at 512 x 512,
#: 90 of 166 whole-frame renders were repeats: 28 of 86 s of render time).
RENDER_CACHE_BYTES = 192 * 2 ** 20


def session_scene(scene: Any, data: HeldOutData) -> Any:
    """The scene set to the session's camera and sensor (see :func:`session_setup_for`)."""
    from tofhil.sim.session_setup import scene_for_setup

    out = scene_for_setup(scene, session_setup_for(scene, data))
    if data.bin_px > 1:
        # A binned pixel is the mean of bin_px^2 pixels: the twin samples it as densely as the
        # scene samples the sensor's pixels, up to MAX_BIN_SAMPLES a bin (a render budget: 144
        # at 1024 x 1024 cost 2.6 x the CPU of 44 and found the same). What sampling error is
        # left, against a noise bin_px times below a pixel's, is measured and added to the
        # noise (TwinModel.sampling_variance).
        spp = min(out.render.samples_per_pixel * data.bin_px ** 2, max(MAX_BIN_SAMPLES, out.render.samples_per_pixel))
        out = dataclasses.replace(out, render=dataclasses.replace(out.render, samples_per_pixel=spp))
    return out


class TwinModel:
    """Predicts the measured channels for a set of extra effects on top of the base scene
    (a :class:`~tofhil.eval.diagnose.selection.ForwardModel`)."""

    def __init__(self, scene: Any, data: HeldOutData, *, render_kwargs: Mapping[str, Any] | None = None,
                 cache_size: int = 96, renders_from: "TwinModel | None" = None, sensor: Any = None) -> None:
        """``renders_from``: a model of the same scene whose renders to share (the extended
        scene of a diagnosis renders what the base twin already rendered, unless a
        scene-stage effect was fitted). ``sensor``: the sensor to predict with instead of the
        session's (a diagnosis's twin with its signal scale fitted, :mod:`signal_scale`)."""
        from tofhil.sim.sensor import waveform_from_scene
        from tofhil.sim.twin import Twin

        self.setup = session_setup_for(scene, data)
        self.scene = session_scene(scene, data)
        self._given_scene = scene
        if sensor is not None:
            self.scene = dataclasses.replace(self.scene, sensor=sensor)
            self.setup = dataclasses.replace(self.setup, sensor=sensor)
        self.data = data
        kwargs = dict(render_kwargs or {})
        if "harmonics" not in kwargs:
            # Render the 3rd harmonic explicitly: synthesising it from the fundamental is exact
            # only for single-path pixels, and wrong once stray light or multipath mixes paths
            # (the harmonic of a mixture is not the mixture of harmonics).
            kwargs["harmonics"] = tuple(sorted(set(waveform_from_scene(scene)) | {1, 3}))
        self.twin = Twin(self.scene, render_kwargs=kwargs, cache_size=cache_size, cache_bytes=RENDER_CACHE_BYTES,
                         cache=renders_from.twin.cache if renders_from is not None else None)
        self.twin.differential_readout = bool(getattr(data, "differential_taps", False))
        self.extra_starts: dict[str, list[dict[str, float]]] = {}
        self.evaluations = 0
        #: Profile the device's signal gain out of every prediction (:meth:`gain`): set where
        #: the scale was fitted (``signal_scale``), since there a global gain is a nuisance.
        self.profile_gain = False
        self._log_ratio_scale: float | None = None
        self._measured = LRUCache(4)

    # ---------------------------------------------------------------- library
    def library(self) -> dict[str, EffectSpec]:
        def current(effect: str, param: str) -> float:
            return self.twin.current_value(effect, param)

        return fit_library(current, self.extra_starts, n_taps=len(self.data.theta_rad), n_freq=self.data.n_freq)

    def align_pose(self, max_distance_m: float = 0.05) -> dict[str, float] | None:
        """A starting pose from point-to-plane ICP of the measured cloud onto the twin's.

        With the twin camera at P and the real one at P @ D, a point seen by both satisfies
        p_twin = D p_meas, so the ICP transform (measured -> twin) is the pose effect's D.
        Pixel-residual fits alone stall here: at depth edges the misfit changes in steps as
        samples cross the edge, and rotations trade off against translations.
        """
        from scipy.spatial.transform import Rotation

        from tofhil.eval.metrics.matching import icp

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
        params = EFFECTS[PoseEffect.name].params
        # Open3D's ICP sums its normal equations over threads in no fixed order, so its last
        # digits differ from run to run; a start rounded to 1e-6 (rad, m) is repeatable.
        start = {k: round(float(np.clip(v, *(params[k].fit or (-np.inf, np.inf)))), 6) for k, v in start.items()}
        # ICP's lateral components (x, y, roll) are poorly constrained when the view is mostly
        # one plane facing the camera; offer the start without them too and let the fit choose.
        self.extra_starts[PoseEffect.name] = [start, dict(start, tx=0.0, ty=0.0, rz=0.0)]
        return start

    # ---------------------------------------------------------------- model
    def effects_for(self, active: EffectParams) -> dict[str, dict[str, Any]]:
        """The full effect set: the base scene's effects, overridden by the fitted ones."""
        return self.twin.effects({name: to_effect_values(name, fitted) for name, fitted in active.items()})

    def taps(self, active: EffectParams, pixels: np.ndarray | None = None) -> np.ndarray:
        """Noise-free taps ``[F, K, H, W]`` (DN); ``pixels``: see :meth:`predict`."""
        return self.twin.expected_taps(self.effects_for(active), pixels=pixels).astype(np.float64)

    #: :meth:`predict` takes ``pixels`` (a fit asks only for its pixels).
    predicts_pixels = True

    def sampling_variance(self) -> np.ndarray:
        """The variance per real component ``[C, H, W]`` of the base prediction's own Monte
        Carlo error: the same twin rendered with an independent placement of its samples (the
        render seed's per-pixel shift), ``|p1 - p0|^2 / 4`` pooled as the noise is."""
        from tofhil.eval.metrics.noise import pooled_variance

        # (from the scene as given: set to the session again, it takes the same samples)
        given = self._given_scene
        render = dataclasses.replace(given.render, seed=given.render.seed + 1)
        other = TwinModel(dataclasses.replace(given, render=render), self.data, sensor=self.scene.sensor)
        other.profile_gain, other._log_ratio_scale = self.profile_gain, self._log_ratio_scale
        return pooled_variance(np.abs(other.predict({}) - self.predict({})) ** 2 / 4.0)

    def predict(self, active: EffectParams, pixels: np.ndarray | None = None) -> np.ndarray:
        """Predicted channels ``[C, H, W]`` (S per frequency, then the offset if used).
        ``pixels`` (bool ``[H, W]``): only these pixels are needed (a fit's); the others may
        then be wrong (the twin renders only the pixels asked for when that is exact)."""
        self.evaluations += 1
        if pixels is not None:
            return self._predict_at(self.effects_for(active), pixels)
        taps = self.taps(active)
        s = phasor(taps, self.data.theta_rad)
        if self.data.offset_channel:
            s = np.concatenate([s, taps.mean(axis=(0, 1))[None].astype(np.complex128)])
        return self._profiled(s, np.ones(self.data.camera.shape, dtype=bool))

    # ---------------------------------------------------------------- gain
    def _profiled(self, s: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """``s`` times the gain that brings it closest to the measured signal (when profiled)."""
        if not self.profile_gain:
            return s
        g = self._gain_of(s, pixels)
        if g == 1.0:
            return s
        out = s.copy()
        nf = self.data.n_freq
        out[:nf] *= g
        if self.data.offset_channel:
            # the offset above the black level scales with the same conversion gain
            black = float(getattr(self.scene.sensor, "black_level_dn", 0.0))
            out[nf] = black + g * (out[nf] - black)
        return out

    def _log_ratios(self, s: np.ndarray, pixels: np.ndarray) -> np.ndarray | None:
        """``log(|S_measured| / |S_predicted|)`` over the fit pixels in ``pixels`` (the frequencies
        averaged), or None where fewer than 20 pixels hold both."""
        nf = self.data.n_freq
        use = self.data.fit_pixels & pixels
        meas = self._measured_magnitude(use)
        pred = np.abs(s[:nf][:, use]).mean(axis=0)
        ok = (meas > 0) & (pred > 0)
        return np.log(meas[ok] / pred[ok]) if ok.sum() >= 20 else None

    def _measured_magnitude(self, use: np.ndarray) -> np.ndarray:
        """``|S_measured|`` of the training frames on the pixels of ``use``, the frequencies
        averaged: kept for the last few masks (every prediction of a fit profiles its gain on
        the same pixels)."""
        key = (id(self.data.s_train), np.packbits(use).tobytes())
        meas = self._measured.get(key)
        if meas is None:
            meas = np.abs(self.data.s_train[:self.data.n_freq][:, use]).mean(axis=0)
            self._measured.put(key, meas)
        return meas

    @staticmethod
    def _robust_spread(lr: np.ndarray) -> float:
        return max(1.4826 * float(np.median(np.abs(lr - np.median(lr)))), 1e-6)

    def _gain_of(self, s: np.ndarray, pixels: np.ndarray) -> float:
        """The device gain profiled out of a prediction: Huber's M-estimate of the location of
        ``log(|S_measured| / |S_predicted|)`` over the fit pixels the prediction holds, the
        scale of the log ratios fixed by the base twin's. Where the scale is fitted a global
        gain cannot be told from it (``signal_scale``), and a cause that adds or removes light
        everywhere (a stray-light veil, an unseen reflector) must not be charged for the gain
        that the scale, fitted once on the base twin, took up: its prediction gets its own
        (the profile likelihood of a nuisance parameter). An M-estimate rather than the median
        is a smooth function of the prediction, which a least-squares fit differentiates."""
        lr = self._log_ratios(s, pixels)
        if lr is None:
            return 1.0
        if self._log_ratio_scale is None:
            # the base twin had too few pixels: this prediction's spread, fixed from now on
            self._log_ratio_scale = self._robust_spread(lr)
        k = HUBER_K * self._log_ratio_scale
        mu = float(np.median(lr))
        for _ in range(MAX_GAIN_ITERATIONS):
            r = lr - mu
            inside = np.abs(r) <= k
            step = float(np.sum(np.clip(r, -k, k))) / max(int(inside.sum()), 1)
            mu += step
            if abs(step) < 1e-12:
                break
        return float(np.exp(mu))

    def enable_gain_profile(self) -> None:
        """Profile the gain out of every prediction from now on (:meth:`_gain_of`), the spread
        of the log ratios fixed at the base twin's, so the estimate is smooth in the prediction."""
        self.profile_gain = False
        lr = self._log_ratios(self.predict({}), np.ones(self.data.camera.shape, dtype=bool))
        if lr is not None:
            self._log_ratio_scale = self._robust_spread(lr)
        self.profile_gain = True

    def gain(self, active: EffectParams) -> float:
        """The gain :meth:`predict` applies to ``active``'s prediction (1 when not profiled)."""
        if not self.profile_gain:
            return 1.0
        saved, self.profile_gain = self.profile_gain, False
        try:
            s = self.predict(active)
        finally:
            self.profile_gain = saved
        return self._gain_of(s, np.ones(self.data.camera.shape, dtype=bool))

    def predicts_alone(self, active: EffectParams) -> bool:
        """True when :meth:`predict` on some pixels renders only those (no effect of the set
        moves light between pixels): else a prediction anywhere is a whole frame's."""
        return self.twin.pixel_local(self.effects_for(active))

    def _predict_at(self, effects: dict[str, dict[str, Any]], pixels: np.ndarray, *,
                    profile: bool = True) -> np.ndarray:
        """The taps and the signal only where asked (the rest of the frame stays zero)."""
        taps = self.twin.expected_taps_at(effects, pixels).astype(np.float64)
        s = phasor(taps, self.data.theta_rad)[:, 0]
        if self.data.offset_channel:
            s = np.concatenate([s, taps.mean(axis=(0, 1))[None, 0].astype(np.complex128)])
        from tofhil.sim.twin import flat_index

        out = np.zeros((s.shape[0],) + self.data.camera.shape, dtype=np.complex128)
        out.reshape(s.shape[0], -1)[:, flat_index(pixels)] = s
        return self._profiled(out, pixels) if profile else out

    def predict_local(self, active: EffectParams, pixels: np.ndarray) -> np.ndarray | None:
        """:meth:`predict` on ``pixels`` with the effects that move light between pixels (stray
        light) left out, so that only ``pixels`` are rendered; None when the set has none, or
        when a lens prescription makes every pixel's light depend on the others. A fit that
        holds those effects adds their part at its start as a constant (``selection.fit``)."""
        effects = self.effects_for(active)
        moving = [n for n, v in effects.items() if not EFFECTS[n].pixel_local and not EFFECTS[n].is_off(v)]
        if not moving or getattr(self.scene.camera, "lens", None) is not None:
            return None
        self.evaluations += 1
        # not profiled: without the light moved between pixels its amplitude ratios are not the
        # device's gain (a dark square lit mostly by stray light), and the fit adds this part's
        # change to the whole (profiled) prediction at its start
        return self._predict_at(ParsedEffects({n: v for n, v in effects.items() if n not in moving}), pixels,
                                profile=False)

    def base_render(self) -> Any:
        return self.twin.render(self.effects_for({}))[1]

    def extended_effects_block(self, active: EffectParams) -> dict[str, dict[str, Any]]:
        """The effects block of the extended scene (base effects plus the fitted ones)."""
        from tofhil.sim.effects import effects_to_block

        return effects_to_block(self.effects_for(active))
