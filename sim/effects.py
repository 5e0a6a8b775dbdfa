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
  ``illumination`` (the emitter's profile), ``stray_light`` (optics), ``offset`` (unmodulated charge), ``range_offset``, ``field_angle``,
  ``wiggling``, ``amplitude_dependent``.
- ``pixel``: per-pixel demodulation properties -- ``fixed_pattern``, ``range_offset_map``.

Each stage has one hook (``STAGE_HOOKS``) that its effects implement. Render-, signal- and
pixel-stage effects apply to a cached render in milliseconds; scene-stage effects whose change
is exactly a rescaling of a render (reflectance, ambient) also implement ``rescale_render``.
The twin (``tofhil.sim.twin.Twin``) runs these hooks for simulation and diagnosis alike. What
diagnosis fits of each parameter (range, step, log scale, starting points) is in its ``Param``. A scene file switches effects on with an ``effects:`` block
``{name: {param: value}}``; a missing parameter takes its ``default`` (or its off value).
See docs/effects.md.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.schema import Schema, to_plain
from tofhil.sim.sensor import OpticalSignal, SensorConfig
from tofhil.sim.straylight import StrayLightOperator, StrayLightPSF, apply_lobes, lobes_only

STAGES = ("scene", "render", "signal", "pixel")
#: The hook each stage's effects implement.
STAGE_HOOKS = {"scene": "apply_scene", "render": "apply_render", "signal": "apply_signal", "pixel": "apply_signal"}


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


class Effect:
    """Base class. Subclasses set ``name``, ``stage``, ``params``, ``options``, ``doc`` and
    implement the hook of their stage."""

    name: str = ""
    stage: str = ""
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

    def form_params(self, form: str = "", n_taps: int | None = None) -> dict[str, Param]:
        """The parameters diagnosis fits in ``form`` ("" the simple form), leaving out those a
        session with ``n_taps`` taps per frequency cannot see (:meth:`observable`)."""
        return {k: p for k, p in self.params.items()
                if p.fitted and form in p.forms and (n_taps is None or self.observable(k, n_taps))}

    def observable(self, param: str, n_taps: int) -> bool:
        """Whether ``param`` changes what ``n_taps`` equally spaced taps measure (default yes)."""
        return True

    def roughness(self, form: str, values: Mapping[str, Any]) -> np.ndarray | None:
        """The prior of a flexible form: a vector that is zero for the form's smoothest
        shape, its squared norm what diagnosis penalises, the strength chosen on held-out data
        (:mod:`tofhil.eval.form_prior`). None: the form has no prior (its parameter count,
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


# =============================================================================================
# scene stage
# =============================================================================================
# Diagnosis searches small pose errors: a bench camera is placed to a few centimetres and degrees.
_POSE_R: dict[str, Any] = {"fit": (-0.05, 0.05), "step": 1e-3}
_POSE_T: dict[str, Any] = {"fit": (-0.1, 0.1), "step": 1e-3}


class PoseEffect(Effect):
    name = "pose"
    stage = "scene"
    summary = 'camera pose error in the camera frame: `pose @ [R(r) t; 0 1]`'
    doc = ("Small rigid error of the camera pose, in the camera frame: the twin's camera is moved "
           "by the rotation vector (rx, ry, rz) and the translation (tx, ty, tz): "
           "pose' = pose @ [R(r) t; 0 1].")
    params = {
        "rx": Param(0.0, -0.2, 0.2, "rad", "rotation about the camera x axis (right)", **_POSE_R),
        "ry": Param(0.0, -0.2, 0.2, "rad", "rotation about the camera y axis (down)", **_POSE_R),
        "rz": Param(0.0, -0.2, 0.2, "rad", "rotation about the optical axis", **_POSE_R),
        "tx": Param(0.0, -0.5, 0.5, "m", "translation along camera x", **_POSE_T),
        "ty": Param(0.0, -0.5, 0.5, "m", "translation along camera y", **_POSE_T),
        "tz": Param(0.0, -0.5, 0.5, "m", "translation along the optical axis", **_POSE_T),
    }

    def apply_scene(self, scene: Any, values: Mapping[str, Any]) -> Any:
        from scipy.spatial.transform import Rotation

        delta = np.eye(4)
        delta[:3, :3] = Rotation.from_rotvec([values["rx"], values["ry"], values["rz"]]).as_matrix()
        delta[:3, 3] = [values["tx"], values["ty"], values["tz"]]
        return dataclasses.replace(scene, camera_pose=np.asarray(scene.camera_pose) @ delta)


class LensDistortionEffect(Effect):
    name = "lens_distortion"
    stage = "scene"
    summary = "OpenCV coefficients added to the camera's; the renderer's rays follow them"
    doc = ("Lens distortion the camera model lacks: OpenCV coefficients added to the camera's "
           "(k1, k2, p1, p2, k3; of a rational camera the same five, of a fisheye k1, k2, k3 of its "
           "theta polynomial, p1 and p2 then changing nothing). The renderer's pixel rays follow the "
           "distorted model.")
    params = {
        "k1": Param(0.0, -1.0, 1.0, "", "radial r^2 coefficient", fit=(-0.5, 0.5), step=0.01,
                     starts=(-0.1, 0.1, -0.25, 0.25)),
        "k2": Param(0.0, -1.0, 1.0, "", "radial r^4 coefficient", fit=(-0.5, 0.5), step=0.01),
        "p1": Param(0.0, -0.05, 0.05, "", "tangential coefficient p1"),
        "p2": Param(0.0, -0.05, 0.05, "", "tangential coefficient p2"),
        "k3": Param(0.0, -1.0, 1.0, "", "radial r^6 coefficient"),
    }

    def apply_scene(self, scene: Any, values: Mapping[str, Any]) -> Any:
        cam = scene.camera
        return dataclasses.replace(scene, camera=cam.with_added_distortion({k: float(values[k]) for k in self.params}))


class ReflectanceEffect(Effect):
    name = "reflectance"
    stage = "scene"
    summary = "NIR reflectance differing from the file's (diffuse, glossy and checker values scaled); options `materials: {name: factor}`, `objects: {name: factor}`"
    doc = ("NIR reflectance different from the scene file's: every material's diffuse and glossy "
           "reflectance (and checker texture values) times `scale`, and per material or per object "
           "times the factors in `materials: {name: factor}` / `objects: {name: factor}`.")
    params = {"scale": Param(1.0, 0.0, 20.0, "", "factor on every material's reflectance",
                             fit=(0.05, 20.0), step=0.02)}
    options = {"materials": "mapping material name -> reflectance factor",
               "objects": "mapping object name -> reflectance factor (the object gets its own material)"}

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        for key in ("materials", "objects"):
            m = values.get(key)
            if m is None:
                continue
            if not isinstance(m, Mapping):
                raise InputFileError(f"got {m!r}", file=source, field=f"{prefix}.{key}",
                                     expected="a mapping name -> factor")
            for name, fac in m.items():
                if isinstance(fac, bool) or not isinstance(fac, (int, float)) or not 0 <= fac <= 20:
                    raise InputFileError(f"got {fac!r}", file=source, field=f"{prefix}.{key}.{name}",
                                         expected="a factor in [0, 20]")

    def is_off(self, values: Mapping[str, Any]) -> bool:
        factors = list((values.get("materials") or {}).values()) + list((values.get("objects") or {}).values())
        return float(values.get("scale", 1.0)) == 1.0 and all(f == 1 for f in factors)

    @staticmethod
    def _scaled(mat: Any, s: float, name: str | None = None) -> Any:
        tex = mat.texture
        if tex is not None and tex.kind == "checker":
            tex = dataclasses.replace(tex, values=tuple(v * s for v in tex.values))
        return dataclasses.replace(mat, name=name or mat.name, reflectance=mat.reflectance * s,
                                   glossy_reflectance=mat.glossy_reflectance * s, texture=tex)

    def apply_scene(self, scene: Any, values: Mapping[str, Any]) -> Any:
        scale = float(values.get("scale", 1.0))
        per_mat = dict(values.get("materials") or {})
        per_obj = dict(values.get("objects") or {})
        for name in per_mat:
            if name not in scene.materials:
                raise InputFileError(f"no material {name!r} in the scene", file=scene.source,
                                     field=f"effects.reflectance.materials.{name}",
                                     expected="one of " + ", ".join(scene.materials))
        names = [o.name for o in scene.objects]
        for name in per_obj:
            if name not in names:
                raise InputFileError(f"no object {name!r} in the scene", file=scene.source,
                                     field=f"effects.reflectance.objects.{name}",
                                     expected="one of " + ", ".join(names))
        mats = {k: self._scaled(m, scale * float(per_mat.get(k, 1.0))) for k, m in scene.materials.items()}
        objects = list(scene.objects)
        for i, o in enumerate(objects):
            if o.name in per_obj:
                own = f"{o.material}@{o.name}"
                mats[own] = self._scaled(mats[o.material], float(per_obj[o.name]), own)
                objects[i] = dataclasses.replace(o, material=own)
        return dataclasses.replace(scene, materials=mats, objects=objects)

    def rescale_render(self, result: Any, values: Mapping[str, Any], rendered: Mapping[str, Any],
                       scene: Any) -> Any | None:
        """Light that reflected n times scales as ``s^n``: exact for the direct light (n = 1) and
        one bounce (n = 2) when every material scales alike (the renderer's paths do not depend
        on the reflectance); a render with more bounces, per-material factors, a transient or a
        zero reference needs a new render."""
        if _same_values(values, rendered):
            return result
        s_new, s_ref = float(values.get("scale", 1.0)), float(rendered.get("scale", 1.0))
        same_options = all(dict(values.get(k) or {}) == dict(rendered.get(k) or {}) for k in ("materials", "objects"))
        if not same_options or s_ref <= 0.0 or result.transient is not None or result.bounces > 1:
            return None
        s = s_new / s_ref
        changes: dict[str, Any] = {"ambient_power_w": result.ambient_power_w * s}
        if result.ambient_power_per_irradiance is not None:
            changes["ambient_power_per_irradiance"] = result.ambient_power_per_irradiance * s
        if result.bounces == 0:
            changes.update(phasor=result.phasor * s, power_w=result.power_w * s)
            if result.phasor_direct is not None:
                changes.update(phasor_direct=result.phasor_direct * s, phasor_indirect=result.phasor_indirect * s)
            return dataclasses.replace(result, **changes)
        freq = np.asarray(result.freq_hz)
        zero = np.flatnonzero(freq == 0.0)
        if result.phasor_direct is None or result.phasor_indirect is None or not zero.size:
            return None  # the direct/indirect split of the power is unknown
        direct, indirect = result.phasor_direct * s, result.phasor_indirect * (s * s)
        p_direct = result.phasor_direct[zero[0], tuple(result.harmonics).index(1)].real
        changes.update(phasor_direct=direct, phasor_indirect=indirect, phasor=direct + indirect,
                       power_w=s * p_direct + (s * s) * (result.power_w - p_direct))
        return dataclasses.replace(result, **changes)


class AmbientEffect(Effect):
    name = "ambient"
    stage = "scene"
    summary = 'ambient irradiance added on every surface (offset and shot noise, no phase)'
    doc = ("Unmodulated ambient light (sun, lamps) added to the scene's ambient irradiance on every "
           "surface; it raises the tap offset and the shot noise, not the phase.")
    params = {"irradiance_w_m2": Param(0.0, 0.0, 2000.0, "W/m^2", "added ambient irradiance (NIR band)",
                                       default=1.0, fit=(0.0, 2000.0), step=1.0, start=5.0)}

    def apply_scene(self, scene: Any, values: Mapping[str, Any]) -> Any:
        return dataclasses.replace(scene, ambient_irradiance_w_m2=scene.ambient_irradiance_w_m2
                                   + float(values["irradiance_w_m2"]))

    def rescale_render(self, result: Any, values: Mapping[str, Any], rendered: Mapping[str, Any],
                       scene: Any) -> Any | None:
        """Ambient power is linear in the irradiance (the render keeps the power per W/m^2)."""
        if _same_values(values, rendered):
            return result
        if result.ambient_power_per_irradiance is None:
            return None
        e = scene.ambient_irradiance_w_m2 - float(rendered["irradiance_w_m2"]) + float(values["irradiance_w_m2"])
        return dataclasses.replace(result, ambient_power_w=result.ambient_power_per_irradiance * e)


# =============================================================================================
# render stage
# =============================================================================================
class MultipathEffect(Effect):
    name = "multipath"
    stage = "render"
    summary = '`S = S_direct + scale * S_indirect` (0 = direct only, 1 = physical); option `bounces` (default max(2, render.bounces))'
    doc = ("Scale of the indirect (multi-bounce) light: S = S_direct + scale * S_indirect. 0 = direct "
           "only, 1 = physical. Needs a render with separate direct/indirect phasors and bounces > 0 "
           "(`bounces` option; default the scene's render.bounces, at least 2). A scene without this "
           "effect uses whatever the renderer computed.")
    params = {"scale": Param(0.0, 0.0, 3.0, "", "factor on the indirect light", default=1.0,
                             fit=(0.0, 3.0), step=0.1, start=1.0)}
    options = {"bounces": "number of indirect bounces to render (integer >= 1)"}

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        b = values.get("bounces")
        if b is not None and (isinstance(b, bool) or not isinstance(b, int) or b < 1):
            raise InputFileError(f"got {b!r}", file=source, field=f"{prefix}.bounces",
                                 expected="an integer >= 1")

    def render_requirements(self, values: Mapping[str, Any], scene: Any) -> dict[str, Any]:
        b = values.get("bounces") or max(2, int(scene.render.bounces))
        return {"separate_direct": True, "bounces": int(b)}

    def apply_render(self, result: Any, values: Mapping[str, Any],
                     waveform: Mapping[int, complex] | None = None) -> OpticalSignal:
        return OpticalSignal.from_render(result, waveform, multipath_scale=float(values["scale"]))


# =============================================================================================
# signal stage
# =============================================================================================
class StrayLightEffect(Effect):
    name = "stray_light"
    stage = "signal"
    pixel_local = False
    summary = 'lens scattering `S_meas = (delta + h) * S`; options below'
    doc = ("Lens scattering: S_meas = (delta + h) * S on every frequency, harmonic and on the "
           "unmodulated light (sim/straylight.py). h = a Gaussian (weight, sigma_px) + more Gaussians "
           "+ a uniform veil + a ghost mirrored through the optical centre, or a measured PSF image; "
           "each weight is the fraction of light it moves.")
    params = {
        "weight": Param(0.0, 0.0, 0.5, "", "fraction of light in the main Gaussian lobe", default=0.02,
                        fit=(0.0, 0.3), step=0.01, start=0.02),
        "sigma_px": Param(20.0, 0.3, 1000.0, "px", "sigma of the main lobe (x, and y unless sigma_y_px)",
                          fit=(0.5, 300.0), step=5.0, start=15.0, starts=(4.0, 50.0)),
        "veil": Param(0.0, 0.0, 0.5, "", "fraction spread uniformly over the sensor", fit=(0.0, 0.2), step=0.002,
                      starts=(0.01,)),
        "ghost_weight": Param(0.0, 0.0, 0.2, "", "fraction imaged mirrored through the optical centre"),
        "ghost_sigma_px": Param(2.0, 0.0, 100.0, "px", "blur of the ghost"),
    }
    options = {"sigma_y_px": "sigma of the main lobe along y (default sigma_px)",
               "gaussians": "more lobes: [[weight, sigma_x_px, sigma_y_px(, field_weight(, field_weight4))], ...]; "
                            "field_weight makes a lobe shift-variant: weight + field_weight rho^2 "
                            "(+ field_weight4 rho^4; rho = 0 at the principal point, 1 at the sensor's corner)",
               "radial": "free-form lobe: {radii_px: [...], values: [per-pixel fraction at each radius], "
                         "field_values: [...], aspect: A}; piecewise linear in log r, heavy tails allowed",
               "ghost_center_px": "[x, y] the ghost mirrors through (default the principal point)",
               "ghosts": "more ghosts: [[weight, sigma_px], ...] or [[weight, sigma_px, cx, cy], ...], or mappings "
                         "{weight, sigma_px, magnification, extra_path_m, center_px} (light at p lands at "
                         "c + m (p - c), delayed by extra_path_m; a lens prescription's ghosts)",
               "psf_file": "measured PSF image (.npy/.png/.tif; its peak pixel is the direct light)",
               "psf_center_px": "[x, y] of the PSF image's direct pixel (default its maximum)",
               "psf_scale": "factor on the measured PSF's scattered part (default 1)",
               "conserve": "true: h moves light (energy conserved); false: h adds light",
               "direct": "fraction of a pixel's light kept on it (default 1 - total weight, or 1 "
                         "without conserve); a calibration fits it"}

    def validate(self, values: Mapping[str, Any] | None, *, source: str | Path = "<effects>",
                 prefix: str | None = None) -> dict[str, Any]:
        out = super().validate(values, source=source, prefix=prefix)
        given = values or {}
        components = ("veil", "ghost_weight", "gaussians", "ghosts", "psf_file", "radial")
        if "weight" not in given and any(given.get(c) for c in components):
            out["weight"] = 0.0  # the default lobe only stands in when no component is named
        self.psf(out, source=source, prefix=prefix or "effects.stray_light", check_file=False)
        return out

    def is_off(self, values: Mapping[str, Any]) -> bool:
        extra = values.get("gaussians") or values.get("ghosts") or values.get("psf_file") or values.get("radial")
        direct = values.get("direct")
        return super().is_off(values) and not extra and (direct is None or float(direct) == 1.0)

    @staticmethod
    def psf(values: Mapping[str, Any], *, source: str | Path = "<effects>", prefix: str = "effects.stray_light",
            base_dir: Path | None = None, check_file: bool = True) -> StrayLightPSF:
        """The effect's parameters -> the one PSF type of sim/straylight.py."""
        p = dict(values)
        if not check_file:
            p.pop("psf_file", None)
        return StrayLightPSF.from_params(p, source=source, prefix=prefix, base_dir=base_dir)

    @staticmethod
    def values(psf: StrayLightPSF, measured_file: str | None = None) -> dict[str, Any]:
        """A PSF (calibrated, diagnosed or loaded) -> this effect's parameters."""
        return psf.to_params(measured_file)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        psf = self.psf(values, source=ctx.source, base_dir=ctx.base_dir)
        if psf.is_identity:
            return signal
        if lobes_only(psf):
            # (the form diagnosis fits: the light's transform is kept while only the PSF changes)
            n = signal.phasor_w.shape[:-2]
            shape = signal.shape
            stack = np.concatenate([signal.phasor_w.reshape((-1,) + shape),
                                    np.broadcast_to(signal.dc_w, shape)[None], np.broadcast_to(signal.ambient_w, shape)[None]])
            res = apply_lobes(psf, stack)
            k = int(np.prod(n))
            return dataclasses.replace(signal, phasor_w=res[:k].reshape(signal.phasor_w.shape), dc_w=res[k].real.copy(),
                                       ambient_w=res[k + 1].real.copy(), waveform=dict(signal.waveform))
        op = StrayLightOperator(psf, signal.shape, (ctx.camera.cx, ctx.camera.cy))
        out = signal.copy()
        # Each channel's modulation frequency: a ghost's extra optical path delays its phasor.
        freq = (signal.freq_hz[:, None] * np.asarray(signal.harmonics, dtype=np.float64)[None, :])[..., None, None]
        out.phasor_w = op.apply(signal.phasor_w, freq_hz=freq)
        both = op.apply(np.stack([signal.dc_w, signal.ambient_w]))  # unmodulated light scatters too
        out.dc_w, out.ambient_w = both[0], both[1]
        return out


class RangeOffsetEffect(Effect):
    name = "range_offset"
    stage = "signal"
    summary = 'constant optical-path offset: reads `path_m / 2` farther'
    doc = ("A constant optical-path offset (e.g. an electronic delay between the emitter drive and "
           "the pixel clock): L -> L + path_m on every pixel, so the radial distance reads "
           "path_m / 2 farther.")
    params = {"path_m": Param(0.0, -2.0, 2.0, "m", "optical path length added (radial shift = half)",
                              default=0.02, fit=(-2.0, 2.0), step=0.01)}

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        return _rotate_phase(signal, float(values["path_m"]))


def harmonic_aliases(h: int, n_taps: int) -> bool:
    """Whether harmonic ``h`` of the correlation waveform reaches the estimate
    ``S = (2/K) sum_k c_k exp(i theta_k)`` of ``K = n_taps`` equally spaced taps: the sum over
    the taps keeps exactly the orders ``h = +-1 (mod K)``, each folded onto the fundamental
    (K = 4: every odd order, 3 and 7 as ``exp(-i(h-1) phi)``, 5 as ``exp(+i 4 phi)``; K = 3:
    2, 4, 5, 7 but not 3). Other orders cancel and cannot be seen in the data."""
    return h % n_taps in (1, n_taps - 1)


_WIGGLE_ORDERS = (3, 5, 7)
_AMP: dict[str, Any] = {"fit": (0.0, 0.5), "step": 0.01}
_PHASE: dict[str, Any] = {"fit": (-math.pi, math.pi), "step": 0.3, "periodic": True}
_ALL = ("harmonics",)


class WigglingEffect(Effect):
    name = "wiggling"
    stage = "signal"
    summary = ('odd harmonics 3, 5, 7 of the correlation waveform; harmonic h reaches K taps only if h = +-1 mod K '
               '(K = 4: phase error about `-a3 sin(4 phi + psi3) + a5 sin(4 phi + psi5) - a7 sin(8 phi + psi7)`)')
    doc = ("Non-sinusoidal modulation: odd harmonics of the correlation waveform, added to the "
           "emitter's. With K taps harmonic h aliases onto the fundamental when h = +-1 mod K and gives a "
           "cyclic distance error (K = 4: the 3rd and 5th give 4 cycles per ambiguity range, the 7th 8); "
           "other orders cancel. Harmonics the render did not compute are synthesised from the "
           "fundamental (exact for single-path pixels). Diagnosis fits the 3rd harmonic (simple form) "
           "or every visible order up to the 7th (form `harmonics`).")
    forms = {"harmonics": "all odd harmonics up to the 7th that the session's taps see (amplitude and phase each)"}
    params = {
        "h3_amplitude": Param(0.0, 0.0, 0.5, "", "3rd-harmonic correlation amplitude / fundamental's",
                              default=0.05, start=0.03, forms=("",) + _ALL, **_AMP),
        "h3_phase_rad": Param(0.0, -math.pi, math.pi, "rad", "3rd-harmonic phase", start=0.0, starts=(-2.0, 2.0),
                              forms=("",) + _ALL, **_PHASE),
        "h5_amplitude": Param(0.0, 0.0, 0.5, "", "5th-harmonic correlation amplitude / fundamental's",
                              start=0.01, forms=_ALL, **_AMP),
        "h5_phase_rad": Param(0.0, -math.pi, math.pi, "rad", "5th-harmonic phase", start=0.0, starts=(-2.0, 2.0),
                              forms=_ALL, **_PHASE),
        "h7_amplitude": Param(0.0, 0.0, 0.5, "", "7th-harmonic correlation amplitude / fundamental's",
                              start=0.01, forms=_ALL, **_AMP),
        "h7_phase_rad": Param(0.0, -math.pi, math.pi, "rad", "7th-harmonic phase", start=0.0, starts=(-2.0, 2.0),
                              forms=_ALL, **_PHASE),
    }

    def is_off(self, values: Mapping[str, Any]) -> bool:
        return not self.harmonics(values)

    @staticmethod
    def harmonics(values: Mapping[str, Any]) -> tuple[int, ...]:
        return tuple(h for h in _WIGGLE_ORDERS if float(values.get(f"h{h}_amplitude", 0.0)) != 0.0)

    def observable(self, param: str, n_taps: int) -> bool:
        return harmonic_aliases(int(param[1:param.index("_")]), n_taps)

    def roughness(self, form: str, values: Mapping[str, Any]) -> np.ndarray | None:
        # the harmonics beyond the 3rd shrink to zero: a ridge on their complex amplitudes (in
        # units of their typical size 0.01; amplitude and phase alike, so that the phase of a
        # small harmonic is not a free parameter); only the simple form's 3rd is smoothest
        if form != "harmonics":
            return None
        out = []
        for h in _WIGGLE_ORDERS[1:]:
            a, psi = float(values.get(f"h{h}_amplitude", 0.0)), float(values.get(f"h{h}_phase_rad", 0.0))
            out += [a * math.cos(psi) / 0.01, a * math.sin(psi) / 0.01]
        return np.array(out)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        out = signal.copy()
        for h in self.harmonics(values):
            a = float(values[f"h{h}_amplitude"])
            out.waveform[h] = out.waveform.get(h, 0.0) + a * np.exp(1j * float(values[f"h{h}_phase_rad"]))
        return out


#: Knots of the amplitude-dependent spline, log10 of the modulation amplitude in electrons per tap.
AMPLITUDE_KNOTS_LOG10_E = (2.0, 2.75, 3.5, 4.25, 5.0)
_SPLINE = ("spline",)


def stick_breaking(q: np.ndarray) -> np.ndarray:
    """Fractions ``w_1..w_m >= 0`` summing to 1 from ``m - 1`` numbers in [0, 1]: ``w_j = q_j
    prod_{i<j} (1 - q_i)``, the last takes what is left. ``q_j = 1 / (m - j + 1)`` gives equal parts."""
    rest = np.concatenate([[1.0], np.cumprod(1.0 - q)])
    return np.concatenate([q, [1.0]]) * rest


def monotone_spline(x: np.ndarray, knots: np.ndarray, level: float, span: float, q: np.ndarray) -> np.ndarray:
    """Piecewise linear in ``x`` through the knots, ``level`` at and below the first knot,
    ``level + span`` at and above the last, the rise between knots ``span * w_j`` with ``w`` from
    :func:`stick_breaking`: monotone (in the sign of ``span``) for every parameter value."""
    steps = span * stick_breaking(np.asarray(q, dtype=np.float64))
    values = level + np.concatenate([[0.0], np.cumsum(steps)])
    return np.interp(x, knots, values)


class AmplitudeDependentEffect(Effect):
    name = "amplitude_dependent"
    stage = "signal"
    summary = ('radial error as a function of A, the modulation amplitude per tap in electrons: '
               '`error_m * exp(-A / amplitude_e)` plus, as the flexible form `spline`, a monotone piecewise-linear '
               'function of log10 A (knots at 10^2 ... 10^5 e-)')
    doc = ("Range error that depends on the signal strength (pixel nonlinearity and charge-transfer "
           "lag at low signal): radial error = error_m * exp(-A / amplitude_e) + s(log10 A), with A the "
           "pixel's modulation amplitude in electrons per tap at that frequency (needs the sensor block). "
           "s is monotone by construction: piecewise linear through knots at log10 A = "
           + ", ".join(f"{k:g}" for k in AMPLITUDE_KNOTS_LOG10_E) + ", spline_level_m at and below the "
           "first, rising (or falling) by spline_span_m to the last, the share of each interval from the "
           "stick-breaking fractions spline_q1..q3 (their off values give equal shares: an error linear in "
           "log A). Diagnosis fits the exponential (simple form) or the spline (form `spline`).")
    forms = {"spline": "monotone piecewise-linear error in log10 amplitude (level, span, 3 shape fractions)"}
    params = {
        "error_m": Param(0.0, -0.5, 0.5, "m", "radial error at zero amplitude", default=0.01, fit=(-0.5, 0.5),
                         step=0.01, start=0.02, starts=(-0.02,)),
        "amplitude_e": Param(1000.0, 1.0, 1.0e6, "e-", "amplitude scale A0 over which the error decays",
                             fit=(0.0, 6.0), step=0.2, log=True, start=1000.0,
                             starts=(10.0 ** 2.5, 10.0 ** 3.5)),
        "spline_level_m": Param(0.0, -0.5, 0.5, "m", "spline: radial error at and below the first knot",
                                fit=(-0.3, 0.3), step=0.005, start=-0.02, starts=(0.02,), forms=_SPLINE),
        "spline_span_m": Param(0.0, -0.5, 0.5, "m", "spline: error at the last knot minus at the first",
                               fit=(-0.3, 0.3), step=0.005, start=0.03, starts=(-0.03,), forms=_SPLINE),
        "spline_q1": Param(0.25, 0.0, 1.0, "", "spline: share of the span in the 1st interval",
                           fit=(0.0, 1.0), step=0.05, forms=_SPLINE),
        "spline_q2": Param(1.0 / 3.0, 0.0, 1.0, "", "spline: share of the rest in the 2nd interval",
                           fit=(0.0, 1.0), step=0.05, forms=_SPLINE),
        "spline_q3": Param(0.5, 0.0, 1.0, "", "spline: share of the rest in the 3rd interval (the 4th takes the rest)",
                           fit=(0.0, 1.0), step=0.05, forms=_SPLINE),
    }

    def is_off(self, values: Mapping[str, Any]) -> bool:
        return float(values.get("error_m", 0.0)) == 0.0 and float(values.get("spline_level_m", 0.0)) == 0.0 \
            and float(values.get("spline_span_m", 0.0)) == 0.0

    def roughness(self, form: str, values: Mapping[str, Any]) -> np.ndarray | None:
        # a smoothness prior: the second differences of the spline's values at its knots, in
        # units of 5 mm; an error linear in log A (any level and span) costs nothing
        if form != "spline":
            return None
        p = self.params
        q = np.array([float(values.get(f"spline_q{j}", p[f"spline_q{j}"].off)) for j in (1, 2, 3)])
        knots = np.asarray(AMPLITUDE_KNOTS_LOG10_E)
        at_knots = monotone_spline(knots, knots, float(values.get("spline_level_m", 0.0)),
                                   float(values.get("spline_span_m", 0.0)), q)
        return np.diff(at_knots, 2) / 0.005

    @staticmethod
    def error_m(values: Mapping[str, Any], amp_e: np.ndarray) -> np.ndarray:
        """The radial error at modulation amplitude ``amp_e`` (electrons per tap)."""
        p = AmplitudeDependentEffect.params
        err = float(values.get("error_m", 0.0)) * np.exp(-amp_e / float(values.get("amplitude_e", 1000.0)))
        level, span = float(values.get("spline_level_m", 0.0)), float(values.get("spline_span_m", 0.0))
        if level or span:
            q = np.array([float(values.get(f"spline_q{j}", p[f"spline_q{j}"].off)) for j in (1, 2, 3)])
            x = np.log10(np.maximum(amp_e, 1e-3))
            err = err + monotone_spline(x, np.asarray(AMPLITUDE_KNOTS_LOG10_E), level, span, q)
        return err

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        if ctx.sensor is None:
            raise ValueError("amplitude_dependent needs the sensor configuration (electrons per watt)")
        s = ctx.sensor
        amp_e = (s.tap_fraction * s.modulation_contrast * s.electrons_per_watt
                 * np.abs(signal.phasor_w[:, signal.harmonics.index(1)]))  # [F, H, W]
        return _rotate_phase(signal, 2.0 * self.error_m(values, amp_e))  # radial error -> optical path


class FieldAngleEffect(Effect):
    name = "field_angle"
    stage = "signal"
    summary = 'radial error growing with the field angle: `c2 t^2 + c4 t^4`, t = tan(field angle) of the pixel ray'
    doc = ("Range error that depends on the field angle (lens and illumination path differences, "
           "optical path through the lens varying over the field): radial error = c2 t^2 + c4 t^4 "
           "with t the tangent of the pixel ray's angle to the optical axis (undistorted pinhole). "
           "Even in t: a rotationally symmetric lens.")
    params = {
        "c2_m": Param(0.0, -1.0, 1.0, "m", "radial error per tan^2 of the field angle", default=0.01,
                      fit=(-0.5, 0.5), step=0.002),
        "c4_m": Param(0.0, -1.0, 1.0, "m", "radial error per tan^4 of the field angle",
                      fit=(-0.5, 0.5), step=0.002),
    }

    @staticmethod
    def tan2(camera: CameraModel, shape: tuple[int, int]) -> np.ndarray:
        v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
        return ((u - camera.cx) / camera.fx) ** 2 + ((v - camera.cy) / camera.fy) ** 2

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        t2 = self.tan2(ctx.camera, signal.shape)
        err = float(values["c2_m"]) * t2 + float(values["c4_m"]) * t2 * t2
        return _rotate_phase(signal, 2.0 * err)  # radial error -> optical path


class IlluminationEffect(Effect):
    name = "illumination"
    stage = "signal"
    summary = ("emitter illumination profile the scene lacks: the emitter light on each pixel times "
               "`cos(alpha)^dn (1 + b4 t^4 + b6 t^6)`, alpha the pixel ray's field angle, t = tan(alpha)")
    doc = ("The emitter's illumination profile differing from the scene's beam (a cos^n beam of "
           "another exponent, a diffuser, an LED array, a cover glass): the emitter's light on each "
           "pixel (modulated and unmodulated, not ambient) times cos(alpha)^dn (1 + b4 t^4 + b6 t^6), "
           "clipped at 0, with alpha the pixel ray's angle to the optical axis and t = tan(alpha) "
           "(emitter next to the lens: a point seen at field angle alpha is lit at about alpha; "
           "indirect light is scaled like the direct light of its pixel). dn changes the exponent of "
           "the scene's cos^n beam (the simple form); b4 and b6 bend the profile further (the flexible "
           "form `radial`; no t^2 term: to first order it is dn). Changes the amplitude only; acts "
           "before the lens's stray light.")
    forms = {"radial": "cos^dn times a radial polynomial 1 + b4 t^4 + b6 t^6"}
    params = {
        "dn": Param(0.0, -20.0, 20.0, "", "change of the beam's cos^n exponent", default=1.0,
                    fit=(-10.0, 10.0), step=0.05, forms=("", "radial")),
        "b4": Param(0.0, -50.0, 50.0, "", "relative change per tan^4 of the field angle",
                    fit=(-20.0, 20.0), step=0.05, forms=("radial",)),
        "b6": Param(0.0, -200.0, 200.0, "", "relative change per tan^6 of the field angle",
                    fit=(-100.0, 100.0), step=0.1, forms=("radial",)),
    }

    def roughness(self, form: str, values: Mapping[str, Any]) -> np.ndarray | None:
        # the radial terms shrink to the simple cos^dn form: a ridge on what each changes at
        # t = 0.5 (about the field edge of the presets), in units of 1 % of the light
        if form != "radial":
            return None
        return np.array([float(values.get("b4", 0.0)) * 0.5 ** 4 / 0.01, float(values.get("b6", 0.0)) * 0.5 ** 6 / 0.01])

    @staticmethod
    def factor(values: Mapping[str, Any], camera: CameraModel, shape: tuple[int, int]) -> np.ndarray:
        t2 = FieldAngleEffect.tan2(camera, shape)
        poly = 1.0 + float(values.get("b4", 0.0)) * t2 ** 2 + float(values.get("b6", 0.0)) * t2 ** 3
        # cos^2(alpha) = 1 / (1 + tan^2(alpha))
        return (1.0 + t2) ** (-0.5 * float(values.get("dn", 0.0))) * np.maximum(poly, 0.0)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        g = self.factor(values, ctx.camera, signal.shape)
        out = signal.copy()
        out.phasor_w = signal.phasor_w * g
        out.dc_w = np.asarray(signal.dc_w) * g
        return out


class OffsetEffect(Effect):
    name = "offset"
    stage = "signal"
    summary = 'unmodulated charge the scene does not explain (dark/black-level offset, LED leakage, a glowing cover): `dark_e` electrons per tap on every pixel'
    doc = ("Unmodulated charge that is not scene ambient: a dark or black-level offset the sensor "
           "model lacks, or unmodulated light not from the scene (emitter leakage, a glowing cover "
           "glass), uniform over the sensor. It raises every tap by dark_e electrons (the tap "
           "offset, and the shot noise) and leaves the phase alone; unlike ambient it does not "
           "follow the scene's reflectance or the lens.")
    params = {"dark_e": Param(0.0, 0.0, 1.0e6, "e-", "unmodulated electrons added to every tap", default=100.0,
                              fit=(0.0, 2.0e5), step=50.0, start=100.0, starts=(1.0e3, 1.0e4, 5.0e4))}

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        if ctx.sensor is None:
            raise ValueError("offset needs the sensor configuration (electrons per watt)")
        out = signal.copy()
        # the sensor turns unmodulated power P into tap_fraction * e_per_W * P electrons per tap
        e_w = ctx.sensor.tap_fraction * ctx.sensor.electrons_per_watt
        out.ambient_w = np.array(signal.ambient_w) + float(values["dark_e"]) / e_w
        return out


# =============================================================================================
# pixel stage
# =============================================================================================
class FixedPatternEffect(Effect):
    name = "fixed_pattern"
    stage = "pixel"
    summary = 'per-pixel demodulation delay: row/column gradients about the image centre (clock distribution) plus a seeded random part (option `seed`); a delay tau reads `c tau / 2` farther'
    doc = ("Per-pixel demodulation delay pattern: linear row and column gradients (the modulation "
           "clock reaching rows/columns at different times) about the image centre, plus a seeded "
           "random per-pixel part. tau > 0 reads farther by c tau / 2.")
    params = {
        "row_delay_s": Param(0.0, -2e-11, 2e-11, "s/row", "delay per row from the image centre",
                             fit=(-2e-11, 2e-11), step=1e-13),
        "col_delay_s": Param(0.0, -2e-11, 2e-11, "s/column", "delay per column from the image centre",
                             fit=(-2e-11, 2e-11), step=1e-13),
        "random_delay_s": Param(0.0, 0.0, 1e-10, "s", "standard deviation of the random per-pixel delay",
                                default=5e-12),
    }
    options = {"seed": "seed of the random part (integer >= 0, default 0)"}

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        s = values.get("seed", 0)
        if isinstance(s, bool) or not isinstance(s, int) or s < 0:
            raise InputFileError(f"got {s!r}", file=source, field=f"{prefix}.seed", expected="an integer >= 0")

    @staticmethod
    def delay_s(values: Mapping[str, Any], shape: tuple[int, int]) -> np.ndarray:
        h, w = shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        tau = float(values["row_delay_s"]) * (v - (h - 1) / 2) + float(values["col_delay_s"]) * (u - (w - 1) / 2)
        sd = float(values["random_delay_s"])
        if sd:
            rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(values.get("seed", 0)), 0xF1])))
            tau = tau + sd * rng.standard_normal(shape)
        return tau

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        return _rotate_phase(signal, C_M_PER_S * self.delay_s(values, signal.shape))


class RangeOffsetMapEffect(Effect):
    name = "range_offset_map"
    stage = "pixel"
    summary = ('fixed-pattern radial offset map `[H, W]` (m): per-column, per-row and per-pixel offsets of the readout; '
               'option `file` (.npy beside the scene) or `values` (inline rows); diagnosis fits it in closed form')
    doc = ("Fixed-pattern range offsets a real readout has and no parametric form names: a radial offset "
           "per pixel, read from a map [H, W] in metres (the camera's size). Every harmonic's phase moves "
           "as if the pixel read map[v, u] farther (optical path 2 map). Diagnosis fits the map in closed "
           "form (per-column + per-row + per-pixel, ridge-regularised; eval/linear_forms.py) and writes "
           "it as range_offset_map.npy beside diagnosis.json.")
    params: dict[str, Param] = {}
    options = {"file": ".npy file holding the map [H, W] in metres (relative to the scene file)",
               "values": "the map inline: H rows of W radial offsets in metres"}

    def is_off(self, values: Mapping[str, Any]) -> bool:
        return values.get("file") is None and values.get("values") is None

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        f = values.get("file")
        if f is not None and values.get("values") is not None:
            raise InputFileError("both file and values given", file=source, field=f"{prefix}.file",
                                 expected="one of file or values")
        if f is not None:
            if not isinstance(f, (str, Path)) or not str(f):
                raise InputFileError(f"got {f!r}", file=source, field=f"{prefix}.file",
                                     expected="the path of a .npy map")
            base = Path(str(source)).parent if Path(str(source)).is_file() else None
            if base is not None or Path(str(f)).is_absolute():  # resolvable now: check it at load time
                self.load(values, base_dir=base, source=source, prefix=prefix)
        elif values.get("values") is not None:
            self.load(values, source=source, prefix=prefix)

    @staticmethod
    def load(values: Mapping[str, Any], *, base_dir: Path | None = None, source: str | Path = "<effects>",
             prefix: str = "effects.range_offset_map", shape: tuple[int, int] | None = None) -> np.ndarray:
        """The map [H, W] (m), from ``file`` or ``values``; errors name the file and the field."""
        expected = "a finite 2-D array of radial offsets in metres" + (
            f" of shape {shape[0]} x {shape[1]} (the camera's rows x columns)" if shape else "")
        if values.get("file") is not None:
            f = Path(str(values["file"]))
            if not f.is_absolute() and base_dir is not None:
                f = base_dir / f
            where, field_ = f, prefix + ".file"
            try:
                m = np.load(f, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise InputFileError(f"cannot read the map {f}: {exc}", file=source, field=field_,
                                     expected="a readable .npy file") from None
        else:
            where, field_ = Path(str(source)), prefix + ".values"
            try:
                m = np.asarray(values["values"], dtype=np.float64)
            except (TypeError, ValueError):
                raise InputFileError("not a numeric array", file=source, field=field_, expected=expected) from None
        if m.ndim != 2 or not np.issubdtype(m.dtype, np.number) or not np.all(np.isfinite(m)) \
                or (shape is not None and m.shape != tuple(shape)):
            got = f"shape {m.shape}, dtype {m.dtype}" if m.ndim else f"{m!r}"
            raise InputFileError(f"got {got} ({where})", file=source, field=field_, expected=expected)
        return m.astype(np.float64, copy=False)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        m = self.load(values, base_dir=ctx.base_dir, source=ctx.source, shape=signal.shape)
        return _rotate_phase(signal, 2.0 * m)  # radial offset -> optical path


# =============================================================================================
# registry and application
# =============================================================================================
#: Forward-model order (optics before the pixel; per-pixel effects after the spatial mixing).
ORDER = ("pose", "lens_distortion", "reflectance", "ambient", "multipath", "illumination", "stray_light", "offset",
         "range_offset", "field_angle", "fixed_pattern", "range_offset_map", "amplitude_dependent", "wiggling")

EFFECTS: dict[str, Effect] = {e.name: e for e in (
    PoseEffect(), LensDistortionEffect(), ReflectanceEffect(), AmbientEffect(), MultipathEffect(),
    IlluminationEffect(), StrayLightEffect(), OffsetEffect(), RangeOffsetEffect(), FieldAngleEffect(), FixedPatternEffect(),
    RangeOffsetMapEffect(),
    AmplitudeDependentEffect(), WigglingEffect())}
assert tuple(sorted(EFFECTS)) == tuple(sorted(ORDER))
for _e in EFFECTS.values():  # every effect implements the hook of its stage
    assert _e.stage in STAGES and getattr(type(_e), STAGE_HOOKS[_e.stage]) is not getattr(Effect, STAGE_HOOKS[_e.stage]), _e.name


def parse_effects(block: Mapping[str, Any] | None, *, source: str | Path = "<effects>") -> dict[str, dict[str, Any]]:
    """Validate an ``effects:`` block into ``{name: values}`` in forward-model order.

    ``{name: null}`` or ``{name: {}}`` switches the effect on with its defaults; ``{name:
    {enabled: false, ...}}`` keeps it off."""
    block = {} if block is None else block
    if not isinstance(block, Mapping):
        raise InputFileError(f"got {block!r}", file=source, field="effects",
                             expected="a mapping effect name -> parameters")
    for name in block:
        if name not in EFFECTS:
            raise InputFileError(f"unknown effect {name!r}", file=source, field=f"effects.{name}",
                                 expected="one of " + ", ".join(ORDER))
    out: dict[str, dict[str, Any]] = {}
    for name in ORDER:
        if name not in block:
            continue
        raw = dict(block[name] or {})
        enabled = raw.pop("enabled", True)
        if not isinstance(enabled, bool):
            raise InputFileError(f"got {enabled!r}", file=source, field=f"effects.{name}.enabled",
                                 expected="true or false")
        if enabled:
            out[name] = EFFECTS[name].validate(raw, source=source)
    return out


def effects_by_stage(effects: Mapping[str, Mapping[str, Any]], *stages: str) -> list[tuple[Effect, Mapping[str, Any]]]:
    return [(EFFECTS[n], effects[n]) for n in ORDER if n in effects and EFFECTS[n].stage in stages]


def apply_scene_effects(scene: Any, effects: Mapping[str, Mapping[str, Any]]) -> Any:
    """The Scene with every scene-stage effect applied (a new Scene; the input is unchanged)."""
    for eff, values in effects_by_stage(effects, "scene"):
        if not eff.is_off(values):
            scene = eff.apply_scene(scene, values)
    return scene


def apply_signal_effects(signal: OpticalSignal, effects: Mapping[str, Mapping[str, Any]],
                         ctx: EffectContext) -> OpticalSignal:
    """Signal- and pixel-stage effects in forward-model order."""
    for eff, values in effects_by_stage(effects, "signal", "pixel"):
        if not eff.is_off(values):
            signal = eff.apply_signal(signal, values, ctx)
    return signal


def render_requirements(effects: Mapping[str, Mapping[str, Any]], scene: Any) -> dict[str, Any]:
    """Renderer arguments the effects need (merged)."""
    req: dict[str, Any] = {}
    for eff, values in effects_by_stage(effects, "render"):
        req.update(eff.render_requirements(values, scene))
    return req


def effects_to_block(effects: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Plain (YAML/JSON-safe) form of parsed effects, for embedding in files."""
    return {n: to_plain(dict(v)) for n, v in effects.items()}


def describe_effects() -> list[dict[str, Any]]:
    """Every effect's name, stage, meaning, parameters (off, bounds, unit) and options."""
    return [EFFECTS[n].describe() for n in ORDER]


def _num(x: float) -> str:
    if x in (math.pi, -math.pi):
        return "-pi" if x < 0 else "pi"
    return f"{x:g}"


def effects_table_markdown() -> str:
    """The table of effects in docs/effects.md, from the registry: stage, each parameter's
    off value, bounds, unit and default, what diagnosis fits (range, step, log scale,
    start and extra starts) and what the effect models."""
    rows = ["| effect | stage | parameters: off / [lo, hi] unit / default | diagnosis fits: range (step) [start; also] "
            "| what it models |", "|---|---|---|---|---|"]
    for name in ORDER:
        e = EFFECTS[name]
        params, fits = [], []
        for k, p in e.params.items():
            text = f"`{k}` {_num(p.off)} / [{_num(p.lo)}, {_num(p.hi)}]" + (f" {p.unit}" if p.unit else "")
            if p.default is not None:
                text += f" / {_num(p.default)}"
            params.append(text)
            if p.fit is not None:
                scale = "log10 " if p.log else ""
                text = f"`{k}` {scale}[{_num(p.fit[0])}, {_num(p.fit[1])}] ({_num(p.step)})"
                tries = ([] if p.start is None else [f"start {_num(p.start)}"])
                tries += [f"also {', '.join(_num(v) for v in p.starts)}"] if p.starts else []
                if tries:
                    text += " [" + "; ".join(tries) + "]"
                if p.forms != ("",):
                    text += " {" + ", ".join(f"form `{f}`" if f else "simple form" for f in p.forms) + "}"
                fits.append(text)
        rows.append(f"| `{name}` | {e.stage} | {'; '.join(params)} | {'; '.join(fits) or '-'} | {e.summary} |")
    return "\n".join(rows) + "\n"
