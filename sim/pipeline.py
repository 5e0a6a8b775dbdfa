"""The twin end to end: scene -> render -> effects -> sensor -> frames/session.

The forward model itself is :class:`tofhil.sim.twin.Twin`; this module runs it for users.
``simulate`` renders once and then exposes every frame with independent noise (the light does
not change between frames; only shot and read noise do). ``forward`` turns a given render
into one frame with given effects; ``prepare_render`` applies the scene-stage effects
(pose, lens distortion, reflectance, ambient) and renders.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil.frames import RawFrame
from tofhil.progress import Progress
from tofhil.sim.effects import effects_to_block, parse_effects
from tofhil.sim.sensor import OpticalSignal, SensorConfig, SensorModel
from tofhil.sim.twin import Twin, readout, signal_from_render, with_readout

Effects = Mapping[str, Mapping[str, Any]]


def resolve_effects(scene: Any, effects: Mapping[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """Validated effects: the scene's ``effects:`` block when ``effects`` is None, else ``effects``
    (which replaces the scene's block entirely; an empty mapping means no effects)."""
    if effects is None:
        return parse_effects(getattr(scene, "effects", None) or {}, source=getattr(scene, "source", "<scene>"))
    return parse_effects(effects, source="<effects>")


def sensor_config(scene: Any) -> SensorConfig:
    """The scene's sensor, resolved against its camera preset and validated at load."""
    return scene.sensor


def prepare_render(scene: Any, effects: Mapping[str, Any] | None = None, *,
                   render_kwargs: Mapping[str, Any] | None = None, progress: Progress | None = None) -> tuple[Any, Any]:
    """Apply scene-stage effects and render: ``(scene_with_effects, RenderResult)``."""
    return Twin(scene, effects=effects, render_kwargs=render_kwargs, progress=progress).render()


def optical_signal(scene: Any, render_result: Any, effects: Mapping[str, Any] | None = None) -> OpticalSignal:
    """Light on the sensor: the render recombined by render-stage effects, then the signal- and
    pixel-stage effects. Scene-stage effects are assumed already rendered in."""
    return signal_from_render(scene, render_result, resolve_effects(scene, effects), sensor_config(scene))


def forward(scene: Any, render_result: Any, effects: Mapping[str, Any] | None = None, *, seed: int = 0,
            noise: bool = True, frame_index: int = 0) -> RawFrame:
    """One raw frame (taps in DN) from a given render: render-, signal- and pixel-stage
    effects, then the sensor. ``effects=None`` uses the scene's block."""
    eff = resolve_effects(scene, effects)
    camera = getattr(render_result, "camera", None) or scene.camera
    signal = optical_signal(scene, render_result, eff)
    config = sensor_config(scene)
    frame = SensorModel(config, camera).expose(signal, seed=seed, frame_index=frame_index, noise=noise,
                                               meta={"effects": effects_to_block(eff)})
    return with_readout(frame, scene, eff, config)


def simulate(scene: Any, frames: int = 1, seed: int = 0, noise: bool = True,
             effects: Mapping[str, Any] | None = None, render_kwargs: Mapping[str, Any] | None = None,
             progress: Progress | None = None) -> list[RawFrame]:
    """Render once, apply the effects, and expose ``frames`` raw frames with independent noise.

    The same ``seed`` gives identical frames; the render's Monte Carlo seed is the scene's
    ``render.seed`` unless ``render_kwargs`` says otherwise."""
    if frames < 1:
        raise ValueError("frames must be >= 1")
    # every frame is held in memory at once: the memory check counts them
    twin = Twin(scene, effects=effects, render_kwargs=render_kwargs, progress=progress, frames_kept=frames)
    return list(twin.frames(frames=frames, seed=seed, noise=noise,
                            meta={"effects": effects_to_block(twin.base_effects)}))


@dataclass
class SimulatedSession:
    """A simulation written to a session file, with what a report of it draws on."""

    path: Path
    render: Any          #: the render result (with multipath shares when they were asked for)
    direct: Any = None   #: a direct-ToF scene's simulation (histograms and peaks)

    def multipath_shares(self, scene: Any) -> Any:
        """Where each pixel's light comes from, by bounce and by object (needs ``multipath_shares``)."""
        from tofhil.sim.multipath import shares_from_render

        return shares_from_render(self.render, [o.name for o in scene.objects])


def simulate_session(scene: Any, out_path: str | Path, frames: int = 1, seed: int = 0, noise: bool = True,
                     force: bool = False, effects: Mapping[str, Any] | None = None,
                     render_kwargs: Mapping[str, Any] | None = None, progress: Progress | None = None,
                     twin: Twin | None = None) -> Path:
    """Write a session file (same layout as a capture) and return its path: :func:`write_simulation`."""
    return write_simulation(scene, out_path, frames=frames, seed=seed, noise=noise, force=force, effects=effects,
                            render_kwargs=render_kwargs, progress=progress, twin=twin).path


def write_simulation(scene: Any, out_path: str | Path, frames: int = 1, seed: int = 0, noise: bool = True,
                     force: bool = False, effects: Mapping[str, Any] | None = None,
                     render_kwargs: Mapping[str, Any] | None = None, progress: Progress | None = None,
                     twin: Twin | None = None, multipath_shares: bool = False) -> SimulatedSession:
    """Write a session file (same layout as a capture): raw taps and depth per frame, the scene's
    YAML text embedded, ``device = {"model": "tofhil-sim", ...}``.

    With ``effects`` given, the embedded scene text carries those effects instead of the file's
    block, so the session says exactly what was simulated. ``twin`` is a :class:`Twin` of this
    scene whose render cache to use (a sweep renders a scene once for many cases).
    ``multipath_shares``: the render also keeps where each pixel's light comes from, for a
    report (``tofhil simulate --report``)."""
    from tofhil import __version__
    from tofhil.depth import depth_from_raw
    from tofhil.outputs import check_new_path
    from tofhil.session import SessionWriter
    from tofhil.sim.scene import scene_to_yaml

    out_path = Path(out_path)
    check_new_path(out_path, force)  # fail before the (slow) render
    if multipath_shares:
        render_kwargs = {**dict(render_kwargs or {}), "multipath_shares": True}
    if getattr(scene, "direct_tof", None) is not None:
        return write_direct_simulation(scene, out_path, frames=frames, seed=seed, noise=noise, force=force,
                                       render_kwargs=render_kwargs, progress=progress)
    if multipath_shares and twin is not None:
        twin = None      # the shares need their own render (a sweep asks for none)
    if twin is None:
        twin = Twin(scene, effects=effects, render_kwargs=render_kwargs, progress=progress)
    eff = resolve_effects(scene, effects)
    _, result = twin.render(eff)
    if effects is None:
        text = getattr(scene, "text", "") or scene_to_yaml(scene)
    else:
        import dataclasses

        text = scene_to_yaml(dataclasses.replace(scene, effects=effects_to_block(eff)))
    device = {"model": "tofhil-sim", "software": f"tofhil {__version__}", "scene": str(getattr(scene, "source", "")),
              "seed": int(seed), "noise": bool(noise), "effects": effects_to_block(eff),
              "samples_per_pixel": int(getattr(result, "samples_per_pixel", 1)),
              "bounces": int(getattr(result, "bounces", 0))}
    it = twin.frames(eff, frames=frames, seed=seed, noise=noise)
    if progress is not None:
        it = progress(it, frames, "simulate")
    # The session records the camera as the scene file states it (what a user's calibration
    # says); a lens_distortion effect is a deviation of the real lens from that model, so it
    # shows in the data, not in the recorded camera.
    # The resolved sensor travels with the session: a re-render (diagnosis, compare) uses it.
    with SessionWriter(out_path, scene.camera, device=device, scene_text=text, force=force,
                       sensor_config=twin.config.to_dict(), derived=True) as w:
        for raw in it:
            w.append(raw, depth_from_raw(raw))  # the saturation level travels in raw.meta
    second = getattr(scene, "rgb_camera", None)
    if second is not None:
        # the scene does not move between frames: one image of the second camera, with frame 0
        from tofhil.session_rgb import write_rgb
        from tofhil.sim.rgb import render_grey

        grey = render_grey(scene, second.camera, second.tof_to_camera, samples=second.samples)
        write_rgb(out_path, [grey], second.camera, frame_index=[0], tof_to_camera=second.tof_to_camera)
    return SimulatedSession(out_path, result)


def simulate_direct_session(scene: Any, out_path: str | Path, frames: int = 1, seed: int = 0, noise: bool = True,
                            force: bool = False, render_kwargs: Mapping[str, Any] | None = None,
                            progress: Progress | None = None) -> Path:
    """A direct-ToF session and its path: :func:`write_direct_simulation`."""
    return write_direct_simulation(scene, out_path, frames=frames, seed=seed, noise=noise, force=force,
                                   render_kwargs=render_kwargs, progress=progress).path


def write_direct_simulation(scene: Any, out_path: str | Path, frames: int = 1, seed: int = 0, noise: bool = True,
                            force: bool = False, render_kwargs: Mapping[str, Any] | None = None,
                            progress: Progress | None = None) -> SimulatedSession:
    """A direct-ToF session (the scene's ``direct_tof:`` block): per frame the SPAD histograms
    (``histograms/counts``, the peaks found in them) and the depth of the strongest peak
    (``depth/``); no raw taps (docs/session-format.md). The correlation ``effects:`` do not
    apply to histograms and are not recorded."""
    from tofhil import __version__
    from tofhil.frames import DepthFrame
    from tofhil.session import SessionWriter
    from tofhil.sim.direct_tof import render_direct, simulate_direct
    from tofhil.sim.scene import scene_to_yaml

    cfg = scene.direct_tof
    result = render_direct(scene, progress=progress, **dict(render_kwargs or {}))
    sim = simulate_direct(scene, frames=frames, seed=seed, noise=noise, result=result)
    device = {"model": "tofhil-sim", "kind": "direct_tof", "software": f"tofhil {__version__}",
              "scene": str(getattr(scene, "source", "")), "seed": int(seed), "noise": bool(noise),
              "samples_per_pixel": int(result.samples_per_pixel), "bounces": int(result.bounces)}
    attrs = {"bin_width_s": cfg.bin_width_s, "t0_s": cfg.t0_s, "cycles_per_frame": cfg.cycles_per_frame,
             "dead_time_s": cfg.dead_time_s, "repetition_hz": cfg.repetition_hz,
             "counts_model": "SPAD counts per bin over cycles_per_frame laser cycles (expected counts with "
                             "noise = false); bin i spans t0_s + [i, i+1) * bin_width_s after the pulse"}
    text = getattr(scene, "text", "") or scene_to_yaml(scene)
    period = float(cfg.cycles_per_frame / cfg.repetition_hz)
    with SessionWriter(out_path, scene.camera, device=device, scene_text=text, force=force, derived=True,
                       sensor_config=None, histogram_attrs=attrs) as w:
        for i, (counts, peaks) in enumerate(zip(sim.counts, sim.peaks)):
            found = np.isfinite(peaks.time_s[0])
            depth = DepthFrame(distance_m=np.where(found, peaks.distance_m[0], np.nan).astype(np.float32),
                               kind="radial", camera=scene.camera,
                               amplitude=(peaks.photons[0] * cfg.cycles_per_frame).astype(np.float32),
                               intensity=(peaks.background * cfg.cycles_per_frame).astype(np.float32),
                               valid=found, timestamp_s=i * period, sequence=i)
            w.append(None, depth, histogram={"counts": counts, "peak_distance_m": peaks.distance_m,
                                             "peak_counts": peaks.photons * cfg.cycles_per_frame})
    return SimulatedSession(Path(out_path), result, direct=sim)


def expected_taps(scene: Any, render_result: Any, effects: Mapping[str, Any] | None = None) -> np.ndarray:
    """Noise-free taps in DN ``[F, K, H, W]`` (float32, as in a frame) from a given render."""
    camera = getattr(render_result, "camera", None) or scene.camera
    eff = resolve_effects(scene, effects)
    config = sensor_config(scene)
    taps = SensorModel(config, camera).taps_dn(optical_signal(scene, render_result, eff), noise=False)
    return readout(taps, scene, camera, eff, config)
