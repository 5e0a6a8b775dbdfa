"""The twin's forward model: effect values -> render (cached) -> light on the sensor -> taps.

A :class:`Twin` is a scene with its resolved sensor configuration and a base effect set (the
scene's ``effects:`` block, or the one given). It predicts the noise-free taps, or noisy
frames, for any effect set; ``simulate`` and ``diagnose`` both go through it, so a frame
simulated and a frame predicted while fitting come from one model.

Each effect acts through the hook of its stage (``tofhil.sim.effects.STAGE_HOOKS``):

- scene stage: changes what is rendered. Renders are cached by content (a digest of the
  scene, of the scene-stage effect values rendered in and of the renderer's arguments, not
  of Python object identity; :func:`render_key` digests a scene after its effects). An effect whose change is exactly a rescaling of a render
  (reflectance, ambient) is applied to the cached render of the base values instead
  (``Effect.rescale_render``); when that is not exact it is rendered in.
- render stage: recombines a render's parts (multipath: direct + scale * indirect).
- signal and pixel stages: act on the light on the sensor in milliseconds.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from tofhil.content_cache import LRUCache
from tofhil.frames import RawFrame
from tofhil.progress import Progress
from tofhil.sim.effects import (EFFECTS, ORDER, Effect, EffectContext, ParsedEffects, WigglingEffect,
                                apply_scene_effects,
                                apply_tap_effects,
                                apply_signal_effects, effects_by_stage, parse_effects, render_requirements)
from tofhil.sim.memory import check_memory, render_memory
from tofhil.sim.optics import apply_lens
from tofhil.sim.render import content_key
from tofhil.sim.sensor import OpticalSignal, SensorConfig, SensorModel, waveform_from_scene

Effects = Mapping[str, Mapping[str, Any]]


def render_arguments(scene: Any, effects: Effects, render_kwargs: Mapping[str, Any] | None = None,
                     *, freq_hz: Iterable[float] | None = None) -> dict[str, Any]:
    """Arguments for ``render``: the sensor's frequencies, the harmonics the waveform and the
    wiggling effect need, and what render-stage effects require (separate direct/indirect and
    a 0 Hz channel carrying the direct power for the multipath effect)."""
    if freq_hz is None:
        from tofhil.sim.pipeline import sensor_config

        freq_hz = sensor_config(scene).freq_hz
    harm = set(waveform_from_scene(scene)) | {1}
    if "wiggling" in effects:
        harm |= set(WigglingEffect.harmonics(effects["wiggling"]))
    kw: dict[str, Any] = {"freq_hz": [float(f) for f in freq_hz], "harmonics": tuple(sorted(harm))}
    req = render_requirements(effects, scene)
    if req.get("separate_direct"):
        kw["freq_hz"] = kw["freq_hz"] + [0.0]
    kw.update(req)
    kw.update(dict(render_kwargs or {}))
    return kw


def render_key(scene: Any, render_args: Mapping[str, Any]) -> str:
    """What determines a render: the scene's geometry, materials, camera, pose, emitter,
    ambient light and render settings (after scene-stage effects) and the renderer's
    arguments (frequencies, harmonics, bounces, ...)."""
    return content_key(scene, {k: v for k, v in render_args.items() if k != "progress"})


def effect_context(scene: Any, camera: Any, config: SensorConfig, radial_m: np.ndarray | None = None) -> EffectContext:
    src = str(getattr(scene, "source", "<scene>"))
    base = Path(src).parent if Path(src).is_file() else None
    return EffectContext(camera=camera, sensor=config, source=src, base_dir=base, radial_m=radial_m,
                         emitter=getattr(scene, "emitter", None))


def readout(taps: np.ndarray, scene: Any, camera: Any, effects: Effects, config: SensorConfig) -> np.ndarray:
    """The taps as the readout records them: the taps-stage effects (per-tap gains and
    offsets) on the sensor's taps ``[F, K, ...]``; the same array when none is on."""
    if not any(EFFECTS[n].stage == "taps" and not EFFECTS[n].is_off(v) for n, v in effects.items()):
        return taps
    return apply_tap_effects(taps, effects, effect_context(scene, camera, config))


def with_readout(frame: RawFrame, scene: Any, effects: Effects, config: SensorConfig) -> RawFrame:
    """A raw frame through the taps-stage effects (the frame itself when none is on)."""
    taps = readout(frame.taps, scene, frame.camera, effects, config)
    return frame if taps is frame.taps else dataclasses.replace(frame, taps=taps)


_LAST_MASK: list = [None, 0, None]


def flat_index(mask: np.ndarray) -> np.ndarray:
    """``np.flatnonzero`` of a bool pixel mask, kept for the last mask asked for (a fit asks
    for the same pixels at every evaluation; a mask changed in place since is seen by its
    count of pixels)."""
    if _LAST_MASK[0] is mask and _LAST_MASK[1] == np.count_nonzero(mask):
        return _LAST_MASK[2]
    idx = np.flatnonzero(np.asarray(mask, dtype=bool).ravel())
    _LAST_MASK[:] = [mask, idx.size, idx]
    return idx


def signal_from_render(scene: Any, result: Any, effects: Effects, config: SensorConfig,
                       index: np.ndarray | None = None) -> OpticalSignal:
    """Light on the sensor from a render (scene-stage effects already in it): the render-stage
    hook recombines the render (or the render is taken as it is), then the signal- and
    pixel-stage hooks in forward-model order. ``index`` (flat pixel indices; every signal- and
    pixel-stage effect on must be pointwise, ``Effect.pointwise``): the light of those pixels
    only, as one row ``[..., 1, N]``, the effects run there alone."""
    camera = getattr(result, "camera", None) or scene.camera
    waveform = waveform_from_scene(scene)
    render_stage = effects_by_stage(effects, "render")
    if len(render_stage) > 1:  # each hook builds the signal from the render: they do not compose
        raise ValueError("at most one render-stage effect: " + ", ".join(e.name for e, _ in render_stage))
    # (some pixels of a plain render without a lens: taken there before the signal is made)
    gather_first = index is not None and not render_stage and getattr(camera, "lens", None) is None
    if render_stage:
        eff, values = render_stage[0]
        signal = eff.apply_render(result, values, waveform)
    else:
        signal = OpticalSignal.from_render(result, waveform, index=index if gather_first else None)
    signal = apply_lens(signal, camera)  # a lens prescription's vignetting, path and ghosts (else nothing)
    ctx = effect_context(scene, camera, config, getattr(result, "radial_m", None))
    if index is not None:
        if not gather_first:
            signal = signal.at(index)
        ctx = dataclasses.replace(ctx, pixels=index)
    return apply_signal_effects(signal, effects, ctx)


def _nbytes(value: Any) -> int:
    """The bytes of the arrays a render result holds (its own fields; the camera's are not
    counted)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return sum(getattr(value, f.name).nbytes for f in dataclasses.fields(value)
                   if isinstance(getattr(value, f.name), np.ndarray))
    return 0


def differential(taps: np.ndarray) -> np.ndarray:
    """The taps of a pixel that reads the difference of its two gates (the TOFcam635's DCS):
    ``(c_k - c_{k + K/2}) / 2`` of taps ``[F, K, ...]`` after the readout's own imbalance, so
    ``DCS_{k + K/2} = -DCS_k`` exactly (an odd number of taps: the taps less their mean). For a
    sinusoid both are the taps less their offset."""
    k = taps.shape[1]
    if k % 2:
        return taps - taps.mean(axis=1, keepdims=True)
    return 0.5 * (taps - np.roll(taps, k // 2, axis=1))


#: The bytes of unpinned renders a twin keeps by default (a memory bound; it decides nothing).
DEFAULT_CACHE_BYTES = 32 * 2 ** 20


class RenderCache(LRUCache):
    """Renders by content key, least recently used first out, except the pinned ones.

    Diagnosis renders its base twin first and comes back to it after every fit of a
    scene-stage effect (a pose fit renders dozens of poses in a row): the base render is
    pinned (at most :attr:`max_pinned` renders are), so those fits do not evict it. A cache
    may be shared by several twins of one scene (keys are by content, not by twin).

    The unpinned renders are bounded both in number (``size``) and in bytes (``max_bytes``;
    the newest is always kept): at camera resolution a render is 20-60 MB, and the renders
    of a scene-stage fit (one per evaluation, with stray light in the set) are almost never
    asked for again, except the last (the fitted values, predicted once more).
    """

    def __init__(self, size: int = 8, max_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        super().__init__(size, max_bytes, nbytes=_nbytes, max_pinned=4)


class Twin:
    """A scene, its resolved sensor configuration and a base effect set: the forward model.

    ``sensor`` defaults to the scene's interpreted ``sensor:`` block; ``effects`` (the base
    effect set, what the scene models) to its ``effects:`` block. ``render_kwargs`` are
    passed to every render (e.g. harmonics to compute explicitly). Renders are kept in a
    least-recently-used cache of ``cache_size`` entries and ``cache_bytes`` keyed by content
    (the render of the base effect set pinned: :class:`RenderCache`), or in ``cache``, one shared with other
    twins of the same scene; the scene is treated as immutable (derive changed scenes with
    ``dataclasses.replace``).
    """

    def __init__(self, scene: Any, *, sensor: SensorConfig | None = None, effects: Mapping[str, Any] | None = None,
                 render_kwargs: Mapping[str, Any] | None = None, cache_size: int = 8,
                 progress: Progress | None = None, frames_kept: int = 0, cache: RenderCache | None = None,
                 cache_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        from tofhil.sim.pipeline import resolve_effects, sensor_config

        self.scene = scene
        self.config = sensor if sensor is not None else sensor_config(scene)
        self.base_effects = resolve_effects(scene, effects)
        self.render_kwargs = dict(render_kwargs or {})
        self.progress = progress
        self.frames_kept = frames_kept  # frames a caller holds at once (for the memory check)
        self.cache_size = cache_size
        self.cache = cache if cache is not None else RenderCache(cache_size, cache_bytes)
        # Renders of some pixels (a fit's; each Jacobian column of a scene-stage parameter is
        # a new one): few are ever asked for again, and each holds full-frame arrays.
        self.pixel_cache = RenderCache(2)
        self._sensors: dict[Any, SensorModel] = {}
        self.renders = 0  # renders traced (cache misses)
        #: The device reads each tap as the difference of a pixel's two storage nodes (the
        #: TOFcam635's DCS): no common-mode offset reaches its taps, so the twin's taps lose
        #: theirs before the readout's per-tap gains act on them.
        self.differential_readout = False
        self._base_render_bounces = int(scene.render.bounces)
        # The scene's content is hashed once (scenes are not changed in place): a render's key
        # is this digest, the scene-stage effect values rendered in, and the render arguments.
        self._scene_key = content_key(scene)

    # ------------------------------------------------------------------ effect sets
    def effects(self, overrides: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, dict[str, Any]]:
        """The base effect set with some effects' parameters overridden (validated): what
        diagnosis predicts while fitting.

        An effect the base lacks starts from its off values, not its "switched on" defaults:
        parameters not overridden change nothing. The indirect light is made explicit: a scene
        that renders bounces gets ``multipath`` at scale 1, and overriding ``multipath`` asks
        for a render with separate direct and indirect light (at least 2 bounces)."""
        overrides = overrides or {}
        eff: dict[str, dict[str, Any]] = {k: dict(v) for k, v in self.base_effects.items()}
        for name, values in overrides.items():
            merged = dict(eff.get(name) or EFFECTS[name].off_values())
            merged.update(values)
            eff[name] = merged
        bounces = self._base_render_bounces
        if "multipath" in overrides or bounces > 0:
            if "multipath" not in eff:
                eff["multipath"] = {"scale": 1.0 if bounces > 0 else 0.0}
            eff["multipath"].setdefault("bounces", max(2, bounces))
        return parse_effects(eff, source=getattr(self.scene, "source", "<scene>"))

    def current_value(self, effect: str, param: str) -> float:
        """A parameter's value in the base effect set: what the scene models (a scene that
        renders indirect light has multipath at scale 1), else the parameter's off value."""
        base = self.base_effects.get(effect)
        if base is not None and param in base:
            return float(base[param])
        if effect == "multipath" and param == "scale":
            return 1.0 if self._base_render_bounces > 0 else 0.0
        return EFFECTS[effect].params[param].off

    def _resolve(self, effects: Effects | None) -> Effects:
        """The base set for None, else the given set validated (parameters not given take
        their defaults, as in a scene file)."""
        if effects is None:
            return self.base_effects
        if isinstance(effects, ParsedEffects):
            return effects
        return parse_effects(effects, source=getattr(self.scene, "source", "<scene>"))

    # ------------------------------------------------------------------ render (cached)
    def pixel_local(self, effects: Effects | None = None) -> bool:
        """True when the light of every pixel of this effect set follows from that pixel's
        render alone (no effect that moves light between pixels is on, no lens prescription
        with ghosts): a prediction on some pixels then needs only those pixels rendered."""
        return self._every_effect(effects, "pixel_local")

    def pointwise(self, effects: Effects | None = None) -> bool:
        """True when, given the whole frame's render, every effect of the set computes a
        pixel's light from that pixel's alone (``Effect.pointwise``; no lens prescription): a
        prediction on some pixels then runs the effects on those pixels only."""
        return self._every_effect(effects, "pointwise")

    def _every_effect(self, effects: Effects | None, prop: str) -> bool:
        """Every effect of the set on is ``prop`` (and no lens prescription mixes the pixels)."""
        if getattr(self.scene.camera, "lens", None) is not None:
            return False
        return all(getattr(EFFECTS[n], prop) or EFFECTS[n].is_off(v) for n, v in self._resolve(effects).items())

    def render(self, effects: Effects | None = None, *, pixels: np.ndarray | None = None) -> tuple[Any, Any]:
        """``(scene with the rendered scene-stage effects, RenderResult)`` for an effect set
        (default the base set). A scene-stage effect with a fast path (``rescale_render``)
        whose values differ from the base's is applied to the cached render of the base
        values; when that is not exact, or for the other scene-stage effects, the values are
        rendered in. ``pixels`` (bool ``[H, W]``): only these pixels are needed (the render
        may trace only them, the others are then dark; a full render in the cache serves too)."""
        eff = self._resolve(effects)
        rendered: dict[str, Mapping[str, Any]] = {}
        rescaled: list[tuple[Effect, Mapping[str, Any], Mapping[str, Any]]] = []
        for name in ORDER:
            e = EFFECTS[name]
            if e.stage != "scene" or (name not in eff and name not in self.base_effects):
                continue
            target = eff.get(name) or e.off_values()
            base = self.base_effects.get(name) or e.off_values()
            if target != base and type(e).rescale_render is not Effect.rescale_render:
                rescaled.append((e, target, base))
                if name in self.base_effects:
                    rendered[name] = base
            elif name in eff:
                rendered[name] = target
        if rescaled:
            scene2, result = self._cached_render(rendered, eff, pixels)
            for e, target, base in rescaled:
                result = e.rescale_render(result, target, base, scene2)
                if result is None:
                    break
            else:
                return scene2, result
            rendered = {name: eff[name] for name in ORDER if name in eff and EFFECTS[name].stage == "scene"}
        return self._cached_render(rendered, eff, pixels)

    def _cached_render(self, scene_effects: Effects, effects: Effects,
                       pixels: np.ndarray | None = None) -> tuple[Any, Any]:
        from tofhil.sim.render import render

        scene2 = apply_scene_effects(self.scene, scene_effects)
        args = render_arguments(scene2, effects, self.render_kwargs, freq_hz=self.config.freq_hz)
        key = content_key(self._scene_key, scene_effects, args)
        hit = self.cache.get(key)
        if hit is not None:
            # (the scene of this twin: a shared cache's entry may come from another twin
            # whose scene differs in what a render does not read, e.g. its source path)
            return scene2, hit
        if pixels is not None:
            # a render of some pixels: its own entry (the full render, when cached, serves first)
            key = content_key(key, "pixels", np.packbits(np.asarray(pixels, dtype=bool)))
            hit = self.pixel_cache.get(key)
            if hit is not None:
                return scene2, hit
            args = dict(args, pixels=pixels)
        # Refuse, before anything is allocated, a job whose estimated memory (the render, the
        # sensor and the frames held at once) exceeds what the machine has.
        signal_effects = any(EFFECTS[n].stage in ("signal", "pixel", "taps") for n in effects)
        check_memory(render_memory(scene2, args, frames_kept=self.frames_kept, signal_effects=signal_effects),
                     source=str(getattr(scene2, "source", "")) or None)
        result = render(scene2, progress=self.progress, **args)
        self.renders += 1
        if pixels is not None:
            self.pixel_cache.put(key, result)
            return scene2, result
        # A whole frame ends a fit on some pixels (its fitted values predicted) or is one of a
        # fit on whole frames: the renders of some pixels are not asked for again (the next
        # fit's values differ) and hold whole-frame arrays.
        self.pixel_cache.clear()
        base = {n: v for n, v in self.base_effects.items() if EFFECTS[n].stage == "scene"}
        self.cache.put(key, result, pin=scene_effects == base)
        return scene2, result

    # ------------------------------------------------------------------ light and taps
    def signal(self, effects: Effects | None = None, *, pixels: np.ndarray | None = None) -> OpticalSignal:
        """Light on the sensor for an effect set (default the base set; a given set replaces
        it, see :meth:`effects` for the base set with some parameters changed). ``pixels``
        (bool ``[H, W]``): only these pixels' light is needed; when every effect of the set is
        pixel-local only they are rendered (the others are then wrong), else the whole frame."""
        eff = self._resolve(effects)
        if pixels is not None and not self.pixel_local(eff):
            pixels = None
        scene2, result = self.render(eff, pixels=pixels)
        return signal_from_render(scene2, result, eff, self.config)

    def sensor(self, camera: Any | None = None) -> SensorModel:
        """The sensor model for a camera (default the scene's); its fixed pattern is drawn once."""
        camera = self.scene.camera if camera is None else camera
        model = self._sensors.get(camera)
        if model is None:
            model = self._sensors[camera] = SensorModel(self.config, camera)
        return model

    def expected_taps(self, effects: Effects | None = None, *, pixels: np.ndarray | None = None) -> np.ndarray:
        """Noise-free taps in DN ``[F, K, H, W]`` (float32, as in a frame); ``pixels`` see
        :meth:`signal`."""
        return self._readout(self.sensor().taps_dn(self.signal(effects, pixels=pixels), noise=False), effects)

    def expected_taps_at(self, effects: Effects | None, pixels: np.ndarray) -> np.ndarray:
        """:meth:`expected_taps` on the pixels of a bool mask ``[H, W]`` only, as ``[F, K, 1,
        N]`` (row-major order of the mask; rendered only there when that is exact, and the
        effects run only there when they are pointwise)."""
        index = flat_index(pixels)
        eff = self._resolve(effects)
        if self.pointwise(eff):
            scene2, result = self.render(eff, pixels=pixels if self.pixel_local(eff) else None)
            signal = signal_from_render(scene2, result, eff, self.config, index=index)
            taps = self.sensor()._noise_free_taps(signal, index, signal_at_index=True)
        else:
            taps = self.sensor()._noise_free_taps(self.signal(effects, pixels=pixels), index)
        return self._readout(taps, effects)

    def _readout(self, taps: np.ndarray, effects: Effects | None) -> np.ndarray:
        """:func:`readout` of the twin's taps; an effect set naming no taps-stage effect is not
        validated a second time (a fit predicts thousands of times)."""
        names = self.base_effects if effects is None else effects
        if any(EFFECTS[n].stage == "taps" for n in names if n in EFFECTS):
            taps = readout(taps, self.scene, self.scene.camera, self._resolve(effects), self.config)
        return differential(taps) if self.differential_readout else taps

    def frames(self, effects: Effects | None = None, frames: int = 1, *, seed: int = 0, noise: bool = True,
               meta: Mapping[str, Any] | None = None, first_index: int = 0) -> Iterable[RawFrame]:
        """``frames`` raw frames of one (fixed) light with independent noise per frame. The
        frames carry the camera the render used (a lens_distortion effect shows in it)."""
        eff = self._resolve(effects)
        scene2, result = self.render(eff)
        signal = signal_from_render(scene2, result, eff, self.config)
        sensor = self.sensor(getattr(result, "camera", None) or scene2.camera)
        for i in range(first_index, first_index + frames):
            yield with_readout(sensor.expose(signal, seed=seed, frame_index=i, noise=noise, meta=dict(meta or {})),
                               scene2, eff, self.config)


__all__ = ["RenderCache", "Twin", "effect_context", "render_arguments", "render_key", "signal_from_render"]
