"""The camera + sensor configuration a session was recorded with, resolved for a re-render.

Whoever renders the twin *for* a session (diagnosis, the demo's twin of a capture, compare's
twin side) must use the settings the session's frames were made with, not those a scene or a
camera preset would give by default. One function decides, :func:`session_setup`:

- a session written by the twin stores its fully resolved :class:`SensorConfig` (root
  attribute ``sensor_config``, docs/session-format.md): the re-render uses every field of it
  (frequencies, tap phases and integration time as in the ``raw/`` datasets);
- a capture from a device (no stored sensor configuration) gives what it records --
  modulation frequencies, tap phases, integration time, the camera model -- and the rest
  (wavelength, quantum efficiency, contrast, gains, full well, noise, ADC, black level, fixed
  pattern) comes from the scene; :attr:`SessionSetup.note` says which came from where.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from tofhil.camera import CameraModel
from tofhil.sim.sensor import SensorConfig

#: The SensorConfig fields every raw session records itself (datasets raw/freq_hz,
#: raw/theta_rad and attribute raw.integration_time_s).
FROM_SESSION = ("freq_hz", "theta_rad", "integration_time_s")


@dataclass(frozen=True)
class SessionSetup:
    """The camera and sensor a re-render for a session uses, and where each came from."""

    camera: CameraModel
    sensor: SensorConfig
    #: True when the session stored its full sensor configuration (a twin session).
    recorded: bool
    #: SensorConfig fields taken from the scene (empty for a recorded configuration).
    from_scene: tuple[str, ...]

    @property
    def note(self) -> str:
        if self.recorded:
            return "camera and sensor: the session's recorded configuration (every sensor setting)"
        return ("camera and sensor: modulation frequencies, tap phases, integration time and camera from the "
                f"session; the other {len(self.from_scene)} sensor settings (wavelength, gains, noise, ...) from "
                "the scene (the session records no sensor configuration)")


def session_setup(scene_sensor: SensorConfig | None, *, camera: CameraModel, freq_hz: Sequence[float],
                  theta_rad: Sequence[float], integration_time_s: float,
                  recorded: Mapping[str, Any] | None = None, source: str | Path = "<session>") -> SessionSetup:
    """Resolve the configuration for a session (see the module docstring).

    ``recorded`` is the session's stored ``sensor_config`` mapping, or None; ``scene_sensor``
    the base scene's resolved sensor (needed when nothing is recorded)."""
    acquired = {"freq_hz": tuple(float(f) for f in np.ravel(freq_hz)),
                "theta_rad": tuple(float(t) for t in np.ravel(theta_rad)),
                "integration_time_s": float(integration_time_s)}
    if recorded is not None:
        base = SensorConfig.from_dict(recorded, source=f"{source}: sensor_config", camera=None)
        return SessionSetup(camera, dataclasses.replace(base, **acquired), True, ())
    if scene_sensor is None:
        raise ValueError("a session without a recorded sensor configuration needs the scene's sensor")
    rest = tuple(f.name for f in dataclasses.fields(SensorConfig) if f.name not in FROM_SESSION)
    return SessionSetup(camera, dataclasses.replace(scene_sensor, **acquired), False, rest)


def setup_for_session(scene: Any, session: Any) -> SessionSetup:
    """:func:`session_setup` for an open :class:`tofhil.session.Session` with raw taps."""
    return session_setup(getattr(scene, "sensor", None), camera=session.camera, freq_hz=session.freq_hz,
                         theta_rad=session.theta_rad, integration_time_s=session.integration_time_s,
                         recorded=session.sensor_config, source=session.path)


def scene_for_setup(scene: Any, setup: SessionSetup) -> Any:
    """The scene set to the session's camera and sensor (the scene itself is unchanged)."""
    return dataclasses.replace(scene, camera=setup.camera, sensor=setup.sensor)



def write_twin_scene(scene: Any, session_path: str | Path, out_path: str | Path) -> tuple[Any, SessionSetup]:
    """The twin of a recorded session: ``scene`` set to the session's camera and acquisition
    settings, written to ``out_path`` (YAML) and read back, so the twin is exactly what that
    file says (a diagnosis or a later run reads the same file)."""
    from tofhil.session import open_session
    from tofhil.sim.scene import load_scene, scene_to_yaml

    with open_session(session_path) as session:
        setup = setup_for_session(scene, session)
    Path(out_path).write_text(scene_to_yaml(scene_for_setup(scene, setup)), encoding="utf-8")
    return load_scene(out_path), setup
