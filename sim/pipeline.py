"""The twin's forward model end to end: scene -> render -> effects -> sensor -> frames/session.

``simulate`` renders once and then exposes every frame with independent noise (the light does
not change between frames; only shot and read noise do). ``forward`` turns a cached render
into one frame with given effects: this is what diagnosis calls while fitting parameters of
render-, signal- and pixel-stage effects. Scene-stage effects (pose, lens distortion,
reflectance, ambient) change what is rendered: ``prepare_render`` applies them and renders.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from tofhil.frames import RawFrame
from tofhil.progress import Progress
from tofhil.sim.effects import (EFFECTS, EffectContext, WigglingEffect, apply_scene_effects,
                                apply_signal_effects, effects_to_block, parse_effects, render_requirements)
from tofhil.sim.memory import check_memory, render_memory
from tofhil.sim.sensor import OpticalSignal, SensorConfig, SensorModel, waveform_from_scene

Effects = Mapping[str, Mapping[str, Any]]


def resolve_effects(scene: Any, effects: Mapping[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """Validated effects: the scene's ``effects:`` block when ``effects`` is None, else ``effects``
    (which replaces the scene's block entirely; an empty mapping means no effects)."""
    if effects is None:
        return scene.effects  # parsed once, when the scene was loaded
    return parse_effects(effects, source="<effects>")


def sensor_config(scene: Any) -> SensorConfig:
    """The scene's sensor, resolved against its camera preset and validated at load."""
    return scene.sensor


def render_arguments(scene: Any, effects: Effects, render_kwargs: Mapping[str, Any] | None = None, *,
                     frames_kept: int = 0) -> dict[str, Any]:
    """Arguments for ``render``: the sensor's frequencies, the harmonics the waveform and the
    wiggling effect need, and what render-stage effects require (separate direct/indirect and
    a 0 Hz channel carrying the direct power for the multipath effect).

    Refuses (before anything is allocated) a job whose estimated memory -- the render, the
    sensor and ``frames_kept`` frames held at once -- exceeds what the machine has."""
    cfg = sensor_config(scene)
    harm = set(waveform_from_scene(scene)) | {1}
    if "wiggling" in effects:
        harm |= set(WigglingEffect.harmonics(effects["wiggling"]))
    kw: dict[str, Any] = {"freq_hz": list(cfg.freq_hz), "harmonics": tuple(sorted(harm))}
    req = render_requirements(effects, scene)
    if req.get("separate_direct"):
        kw["freq_hz"] = kw["freq_hz"] + [0.0]
    kw.update(req)
    kw.update(dict(render_kwargs or {}))
    signal_effects = any(EFFECTS[n].stage in ("signal", "pixel") for n in effects)
    check_memory(render_memory(scene, kw, frames_kept=frames_kept, signal_effects=signal_effects),
                 source=str(getattr(scene, "source", "")) or None)
    return kw


def prepare_render(scene: Any, effects: Mapping[str, Any] | None = None, *,
                   render_kwargs: Mapping[str, Any] | None = None, progress: Progress | None = None) -> tuple[Any, Any]:
    """Apply scene-stage effects and render: ``(scene_with_effects, RenderResult)``."""
    from tofhil.sim.render import render

    eff = resolve_effects(scene, effects)
    scene2 = apply_scene_effects(scene, eff)
    return scene2, render(scene2, progress=progress, **render_arguments(scene2, eff, render_kwargs))


def _context(scene: Any, camera: Any, cfg: SensorConfig) -> EffectContext:
    src = str(getattr(scene, "source", "<scene>"))
    base = Path(src).parent if Path(src).is_file() else None
    return EffectContext(camera=camera, sensor=cfg, source=src, base_dir=base)


def optical_signal(scene: Any, render_result: Any, effects: Mapping[str, Any] | None = None) -> OpticalSignal:
    """Light on the sensor: the render recombined by render-stage effects, then the signal- and
    pixel-stage effects. Scene-stage effects are assumed already rendered in."""
    eff = resolve_effects(scene, effects)
    cfg = sensor_config(scene)
    camera = getattr(render_result, "camera", None) or scene.camera
    waveform = waveform_from_scene(scene)
    if "multipath" in eff:
        signal = EFFECTS["multipath"].apply_render(render_result, eff["multipath"], waveform)  # type: ignore[attr-defined]
    else:
        signal = OpticalSignal.from_render(render_result, waveform)
    return apply_signal_effects(signal, eff, _context(scene, camera, cfg))


def forward(scene: Any, render_result: Any, effects: Mapping[str, Any] | None = None, *, seed: int = 0,
            noise: bool = True, frame_index: int = 0) -> RawFrame:
    """One raw frame (taps in DN) from a cached render: render-, signal- and pixel-stage
    effects, then the sensor. ``effects=None`` uses the scene's block."""
    eff = resolve_effects(scene, effects)
    cfg = sensor_config(scene)
    camera = getattr(render_result, "camera", None) or scene.camera
    signal = optical_signal(scene, render_result, eff)
    return SensorModel(cfg, camera).expose(signal, seed=seed, frame_index=frame_index, noise=noise,
                                           meta={"effects": effects_to_block(eff)})


def frames_from_signal(scene: Any, signal: OpticalSignal, camera: Any, frames: int, *, seed: int, noise: bool,
                       meta: Mapping[str, Any] | None = None, first_index: int = 0) -> Iterable[RawFrame]:
    """Expose ``frames`` frames of one (fixed) optical signal with independent noise."""
    sensor = SensorModel(sensor_config(scene), camera)
    for i in range(first_index, first_index + frames):
        yield sensor.expose(signal, seed=seed, frame_index=i, noise=noise, meta=dict(meta or {}))


def simulate(scene: Any, frames: int = 1, seed: int = 0, noise: bool = True,
             effects: Mapping[str, Any] | None = None, render_kwargs: Mapping[str, Any] | None = None,
             progress: Progress | None = None) -> list[RawFrame]:
    """Render once, apply the effects, and expose ``frames`` raw frames with independent noise.

    The same ``seed`` gives identical frames; the render's Monte Carlo seed is the scene's
    ``render.seed`` unless ``render_kwargs`` says otherwise."""
    if frames < 1:
        raise ValueError("frames must be >= 1")
    eff = resolve_effects(scene, effects)
    render_arguments(apply_scene_effects(scene, eff), eff, render_kwargs, frames_kept=frames)  # memory check
    scene2, result = prepare_render(scene, eff, render_kwargs=render_kwargs, progress=progress)
    camera = getattr(result, "camera", None) or scene2.camera
    signal = optical_signal(scene2, result, eff)
    return list(frames_from_signal(scene2, signal, camera, frames, seed=seed, noise=noise,
                                   meta={"effects": effects_to_block(eff)}))


def simulate_session(scene: Any, out_path: str | Path, frames: int = 1, seed: int = 0, noise: bool = True,
                     force: bool = False, effects: Mapping[str, Any] | None = None,
                     render_kwargs: Mapping[str, Any] | None = None, progress: Progress | None = None) -> Path:
    """Write a session file (same layout as a capture): raw taps and depth per frame, the scene's
    YAML text embedded, ``device = {"model": "tofhil-sim", ...}``.

    With ``effects`` given, the embedded scene text carries those effects instead of the file's
    block, so the session says exactly what was simulated."""
    from tofhil import __version__
    from tofhil.depth import depth_from_raw
    from tofhil.session import SessionWriter, check_new_path
    from tofhil.sim.scene import scene_to_yaml

    out_path = Path(out_path)
    check_new_path(out_path, force)  # fail before the (slow) render
    eff = resolve_effects(scene, effects)
    scene2, result = prepare_render(scene, eff, render_kwargs=render_kwargs, progress=progress)
    camera = getattr(result, "camera", None) or scene2.camera
    signal = optical_signal(scene2, result, eff)
    if effects is None:
        text = getattr(scene, "text", "") or scene_to_yaml(scene)
    else:
        import dataclasses

        text = scene_to_yaml(dataclasses.replace(scene, effects=effects_to_block(eff)))
    device = {"model": "tofhil-sim", "software": f"tofhil {__version__}", "scene": str(getattr(scene, "source", "")),
              "seed": int(seed), "noise": bool(noise), "effects": effects_to_block(eff),
              "samples_per_pixel": int(getattr(result, "samples_per_pixel", 1)),
              "bounces": int(getattr(result, "bounces", 0))}
    it = frames_from_signal(scene2, signal, camera, frames, seed=seed, noise=noise)
    if progress is not None:
        it = progress(it, frames, "simulate")
    # The session records the camera as the scene file states it (what a user's calibration
    # says); a lens_distortion effect is a deviation of the real lens from that model, so it
    # shows in the data, not in the recorded camera.
    # The resolved sensor travels with the session: a re-render (diagnosis, compare) uses it.
    with SessionWriter(out_path, scene.camera, device=device, scene_text=text, force=force,
                       sensor_config=sensor_config(scene2).to_dict(), derived=True) as w:
        for raw in it:
            w.append(raw, depth_from_raw(raw))  # the saturation level travels in raw.meta
    return out_path


def expected_taps(scene: Any, render_result: Any, effects: Mapping[str, Any] | None = None) -> np.ndarray:
    """Noise-free taps in DN ``[F, K, H, W]`` (float32, as in a frame) for fitting."""
    eff = resolve_effects(scene, effects)
    cfg = sensor_config(scene)
    camera = getattr(render_result, "camera", None) or scene.camera
    return SensorModel(cfg, camera).taps_dn(optical_signal(scene, render_result, eff), noise=False)
