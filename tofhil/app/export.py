"""``tofhil export``: a session as a ROS 2 MCAP bag, with the twin's render beside it.

The session -> MCAP writer is the format's own module (``tofhil.drivers.importers.ros2``,
beside its reader); what needs the simulator twin is here: with a scene, the twin renders it
once for the session's camera and acquisition settings (``tofhil.sim.session_setup``: the
session's recorded sensor configuration, or its frequencies, tap phases, integration time and
camera with the rest from the scene), noise-free, demodulated by the core as a capture is
(``tofhil.depth.depth_from_raw``), and every frame carries the twin's depth and amplitude and
the residual depth image (measured - twin) on their own topics.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.frames import DepthFrame

#: Topics of the twin's images (distance images get ``/radial`` or ``/z`` appended).
TWIN_DEPTH = "/tofhil/twin/depth"
TWIN_AMPLITUDE = "/tofhil/twin/amplitude"
TWIN_POINTS = "/tofhil/twin/points"
RESIDUAL = "/tofhil/residual/depth"


@dataclass
class TwinRender:
    """The twin's noise-free frame of a scene for a session, and how it was set up."""

    depth: DepthFrame
    note: str
    scene: str


def twin_frame_for_session(scene: str | Path, session_path: str | Path) -> TwinRender:
    """Render ``scene`` (a file or bundled name) as the twin of the session: its camera and
    acquisition settings (``session_setup``), noise-free, demodulated into depth."""
    from tofhil.depth import depth_from_raw
    from tofhil.session import open_session
    from tofhil.sim.scene import load_scene
    from tofhil.sim.session_setup import scene_for_setup, session_setup, setup_for_session
    from tofhil.sim.twin import Twin

    sc = load_scene(scene)
    with open_session(session_path) as s:
        if s.has_raw:
            setup = setup_for_session(sc, s)
        else:  # depth + amplitude only: the scene's modulation, the session's camera
            sensor = sc.sensor
            setup = session_setup(sensor, camera=s.camera, freq_hz=sensor.freq_hz, theta_rad=sensor.theta_rad,
                                  integration_time_s=sensor.integration_time_s, recorded=s.sensor_config,
                                  source=s.path)
    twin = Twin(scene_for_setup(sc, setup))
    raw = next(iter(twin.frames(frames=1, noise=False)))
    return TwinRender(depth_from_raw(raw), setup.note, str(getattr(sc, "name", "") or scene))


def residual_m(measured: DepthFrame, twin: DepthFrame) -> np.ndarray:
    """Measured - twin radial distance (m), NaN where either is not a valid measurement."""
    ok = measured.camera.valid_mask(measured.radial_m, measured.valid) & twin.camera.valid_mask(twin.radial_m, twin.valid)
    return np.where(ok, measured.radial_m.astype(np.float64) - twin.radial_m, np.nan).astype(np.float32)


def export_mcap(session_path: str | Path, out: str | Path, *, scene: str | Path | None = None, force: bool = False,
                depth_kind: str = "radial", on_frame: Callable[[int, int], None] | None = None) -> Any:
    """Write ``session_path`` as a ROS 2 MCAP bag ``out`` (``write_session_mcap``); with
    ``scene``, also the twin's depth, amplitude and point cloud and the residual depth per
    frame. Returns the writer's :class:`~tofhil.drivers.importers.ros2.McapExport`."""
    from tofhil.drivers.importers.ros2 import ExtraImage, check_depth_kind, write_session_mcap
    from tofhil.outputs import check_new_path

    out = Path(out)
    check_depth_kind(depth_kind)
    check_new_path(out, force)  # both before the render
    if scene is None:
        return write_session_mcap(session_path, out, force=force, depth_kind=depth_kind, on_frame=on_frame)
    twin = twin_frame_for_session(scene, session_path)
    t = twin.depth
    t_ok = t.camera.valid_mask(t.radial_m, t.valid)
    t_radial = np.where(t_ok, t.radial_m, np.nan).astype(np.float32)
    t_amp = np.asarray(t.amplitude, dtype=np.float32)

    def extra(i: int, measured: DepthFrame) -> list[ExtraImage]:
        return [ExtraImage(TWIN_DEPTH, "twin_depth", t_radial, distance=True, cloud_topic=TWIN_POINTS,
                           intensity=t_amp, unit="m"),
                ExtraImage(TWIN_AMPLITUDE, "twin_amplitude", t_amp, unit="twin amplitude (DN)"),
                ExtraImage(RESIDUAL, "residual_depth", residual_m(measured, t), distance=True,
                           unit="m (measured - twin)")]

    result = write_session_mcap(session_path, out, force=force, depth_kind=depth_kind, extra=extra, on_frame=on_frame,
                                metadata={"twin_scene": str(scene), "twin_setup": twin.note,
                                          "twin": "noise-free render of the scene for the session's camera and "
                                                  "acquisition settings, demodulated as a capture"})
    result.notes.append(f"twin of {twin.scene}: {twin.note}")
    return result
