"""The typed scene of the simulator twin: what :func:`tofhil.sim.scene.load_scene` builds.

Every part is validated once, when the scene is loaded: the camera (:class:`CameraModel`),
the emitter, materials and objects, the sensor (:class:`SensorConfig`, resolved against the
camera preset), the effect set (parsed by :func:`tofhil.sim.effects.parse_effects`) and the
render settings (:class:`RenderSettings`). ``dataclasses.replace`` on a Scene still accepts
plain mappings for ``sensor``, ``effects`` and ``render``: they are validated on the spot
(errors name the scene's source) and stored typed.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Mapping

import numpy as np

from tofhil.camera import CameraModel
from tofhil.schema import Schema, to_plain
from tofhil.sim.effects import effects_to_block, parse_effects
from tofhil.sim.sensor import SensorConfig

#: f-number used for the camera equation when a scene gives none (pinhole geometry, no
#: defocus). Typical ToF lenses are fast (F/1.0 .. F/1.6).
DEFAULT_F_NUMBER = 1.2

OBJECT_TYPES = ("plane", "box", "sphere", "cylinder", "mesh", "board")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
SAMPLERS = ("sobol", "random")


@dataclass(frozen=True)
class BeamProfile:
    """Relative radiant intensity of the emitter versus the angle to its axis.

    ``kind='cos_n'``: ``p(theta) = cos(theta)**n`` on the forward hemisphere (0 behind).
    ``kind='table'``: ``p`` linearly interpolated in ``theta_deg`` (0..180), 0 beyond the table.
    """

    kind: str = "cos_n"
    n: float = 1.0
    theta_deg: tuple[float, ...] = ()
    values: tuple[float, ...] = ()

    def relative(self, cos_theta: np.ndarray) -> np.ndarray:
        c = np.clip(np.asarray(cos_theta, dtype=np.float64), -1.0, 1.0)
        if self.kind == "cos_n":
            return np.where(c > 0, np.abs(c) ** self.n, 0.0)
        theta = np.degrees(np.arccos(c))
        return np.interp(theta, self.theta_deg, self.values, right=0.0)

    @cached_property
    def solid_angle_norm_sr(self) -> float:
        """``integral p(theta) dOmega`` over the sphere, so that ``I = P p / norm`` emits P."""
        if self.kind == "cos_n":
            return 2.0 * math.pi / (self.n + 1.0)
        # The table is piecewise linear in theta: a fine trapezoid in theta is exact to 1e-9.
        theta = np.linspace(0.0, math.pi, 200_001)
        p = np.interp(np.degrees(theta), self.theta_deg, self.values, right=0.0)
        return float(2.0 * math.pi * np.trapezoid(p * np.sin(theta), theta))

    def to_dict(self) -> dict[str, Any]:
        if self.kind == "cos_n":
            return {"type": "cos_n", "n": self.n}
        return {"type": "table", "theta_deg": list(self.theta_deg),
                "relative_intensity": list(self.values)}


@dataclass
class Emitter:
    """Point emitter rigidly attached to the camera.

    ``offset_m`` and ``axis`` are in the camera frame; ``harmonics`` is the modulation
    waveform as ``(order h, amplitude, phase_rad)`` triples (applied by the sensor model).
    """

    power_w: float
    offset_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    profile: BeamProfile = field(default_factory=BeamProfile)
    harmonics: tuple[tuple[int, float, float], ...] = ((1, 1.0, 0.0),)
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    @property
    def waveform(self) -> tuple[tuple[int, float, float], ...]:
        """Alias of ``harmonics``: ``[(h, amplitude, phase_rad), ...]``."""
        return self.harmonics

    def intensity_w_sr(self, cos_theta: np.ndarray) -> np.ndarray:
        """Radiant intensity ``I(theta) = P p(theta) / norm`` (W/sr)."""
        return self.power_w * self.profile.relative(cos_theta) / self.profile.solid_angle_norm_sr

    def to_dict(self) -> dict[str, Any]:
        return {"offset_m": [float(v) for v in self.offset_m], "power_w": self.power_w,
                "axis": [float(v) for v in self.axis], "profile": self.profile.to_dict(),
                "waveform": {"harmonics": [[int(h), float(a), float(p)] for h, a, p in self.harmonics]}}


@dataclass
class Texture:
    """Albedo texture: a procedural checkerboard or an image (multiplies the reflectance).

    ``checker``: solid 3-D checkerboard in the object's local frame with cells of ``size_m``
    alternating between ``values[0]`` and ``values[1]`` (absolute diffuse reflectances); cell
    boundaries at multiples of ``size_m`` in local x and y and half a cell off in z (so a
    plane's surface, local z = 0, is mid-cell); the cell containing the origin has ``values[0]``.
    ``image``: grey values in [0, 1] spanning the object's local x-y bounding box (image
    columns along +x, rows along +y), multiplied by the material's reflectance.
    """

    kind: str
    size_m: float = 0.1
    values: tuple[float, float] = (0.8, 0.1)
    file: str | None = None
    image: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        if self.kind == "checker":
            return {"type": "checker", "size_m": self.size_m, "reflectance": list(self.values)}
        return {"type": "image", "file": self.file}


@dataclass
class Material:
    """NIR surface: Lambertian ``reflectance`` plus an optional normalised Phong lobe.

    BRDF ``f = reflectance/pi + glossy_reflectance * (n+2)/(2 pi) * cos(alpha)**n`` with
    ``alpha`` the angle between the mirror direction of the light and the view direction.

    With ``ior`` the material is a smooth dielectric instead (glass, :mod:`tofhil.sim.dielectric`):
    Fresnel reflection and refraction at its surface, ``absorption_per_m`` inside; its
    ``reflectance`` is 0 (no diffuse part). With ``scattering_per_m`` it is a homogeneous
    participating medium (Henyey-Greenstein phase function, mean cosine ``anisotropy``) behind
    an index-matched boundary (``ior`` 1).
    """

    name: str
    reflectance: float
    glossy_reflectance: float = 0.0
    glossy_exponent: float = 0.0
    texture: Texture | None = None
    ior: float | None = None
    absorption_per_m: float = 0.0
    scattering_per_m: float = 0.0
    anisotropy: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        if self.ior is not None:
            d = {"ior": self.ior, "absorption_per_m": self.absorption_per_m}
            if self.scattering_per_m > 0:
                d.update(scattering_per_m=self.scattering_per_m, anisotropy=self.anisotropy)
            return d
        d: dict[str, Any] = {"reflectance": self.reflectance}
        if self.glossy_reflectance > 0:
            d["glossy"] = {"reflectance": self.glossy_reflectance, "exponent": self.glossy_exponent}
        if self.texture is not None:
            d["texture"] = self.texture.to_dict()
        return d


@dataclass
class SceneObject:
    """One object: a primitive (plane, box, sphere, cylinder) or a mesh file, posed in the world.

    ``params`` holds the type's sizes (plane ``size [w, h]`` in local x-y with normal local z;
    box ``size [sx, sy, sz]``; sphere ``radius``, ``subdivisions``; cylinder ``radius``,
    ``height`` along local z, ``sections``; mesh ``file``, ``scale``; board ``target``, the
    :class:`tofhil.boards.BoardSpec` as a mapping: a plane of the board's printed size whose
    pattern sets the diffuse reflectance). ``pose`` is 4x4 object-to-world.
    """

    name: str
    type: str
    material: str
    pose: np.ndarray
    params: dict[str, Any] = field(default_factory=dict)
    mesh: Any = field(default=None, repr=False, compare=False)  # trimesh.Trimesh for type 'mesh'

    @property
    def board(self) -> Any:
        """The :class:`tofhil.boards.BoardSpec` of a ``board`` object (None otherwise)."""
        if self.type != "board":
            return None
        from tofhil.boards import BoardSpec

        return BoardSpec.from_dict(self.params["target"], source=self.name)

    def to_dict(self) -> dict[str, Any]:
        d = {"name": self.name, "type": self.type, "material": self.material}
        d.update(copy.deepcopy(self.params))
        d["pose"] = {"matrix": self.pose.tolist()}
        return d


@dataclass(frozen=True)
class RenderSettings:
    """The ``render:`` block: Monte Carlo samples per pixel, indirect bounces, the render's
    random seed, sub-pixel sample spreading and the sample sequence."""

    samples_per_pixel: int = 1
    bounces: int = 0
    seed: int = 0
    subpixel: bool = True
    sampler: str = "sobol"

    #: Upper bounds that keep a render finite (a typo of 10**9 samples fails at load).
    MAX_SAMPLES_PER_PIXEL = 1 << 16
    MAX_BOUNCES = 64

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, *, source: Any = "<scene>") -> "RenderSettings":
        v = Schema(source)
        d = v.mapping(d, "render", allowed=("samples_per_pixel", "bounces", "seed", "subpixel", "sampler"))
        kw: dict[str, Any] = {}
        if "samples_per_pixel" in d:
            kw["samples_per_pixel"] = v.integer(d["samples_per_pixel"], "render.samples_per_pixel", lo=1,
                                                hi=cls.MAX_SAMPLES_PER_PIXEL)
        if "bounces" in d:
            kw["bounces"] = v.integer(d["bounces"], "render.bounces", lo=0, hi=cls.MAX_BOUNCES)
        if "seed" in d:
            kw["seed"] = v.integer(d["seed"], "render.seed", lo=0, hi=2 ** 63 - 1)
        if "subpixel" in d:
            kw["subpixel"] = v.boolean(d["subpixel"], "render.subpixel")
        if "sampler" in d:
            kw["sampler"] = v.enum(d["sampler"], "render.sampler", SAMPLERS)
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        return {"samples_per_pixel": self.samples_per_pixel, "bounces": self.bounces, "seed": self.seed,
                "subpixel": self.subpixel, "sampler": self.sampler}


class EffectSet(dict):
    """Effects parsed by :func:`tofhil.sim.effects.parse_effects` (``{name: values}`` in
    forward-model order, defaults filled). The type marks the set as validated, so it is
    not parsed again."""

    @classmethod
    def parse(cls, block: Mapping[str, Any] | None, *, source: Any = "<scene>") -> "EffectSet":
        if isinstance(block, EffectSet):
            return block
        return cls(parse_effects(block or {}, source=source))

    def to_block(self) -> dict[str, dict[str, Any]]:
        """Plain mapping for a YAML/JSON ``effects:`` block."""
        return effects_to_block(self)


@dataclass
class SecondCamera:
    """The ``rgb_camera:`` block: a passive (colour or grey) camera rigidly beside the ToF
    camera. ``pose`` is its camera-to-ToF-camera transform (its position and orientation in
    the ToF camera's frame); ``samples`` x ``samples`` sub-pixel rays per pixel."""

    camera: CameraModel
    pose: np.ndarray
    samples: int = 4

    @property
    def tof_to_camera(self) -> np.ndarray:
        """4x4 ToF frame -> this camera's frame."""
        return np.linalg.inv(self.pose)

    def to_dict(self) -> dict[str, Any]:
        d = self.camera.to_dict()
        d.update({"pose": {"matrix": self.pose.tolist()}, "samples": self.samples})
        return d


@dataclass
class Scene:
    """A validated scene. ``sensor``, ``effects`` and ``render`` are typed (see the module doc)."""

    camera: CameraModel
    camera_pose: np.ndarray
    f_number: float | None
    focus_distance_m: float | None
    emitter: Emitter
    ambient_irradiance_w_m2: float
    objects: list[SceneObject]
    materials: dict[str, Material]
    sensor: SensorConfig = None  # type: ignore[assignment]  # None: resolved from the camera preset
    effects: EffectSet = field(default_factory=EffectSet)
    render: RenderSettings = field(default_factory=RenderSettings)
    params: dict[str, Any] = field(default_factory=dict)
    rgb_camera: SecondCamera | None = None
    #: A pulsed emitter and SPAD histogram sensor (sim/direct_tof.py), or None: correlation ToF.
    direct_tof: Any = None
    name: str = ""
    description: str = ""
    source: str = "<dict>"
    text: str = ""

    def __post_init__(self) -> None:
        # Typed parts pass through; mappings (from dataclasses.replace or direct construction)
        # are validated once here, with errors naming the scene's source.
        if not isinstance(self.sensor, SensorConfig):
            self.sensor = SensorConfig.from_dict(self.sensor or {}, source=self.source, camera=self.camera)
        if not isinstance(self.effects, EffectSet):
            self.effects = EffectSet.parse(self.effects, source=self.source)
        if not isinstance(self.render, RenderSettings):
            self.render = RenderSettings.from_dict(self.render, source=self.source)

    @property
    def radiometric_f_number(self) -> float:
        """The f-number used in the camera equation (``DEFAULT_F_NUMBER`` if none is given)."""
        return DEFAULT_F_NUMBER if self.f_number is None else self.f_number

    @property
    def thin_lens(self) -> bool:
        """True when rays are sampled over the aperture (defocus): f_number and focus given."""
        return self.f_number is not None and self.focus_distance_m is not None

    @property
    def freq_hz(self) -> np.ndarray:
        """Modulation frequencies of the (resolved) sensor."""
        return np.asarray(self.sensor.freq_hz, dtype=np.float64)

    def object_index(self, name: str) -> int:
        for i, o in enumerate(self.objects):
            if o.name == name:
                return i
        raise KeyError(name)

    def emitter_position_world(self) -> np.ndarray:
        return (self.camera_pose @ np.append(self.emitter.offset_m, 1.0))[:3]

    def to_dict(self) -> dict[str, Any]:
        """Plain mapping of the scene (``load_scene`` of its YAML gives an equal scene); the
        sensor block is written in full, resolved against the camera preset."""
        cam = self.camera.to_dict()
        cam.update(copy.deepcopy(self.camera.extra))
        cam["pose"] = {"matrix": self.camera_pose.tolist()}
        if self.f_number is not None and cam.get("lens") is None:  # a lens prescription gives its own
            cam["f_number"] = self.f_number
        if self.focus_distance_m is not None:
            cam["focus_distance_m"] = self.focus_distance_m
        d: dict[str, Any] = {}
        if self.name:
            d["name"] = self.name
        if self.description:
            d["description"] = self.description
        d.update({
            "camera": cam,
            "emitter": self.emitter.to_dict(),
            "ambient_irradiance_w_m2": self.ambient_irradiance_w_m2,
            "materials": {k: m.to_dict() for k, m in self.materials.items()},
            "objects": [o.to_dict() for o in self.objects],
            "sensor": self.sensor.to_dict(),
            "effects": self.effects.to_block(),
            "render": self.render.to_dict(),
        })
        if self.rgb_camera is not None:
            d["rgb_camera"] = self.rgb_camera.to_dict()
        if self.direct_tof is not None:
            d["direct_tof"] = self.direct_tof.to_dict()
        return to_plain(d)
