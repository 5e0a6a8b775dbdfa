"""What every effect is: its parameters (:class:`Param`), the stage hooks (:class:`Effect`)
and what signal- and pixel-stage hooks are given besides the light (:class:`EffectContext`).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.schema import Schema
from tofhil.sim.sensor import OpticalSignal, SensorConfig, take_pixels

STAGES = ("scene", "render", "signal", "pixel", "taps")
#: The hook each stage's effects implement.
STAGE_HOOKS = {"scene": "apply_scene", "render": "apply_render", "signal": "apply_signal", "pixel": "apply_signal",
               "taps": "apply_taps"}

#: The residual channel of the taps' unmodulated offset (``tofhil.eval.diagnose.channels``;
#: the ``offset`` effect, unmodulated charge, moves it alone; the channel is named here so
#: that diagnosis refers to it, not to an effect's name).
OFFSET_CHANNEL = "offset"
#: The kinds of :class:`Separation`: a device setting of the acquisition, or a change of the bench.
ACQUISITION = "acquisition"
BENCH_CHANGE = "bench_change"


@dataclass(frozen=True)
class Separation:
    """A capture that tells two readings of the data apart, as data a program can act on (the
    closed loop takes it): a device setting (``kind`` :data:`ACQUISITION`, ``what`` the
    setting) or a change of the bench (``kind`` :data:`BENCH_CHANGE`, ``what`` the change),
    with the words a reader is given and, where there are several ways, the options."""

    kind: str
    what: str
    text: str
    options: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        out = {"kind": self.kind, "setting" if self.kind == ACQUISITION else "change": self.what, "text": self.text}
        return out | ({"options": list(self.options)} if self.options else {})


#: The capture that separates two effects no effect declares a separation for.
DEFAULT_SEPARATION = Separation(BENCH_CHANGE, "distance", "a second distance, a tilt of the surface, or a known "
                                "target as independent truth",
                                ("a second distance", "a tilt of the surface", "a known target"))
#: The capture that separates a pattern fixed to the pixels from a surface shape the scene lacks:
#: a sensor pattern moves with the sensor, a surface shape with the scene.
SHAPE_SEPARATION = Separation(BENCH_CHANGE, "camera_pose", "the same scene with the camera rolled 90 degrees or "
                              "moved sideways (a sensor pattern moves with the sensor, a surface shape with the "
                              "scene), or a known flat target (--target)",
                              ("roll the camera 90 degrees", "move the camera sideways",
                               "a known flat target (--target)"))


@dataclass(frozen=True)
class Param:
    """One parameter: ``off`` leaves the model unchanged; ``[lo, hi]`` are its bounds.

    The last five fields say how diagnosis fits it (this table is the only place that says
    so): ``fit`` the range searched (None: diagnosis does not fit this parameter, it keeps
    its current value), ``step`` a typical change for the optimiser, ``log`` fit
    ``log10(value)`` (``fit`` and ``step`` are then in decades), ``start`` where a fit of a
    newly added effect begins (None: the current value) and ``starts`` more values to try,
    one parameter at a time with the others at their ``start`` (multi-start: at zero weight a
    lobe's width is irrelevant, at zero amplitude a harmonic's phase is).
    """

    off: float
    lo: float
    hi: float
    unit: str
    doc: str
    #: Value used when the effect is switched on without this parameter (None: the off value).
    default: float | None = None
    fit: tuple[float, float] | None = None
    step: float = 0.0
    log: bool = False
    start: float | None = None
    starts: tuple[float, ...] = ()
    #: The diagnosis forms that fit it: "" the effect's simple form, a name one of its
    #: flexible forms (``Effect.forms``).
    forms: tuple[str, ...] = ("",)
    #: An angle whose bounds are one period: a fit at a bound is not pinned there.
    periodic: bool = False

    def __post_init__(self) -> None:
        if not self.lo <= self.off <= self.hi:
            raise ValueError(f"off value {self.off} outside [{self.lo}, {self.hi}]")
        if self.fit is not None:
            lo, hi = (10.0 ** self.fit[0], 10.0 ** self.fit[1]) if self.log else self.fit
            if not (self.lo <= lo < hi <= self.hi) or not self.step > 0:
                raise ValueError(f"fit range {self.fit} must lie in the bounds [{self.lo}, {self.hi}] "
                                 "with a positive step")

    @property
    def on_default(self) -> float:
        return self.off if self.default is None else self.default

    @property
    def fitted(self) -> bool:
        return self.fit is not None


@dataclass
class EffectContext:
    """What signal- and pixel-stage effects may need besides the signal."""

    camera: CameraModel
    sensor: SensorConfig | None = None
    source: str = "<effects>"
    base_dir: Path | None = None
    #: The render's first-hit distance per pixel ``[H, W]`` (m) and the scene's emitter, for
    #: effects that need the scene's geometry (light from a surface the scene lacks).
    radial_m: np.ndarray | None = None
    emitter: Any = None
    #: Flat indices into the camera's frame of the pixels the signal holds, as one row ``[1,
    #: N]`` (a fit asks for its pixels only); None: the signal is the whole frame. Effects
    #: that depend on where a pixel is take their fields at these pixels (:meth:`at_pixels`).
    pixels: np.ndarray | None = None

    def frame_shape(self, signal_shape: tuple[int, int]) -> tuple[int, int]:
        """The camera frame's shape ``(H, W)`` for a signal of ``signal_shape``."""
        return tuple(signal_shape) if self.pixels is None else self.camera.shape  # type: ignore[return-value]

    def pixel_grid(self, signal_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Row and column ``(v, u)`` of each pixel the signal holds (float, its shape): the
        frame's ``np.mgrid``, or its values at :attr:`pixels`."""
        if self.pixels is None:
            v, u = np.mgrid[0:signal_shape[0], 0:signal_shape[1]].astype(np.float64)
            return v, u
        v, u = np.divmod(self.pixels, self.camera.shape[1])
        return (v.astype(np.float64).reshape(1, -1), u.astype(np.float64).reshape(1, -1))

    def at_pixels(self, field: np.ndarray) -> np.ndarray:
        """A field over the frame ``[..., H, W]`` where the signal is: itself for a whole
        frame, else ``[..., 1, N]`` at :attr:`pixels`."""
        return field if self.pixels is None else take_pixels(field, self.pixels)


class Effect:
    """Base class. Subclasses set ``name``, ``stage``, ``rank``, ``params``, ``options``,
    ``doc`` and implement the hook of their stage; ``registry.register`` enters them."""

    name: str = ""
    stage: str = ""
    #: Place in the forward-model order (``registry.ORDER``): effects apply in increasing
    #: rank, whatever their stage's position; a new effect takes a free rank between two.
    rank: int = 0
    doc: str = ""
    #: One line for the table of effects in docs/effects.md.
    summary: str = ""
    params: dict[str, Param] = {}
    #: Structured, non-fitted options: name -> description.
    options: dict[str, str] = {}
    #: Flexible forms diagnosis fits besides the simple one: form name -> what it adds. A
    #: form fits the parameters whose ``Param.forms`` name it (docs/diagnose.md, Selection).
    forms: dict[str, str] = {}
    #: True when the effect's light at a pixel depends only on that pixel's light (a
    #: prediction on some pixels then needs only those pixels rendered); False when it moves
    #: light between pixels (stray light).
    pixel_local: bool = True
    #: True when, given the whole frame's render, the effect's light at a pixel is computed
    #: from that pixel's light alone (the render's geometry may come from its neighbours: a
    #: prediction on some pixels then runs the effect on those pixels only,
    #: ``EffectContext.pixels``); None: as ``pixel_local``.
    local_given_render: bool | None = None
    #: The light this effect adds that is not a pixel's own direct return, by kind:
    #: "stray_light" (moved on the sensor by the lens) or "multipath" (a longer path in the
    #: scene); None for effects that change the direct return itself. The twin's direct-only
    #: prediction switches these effects off (``tofhil correct --method twin``).
    beyond_direct: str | None = None
    #: True when the effect acts on the taps' offset alone: a session without raw taps (depth
    #: and amplitude only) cannot see it.
    offset_only: bool = False
    #: The residual channel this effect calibrates when it is a generic form of that channel
    #: (a gain or offset field, a per-tap or per-frequency constant, a range offset or map)
    #: rather than a physical cause; "" for a physical cause. Diagnosis prefers a physical
    #: reading that explains as well, where it takes a generic form it also searches from the
    #: best physical cause of that round (``EffectSpec.generic``), and an "A or B" names a
    #: generic form as a calibration of its channel.
    calibrates: str = ""

    @property
    def generic(self) -> bool:
        """True for a calibration form of a channel (:attr:`calibrates`)."""
        return bool(self.calibrates)
    #: Other effects (by name) that can explain a capture as this one does, each with the
    #: capture that tells the two apart. A pair is declared on one of its two effects
    #: (``registry.separation`` reads both).
    mimicked_by: dict[str, Separation] = {}
    #: What a surface shape the scene lacks looks like through this effect ("" when none can
    #: mimic it): a pattern fixed to the pixels, which one view cannot tell from a surface
    #: (the capture that can is :data:`SHAPE_SEPARATION`).
    mimicked_by_shape: str = ""

    @property
    def pointwise(self) -> bool:
        """:attr:`local_given_render`, defaulting to :attr:`pixel_local`."""
        return self.pixel_local if self.local_given_render is None else self.local_given_render

    # -------------------------------------------------------------- values
    def off_values(self) -> dict[str, float]:
        return {k: p.off for k, p in self.params.items()}

    def default_values(self) -> dict[str, float]:
        return {k: p.on_default for k, p in self.params.items()}

    def bounds(self) -> dict[str, tuple[float, float]]:
        return {k: (p.lo, p.hi) for k, p in self.params.items()}

    def validate(self, values: Mapping[str, Any] | None, *, source: str | Path = "<effects>",
                 prefix: str | None = None) -> dict[str, Any]:
        """Check names, types and bounds; fill defaults. Errors name ``effects.<name>.<param>``."""
        prefix = prefix or f"effects.{self.name}"
        values = {} if values is None else values
        if not isinstance(values, Mapping):
            raise InputFileError(f"got {values!r}", file=source, field=prefix,
                                 expected="a mapping of parameter values")
        known = list(self.params) + list(self.options)
        out: dict[str, Any] = self.default_values()
        for key, v in values.items():
            if key in self.options:
                out[key] = copy.deepcopy(v)
                continue
            if key not in self.params:
                raise InputFileError(f"unknown parameter {key!r}", file=source, field=f"{prefix}.{key}",
                                     expected="one of " + ", ".join(known))
            p = self.params[key]
            out[key] = Schema(source).number(v, f"{prefix}.{key}", lo=p.lo, hi=p.hi,
                                             expected=f"a number in [{p.lo:g}, {p.hi:g}] {p.unit}".rstrip())
        self.check_options(out, source=source, prefix=prefix)
        return out

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        """Validate structured options (subclasses)."""

    def is_off(self, values: Mapping[str, Any]) -> bool:
        return all(float(values.get(k, p.off)) == p.off for k, p in self.params.items())

    def form_params(self, form: str = "", n_taps: int | None = None, n_freq: int | None = None) -> dict[str, Param]:
        """The parameters diagnosis fits in ``form`` ("" the simple form), leaving out those a
        session with ``n_taps`` taps per frequency cannot see (:meth:`observable`) and those
        of a frequency it does not have (:meth:`min_frequencies`)."""
        return {k: p for k, p in self.params.items()
                if p.fitted and form in p.forms and (n_taps is None or self.observable(k, n_taps))
                and (n_freq is None or self.min_frequencies(k) <= n_freq)}

    def min_frequencies(self, param: str) -> int:
        """How many modulation frequencies a session needs for ``param`` to act (default 1)."""
        return 1

    def observable(self, param: str, n_taps: int) -> bool:
        """Whether ``param`` changes what ``n_taps`` equally spaced taps measure (default yes)."""
        return True

    def roughness(self, form: str, values: Mapping[str, Any]) -> np.ndarray | None:
        """The prior of a flexible form: a vector that is zero for the form's smoothest
        shape, its squared norm what diagnosis penalises, the strength chosen on held-out data
        (:mod:`tofhil.eval.diagnose.form_prior`). None: the form has no prior (its parameter count,
        shape and the identifiability test hold it)."""
        return None

    # -------------------------------------------------------------- stage hooks
    # Each stage has one hook (``STAGE_HOOKS``); an effect implements the hook of its stage.
    def apply_scene(self, scene: Any, values: Mapping[str, Any]) -> Any:
        """Scene stage: the Scene a new render must see with this effect at ``values``."""
        raise NotImplementedError(f"{self.name} is a {self.stage}-stage effect")

    def rescale_render(self, result: Any, values: Mapping[str, Any], rendered: Mapping[str, Any],
                       scene: Any) -> Any | None:
        """Scene stage, fast path: a cached render of ``scene`` made with this effect at
        ``rendered`` turned into the render at ``values`` without tracing rays, or None when
        only a new render is exact (the default, except when nothing changes)."""
        return result if _same_values(values, rendered) else None

    def render_requirements(self, values: Mapping[str, Any], scene: Any) -> dict[str, Any]:
        """Extra renderer arguments this effect needs (e.g. separate direct/indirect)."""
        return {}

    def apply_render(self, result: Any, values: Mapping[str, Any],
                     waveform: Mapping[int, complex] | None = None) -> OpticalSignal:
        """Render stage: the light on the sensor recombined from a render's parts."""
        raise NotImplementedError(f"{self.name} is a {self.stage}-stage effect")

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        """Signal and pixel stages: the light on the sensor changed by this effect."""
        raise NotImplementedError(f"{self.name} is a {self.stage}-stage effect")

    def apply_taps(self, taps: np.ndarray, values: Mapping[str, Any], ctx: EffectContext) -> np.ndarray:
        """Taps stage: the recorded taps ``[F, K, ...]`` (DN) changed by the readout after the
        pixel (noise and all: a tap gain scales the noise too)."""
        raise NotImplementedError(f"{self.name} is a {self.stage}-stage effect")

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "stage": self.stage, "doc": self.doc,
                "params": {k: dataclasses.asdict(p) for k, p in self.params.items()},
                "options": dict(self.options)}


def _same_values(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    return dict(a) == dict(b)


def _rotate_phase(signal: OpticalSignal, path_m: np.ndarray | float) -> OpticalSignal:
    """Add an optical path ``path_m`` (scalar, ``[H, W]`` or ``[F, H, W]``) to every harmonic:
    ``S_h *= exp(+i 2 pi h f path / c)``."""
    out = signal.copy()
    path = np.asarray(path_m, dtype=np.float64)
    if path.ndim == 3:
        path = path[:, None]  # [F, 1, H, W]
    f = signal.freq_hz[:, None, None, None]
    h = np.asarray(signal.harmonics, dtype=np.float64)[None, :, None, None]
    out.phasor_w = signal.phasor_w * np.exp(1j * 2.0 * np.pi * h * f * path / C_M_PER_S)
    return out
