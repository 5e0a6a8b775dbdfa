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
  (what a job needs, refused before it starts);
- ``sources``: the frame sources the emulated cameras are given (``tofhil.frame_source``).

Importing ``tofhil.sim`` imports none of them (nor numba, embreex or Open3D); the names below
load their module on first use.
"""

from tofhil.faces import lazy_face

__all__, __getattr__, __dir__ = lazy_face(__name__, {
    "Scene": "scene_model", "load_scene": "scene", "Twin": "twin", "simulate": "pipeline",
    "simulate_session": "pipeline", "write_simulation": "pipeline", "EFFECTS": "effects",
    "StrayLightPSF": "straylight", "SimulatedSource": "sources", "AnalyticWall": "sources",
})
