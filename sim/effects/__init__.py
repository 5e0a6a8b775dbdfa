"""The effect library: separate, parametric, switchable parts of the twin's forward model.

Every effect has a ``name`` (the vocabulary diagnosis uses), a ``stage`` saying where in the
forward model it acts, and ``params``: each a :class:`Param` with its "off" value (the value
for which the effect changes nothing), bounds, unit and meaning. Some effects also take
structured options (``options``) that are not fitted (a seed, a measured PSF file, per-material
scales).

Stages, in the order the forward model applies them (``ORDER``):

- ``scene``: changes the Scene before rendering -- ``pose``, ``lens_distortion``,
  ``reflectance``, ``ambient``. Changing them needs a new render.
- ``render``: recombines the renderer's separate direct and indirect phasors --
  ``multipath`` (cheap on a cached render made with ``separate_direct=True``).
- ``signal``: acts on the light on the sensor (an :class:`OpticalSignal`) before the pixel --
  ``unseen_reflector`` (light from a surface the scene lacks), ``illumination`` (the emitter's profile),
  ``gain_field`` (a smooth gain of the emitter's light), ``stray_light`` (optics), ``offset`` (unmodulated
  charge), ``offset_field`` (unmodulated charge varying smoothly over the sensor), ``range_offset``, ``field_angle``,
  ``wiggling``, ``amplitude_dependent``.
- ``pixel``: per-pixel demodulation properties -- ``fixed_pattern``, ``range_offset_map``,
  ``frequency_calibration``.
- ``taps``: the readout after the pixel, on the recorded taps -- ``tap_calibration``.

Each stage has one hook (``STAGE_HOOKS``) that its effects implement. Render-, signal- and
pixel-stage effects apply to a cached render in milliseconds; scene-stage effects whose change
is exactly a rescaling of a render (reflectance, ambient) also implement ``rescale_render``.
The twin (``tofhil.sim.twin.Twin``) runs these hooks for simulation and diagnosis alike. What
diagnosis fits of each parameter (range, step, log scale, starting points) is in its ``Param``. A scene file switches effects on with an ``effects:`` block
``{name: {param: value}}``; a missing parameter takes its ``default`` (or its off value).
See docs/effects.md.

Modules: :mod:`.base` (``Param``, ``Effect``, ``EffectContext``), :mod:`.registry` (``EFFECTS``,
``ORDER``, ``register``, ``parse_effects`` and the application by stage), and one module per
effect family, each registering its effects: :mod:`.geometry` (pose, lens_distortion),
:mod:`.reflectance`, :mod:`.ambient` (ambient, offset), :mod:`.multipath`,
:mod:`.unseen_reflector`, :mod:`.illumination`, :mod:`.fields` (gain_field, offset_field), :mod:`.stray_light`, :mod:`.range_errors` (range_offset, field_angle,
range_offset_map), :mod:`.fixed_pattern`, :mod:`.amplitude` (amplitude_dependent),
:mod:`.wiggling`, :mod:`.frequency_calibration`. Every name is importable from ``tofhil.sim.effects`` itself.
"""


# The family modules register their effects on import (the order of these imports does not
# matter: the registry orders effects by rank).
from tofhil.sim.effects import (ambient, amplitude, fields, fixed_pattern, frequency_calibration, geometry,  # noqa: F401
                                illumination, multipath, range_errors, reflectance, stray_light, tap_calibration,
                                unseen_reflector, wiggling)
from tofhil.sim.effects.ambient import AmbientEffect, OffsetEffect
from tofhil.sim.effects.amplitude import (AMPLITUDE_KNOTS_LOG10_E, AmplitudeDependentEffect, monotone_spline,
                                          stick_breaking)
from tofhil.sim.effects.base import (ACQUISITION, BENCH_CHANGE, DEFAULT_SEPARATION, OFFSET_CHANNEL, SHAPE_SEPARATION,
                                     STAGE_HOOKS, STAGES, Effect, EffectContext, Param, Separation)
from tofhil.sim.effects.fields import GainFieldEffect, OffsetFieldEffect
from tofhil.sim.effects.fixed_pattern import FixedPatternEffect
from tofhil.sim.effects.frequency_calibration import FrequencyCalibrationEffect
from tofhil.sim.effects.geometry import LensDistortionEffect, PoseEffect
from tofhil.sim.effects.illumination import IlluminationEffect
from tofhil.sim.effects.multipath import MultipathEffect
from tofhil.sim.effects.range_errors import FieldAngleEffect, RangeOffsetEffect, RangeOffsetMapEffect
from tofhil.sim.effects.reflectance import ReflectanceEffect
from tofhil.sim.effects.registry import (EFFECTS, ORDER, ParsedEffects, apply_scene_effects, apply_signal_effects, apply_tap_effects,
                                         describe_effects,
                                         effects_by_stage, effects_table_markdown, effects_to_block, parse_effects,
                                         register, render_requirements, separation)
from tofhil.sim.effects.stray_light import StrayLightEffect
from tofhil.sim.effects.tap_calibration import TapCalibrationEffect
from tofhil.sim.effects.unseen_reflector import UnseenReflectorEffect
from tofhil.sim.effects.wiggling import WigglingEffect, harmonic_aliases

__all__ = ["ACQUISITION", "AMPLITUDE_KNOTS_LOG10_E", "BENCH_CHANGE", "DEFAULT_SEPARATION", "EFFECTS",
           "OFFSET_CHANNEL", "ORDER", "ParsedEffects", "SHAPE_SEPARATION", "STAGES", "STAGE_HOOKS", "AmbientEffect", "Separation",
           "AmplitudeDependentEffect", "Effect", "EffectContext", "FieldAngleEffect", "FixedPatternEffect",
           "FrequencyCalibrationEffect", "GainFieldEffect", "IlluminationEffect", "LensDistortionEffect", "MultipathEffect", "OffsetEffect", "OffsetFieldEffect", "Param", "PoseEffect",
           "RangeOffsetEffect", "TapCalibrationEffect", "RangeOffsetMapEffect", "ReflectanceEffect", "StrayLightEffect", "UnseenReflectorEffect",
           "WigglingEffect",
           "apply_scene_effects", "apply_signal_effects", "apply_tap_effects", "describe_effects", "effects_by_stage",
           "effects_table_markdown", "effects_to_block", "harmonic_aliases", "monotone_spline", "parse_effects",
           "register", "render_requirements", "separation", "stick_breaking"]
