"""The twin's noise-free frame for a session or a live capture, and the residual against it.

Whoever shows the twin beside measured frames (``tofhil export``, ``tofhil view``, the live
view of ``tofhil capture``) renders the scene once (it is static) for the camera and
acquisition settings the frames were made with (``tofhil.sim.session_setup``: a session's
recorded sensor configuration, or its frequencies, tap phases, integration time and camera
with the rest from the scene), noise-free, demodulated by the core as a capture is
(``tofhil.depth.depth_from_raw``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from tofhil.camera import CameraModel
from tofhil.frames import DepthFrame, RawFrame


@dataclass
class TwinRender:
    """The twin's noise-free frame of a scene for a session, and how it was set up."""

    depth: DepthFrame
    note: str
    scene: str


def _load(scene: Any) -> Any:
    from tofhil.sim.scene import load_scene

    return load_scene(scene) if isinstance(scene, (str, Path)) else scene


def twin_frame(scene: Any, *, camera: CameraModel, freq_hz: Sequence[float] | None = None,
               theta_rad: Sequence[float] | None = None, integration_time_s: float | None = None,
               recorded: dict[str, Any] | None = None, source: str | Path = "<frames>") -> TwinRender:
    """Render ``scene`` (a file, a bundled name or a loaded scene) as the twin of frames taken
    with ``camera`` and the acquisition settings given (None: the scene's, as for depth +
    amplitude frames, which record none) and the session's recorded sensor configuration
    ``recorded`` (None for a device capture)."""
    from tofhil.depth import depth_from_raw
    from tofhil.sim.session_setup import scene_for_setup, session_setup
    from tofhil.sim.twin import Twin

    sc = _load(scene)
    sensor = sc.sensor
    setup = session_setup(sensor, camera=camera, freq_hz=sensor.freq_hz if freq_hz is None else freq_hz,
                          theta_rad=sensor.theta_rad if theta_rad is None else theta_rad,
                          integration_time_s=sensor.integration_time_s if integration_time_s is None
                          else integration_time_s, recorded=recorded, source=source)
    twin = Twin(scene_for_setup(sc, setup))
    frame = next(iter(twin.frames(frames=1, noise=False)))
    return TwinRender(depth_from_raw(frame), setup.note, str(getattr(sc, "name", "") or scene))


def twin_frame_for_session(scene: Any, session_path: str | Path) -> TwinRender:
    """Render ``scene`` as the twin of the session: its camera and acquisition settings
    (``session_setup``), noise-free, demodulated into depth."""
    from tofhil.session import open_session

    with open_session(session_path, need_frames=True) as s:
        if s.has_raw:
            return twin_frame(scene, camera=s.camera, freq_hz=s.freq_hz, theta_rad=s.theta_rad,
                              integration_time_s=s.integration_time_s, recorded=s.sensor_config, source=s.path)
        return twin_frame(scene, camera=s.camera, recorded=s.sensor_config, source=s.path)


def twin_frame_for_frame(scene: Any, frame: RawFrame | DepthFrame) -> TwinRender:
    """Render ``scene`` as the twin of a live frame (a device capture: no recorded sensor
    configuration): a raw frame's camera and acquisition settings, a depth frame's camera."""
    if isinstance(frame, RawFrame):
        return twin_frame(scene, camera=frame.camera, freq_hz=frame.freq_hz, theta_rad=frame.theta_rad,
                          integration_time_s=frame.integration_time_s, source="<capture>")
    return twin_frame(scene, camera=frame.camera, source="<capture>")


def residual_m(measured: DepthFrame, twin: DepthFrame) -> np.ndarray:
    """Measured - twin radial distance (m), NaN where either is not a valid measurement."""
    ok = measured.camera.valid_mask(measured.radial_m, measured.valid) & twin.camera.valid_mask(twin.radial_m, twin.valid)
    return np.where(ok, measured.radial_m.astype(np.float64) - twin.radial_m, np.nan).astype(np.float32)
