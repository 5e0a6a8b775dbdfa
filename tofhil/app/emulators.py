"""The emulated cameras given the simulator twin's frame sources.

The drivers' emulators (the TOFcam635 firmware, the DepthAI host pipeline) speak the
devices' protocols and take their images from a frame source (``tofhil.drivers.sources``);
the twin provides them (``tofhil.sim.sources``). :func:`connect_emulators` joins the two,
so that ``emulator[:SCENE]`` and ``depthai-sim[:SCENE]`` device specs work. The CLI calls it
at start; a program using the library calls it once, or passes sources explicitly.
"""

from __future__ import annotations

from typing import Any

from tofhil.drivers.sources import provide_frame_sources


def _tofcam635_source(rest: str | None) -> Any:
    from tofhil.sim.sources import source_from_spec  # the twin loads only when an emulator opens

    return source_from_spec(rest)


def _depthai_scene(rest: str | None) -> Any:
    from tofhil.sim.sources import host_scene_from_spec

    return host_scene_from_spec(rest)


def connect_emulators() -> None:
    """Give the emulated devices opened from a spec the simulator twin's frame sources."""
    provide_frame_sources("tofcam635", _tofcam635_source)
    provide_frame_sources("depthai", _depthai_scene)
