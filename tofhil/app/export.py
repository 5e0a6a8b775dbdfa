"""``tofhil export``: a session as a ROS 2 MCAP bag, with the twin's render beside it.

The session -> MCAP writer is the format's own module (``tofhil.drivers.importers.ros2``,
beside its reader); what needs the simulator twin is here: with a scene, the twin renders it
once for the session's camera and acquisition settings (``tofhil.app.twin_render``), and every
frame carries the twin's depth and amplitude and the residual depth image (measured - twin) on
their own topics.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.app.twin_render import residual_m, twin_frame_for_session
from tofhil.frames import DepthFrame

#: Topics of the twin's images (distance images get ``/radial`` or ``/z`` appended).
TWIN_DEPTH = "/tofhil/twin/depth"
TWIN_AMPLITUDE = "/tofhil/twin/amplitude"
TWIN_POINTS = "/tofhil/twin/points"
RESIDUAL = "/tofhil/residual/depth"


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
