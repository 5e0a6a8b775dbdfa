"""The simulator twin: a bench scene rendered into the frames a ToF camera would give.

scene -> render (Embree path tracer: phasors per frequency and harmonic) -> effects (the
switchable parts of the forward model) -> sensor (taps in DN) -> frames and sessions. The
same forward model serves simulation and diagnosis (:class:`~tofhil.sim.twin.Twin`).

Modules:

- scene description: ``scene`` (YAML -> a validated :class:`Scene`), ``scene_model`` (the
  typed scene), ``scene_expressions`` (``${...}`` in scene files), ``from_capture`` (a scene
  built from a capture), ``session_setup`` (the camera and sensor of a recorded session);
- rendering: ``render`` (the renderer and its caches), ``geometry`` (objects -> Embree),
  ``kernels`` and ``embree4`` (the compiled path tracer), ``dielectric`` (glass and media),
  ``radiometry`` (closed forms), ``multipath`` (where the multipath comes from),
  ``direct_tof`` (SPAD histograms), ``rgb`` (a second, passive camera);
- optics and effects: ``optics`` (lens prescriptions), ``straylight`` (the one stray-light
  PSF type, kernels, convolution, operator), ``effects`` (the effect library, one module per
  family);
- the forward model: ``sensor`` and ``sensor_kernels`` (taps from light), ``twin`` (render
  cache + effects + sensor), ``pipeline`` (simulate and sessions end to end), ``memory``
  (what a job needs, refused before it starts).

Importing ``tofhil.sim`` imports none of them (nor numba, embreex or Open3D); the names below
load their module on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

#: A few key names, by the module that defines them (loaded on first use).
_KEY_NAMES = {"Scene": "scene_model", "load_scene": "scene", "Twin": "twin", "simulate": "pipeline",
              "simulate_session": "pipeline", "EFFECTS": "effects", "StrayLightPSF": "straylight"}
_SUBMODULES = ("dielectric", "direct_tof", "effects", "embree4", "from_capture", "geometry", "kernels", "memory",
               "multipath", "optics", "pipeline", "radiometry", "render", "rgb", "scene", "scene_expressions",
               "scene_model", "sensor", "sensor_kernels", "session_setup", "straylight", "twin")

__all__ = sorted(_KEY_NAMES) + list(_SUBMODULES)


def __getattr__(name: str) -> Any:
    if name in _KEY_NAMES:
        return getattr(importlib.import_module(f"{__name__}.{_KEY_NAMES[name]}"), name)
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
