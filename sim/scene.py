"""Scene files of the simulator twin: YAML -> validated :class:`Scene`.

A scene names objects (primitives or mesh files) with poses and materials, the camera with
its pose and lens, the emitter, ambient light, the sensor block and the effects block. The
schema and the radiometric conventions are documented in ``docs/scene-format.md``.

Every user error raises :class:`tofhil.errors.InputFileError` naming the file, the field
(a dotted path such as ``objects[2].material``) and what was expected.
"""

from __future__ import annotations

import ast
import copy
import math
import operator
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.yamlio import load_yaml

#: f-number used for the camera equation when a scene gives none (pinhole geometry, no
#: defocus). Typical ToF lenses are fast (F/1.0 .. F/1.6).
DEFAULT_F_NUMBER = 1.2

OBJECT_TYPES = ("plane", "box", "sphere", "cylinder", "mesh")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")


# --------------------------------------------------------------------------- dataclasses
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
    """

    name: str
    reflectance: float
    glossy_reflectance: float = 0.0
    glossy_exponent: float = 0.0
    texture: Texture | None = None

    def to_dict(self) -> dict[str, Any]:
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
    ``height`` along local z, ``sections``; mesh ``file``, ``scale``). ``pose`` is 4x4
    object-to-world.
    """

    name: str
    type: str
    material: str
    pose: np.ndarray
    params: dict[str, Any] = field(default_factory=dict)
    mesh: Any = field(default=None, repr=False, compare=False)  # trimesh.Trimesh for type 'mesh'

    def to_dict(self) -> dict[str, Any]:
        d = {"name": self.name, "type": self.type, "material": self.material}
        d.update(copy.deepcopy(self.params))
        d["pose"] = {"matrix": self.pose.tolist()}
        return d


@dataclass
class Scene:
    """A validated scene. ``sensor``, ``effects`` and ``render`` are passed through as mappings."""

    camera: CameraModel
    camera_pose: np.ndarray
    f_number: float | None
    focus_distance_m: float | None
    emitter: Emitter
    ambient_irradiance_w_m2: float
    objects: list[SceneObject]
    materials: dict[str, Material]
    sensor: dict[str, Any] = field(default_factory=dict)
    effects: dict[str, Any] = field(default_factory=dict)
    render: dict[str, Any] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)
    name: str = ""
    description: str = ""
    source: str = "<dict>"
    text: str = ""

    def __getstate__(self) -> dict[str, Any]:
        # Copies and pickles leave out the renderer's cached Embree scene (not copyable).
        state = self.__dict__.copy()
        state.pop("_geometry_cache", None)
        state.pop("_view_cache", None)
        return state

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
        """Modulation frequencies: the sensor block's, else the camera preset's."""
        f = self.sensor.get("freq_hz", self.camera.extra.get("freq_hz"))
        if f is None:
            raise InputFileError("no modulation frequency", file=self.source, field="sensor.freq_hz",
                                 expected="a list of frequencies in Hz")
        return np.atleast_1d(np.asarray(f, dtype=np.float64))

    def object_index(self, name: str) -> int:
        for i, o in enumerate(self.objects):
            if o.name == name:
                return i
        raise KeyError(name)

    def emitter_position_world(self) -> np.ndarray:
        return (self.camera_pose @ np.append(self.emitter.offset_m, 1.0))[:3]

    def to_dict(self) -> dict[str, Any]:
        cam = self.camera.to_dict()
        cam.update(copy.deepcopy(self.camera.extra))
        cam["pose"] = {"matrix": self.camera_pose.tolist()}
        if self.f_number is not None:
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
            "sensor": copy.deepcopy(self.sensor),
            "effects": copy.deepcopy(self.effects),
            "render": copy.deepcopy(self.render),
        })
        return d


# --------------------------------------------------------------------------- public API
def scenes_dir() -> Path:
    """The bundled ``configs/scenes`` directory."""
    return Path(str(resources.files("tofhil.configs"))) / "scenes"


def bundled_scenes() -> list[str]:
    """Names of the bundled scenes (``load_scene(name)`` loads them)."""
    return sorted(p.stem for p in scenes_dir().glob("*.yaml"))


def load_scene(path_or_name: str | Path, overrides: dict | None = None) -> Scene:
    """Load a scene file, or a bundled scene by name (``"wall"``, ``"dark_square"``, ...).

    ``overrides`` is a nested mapping merged into the YAML before parameters are substituted
    and the scene is validated, e.g. ``{"params": {"square_reflectance": 0.05}}``.
    """
    path = Path(path_or_name)
    if not path.suffix and not path.exists():
        path = scenes_dir() / f"{path_or_name}.yaml"
        if not path.is_file():
            raise InputFileError("no such bundled scene", file=path, field="scene",
                                 expected="a scene file path or one of " + ", ".join(bundled_scenes()))
    if not path.is_file():
        raise InputFileError("no such file", file=path, field="scene", expected="a scene YAML file")
    text = path.read_text()
    return scene_from_yaml(text, source=str(path), base_dir=path.parent, overrides=overrides)


def scene_from_yaml(text: str, source: str = "<string>", base_dir: str | Path | None = None,
                    overrides: dict | None = None) -> Scene:
    """Parse YAML text into a Scene (relative mesh/texture paths resolve against ``base_dir``)."""
    data = load_yaml(text, source=source)       # reads 44.0e6 as a number (YAML 1.2 style)
    if not isinstance(data, dict):
        raise InputFileError("the file is not a mapping", file=source,
                             expected="a YAML mapping with camera, emitter, materials, objects")
    if overrides:
        data = _deep_merge(data, overrides, source)
    scene = scene_from_dict(data, source=source, base_dir=base_dir)
    scene.text = text if not overrides else scene_to_yaml(scene)
    return scene


def scene_to_yaml(scene: Scene) -> str:
    """YAML text of the scene with parameters resolved; ``load_scene`` reads it back."""
    header = f"# tofhil scene written from {scene.source}\n"
    return header + yaml.safe_dump(_plain(scene.to_dict()), sort_keys=False, default_flow_style=None)


def _plain(x: Any) -> Any:
    """Numpy scalars/arrays and tuples -> plain Python for YAML."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


def scene_from_dict(d: dict, source: str = "<dict>", base_dir: str | Path | None = None) -> Scene:
    """Validate a scene mapping (as read from YAML) and build the Scene."""
    if not isinstance(d, dict):
        raise InputFileError("scene is not a mapping", file=source, expected="a mapping")
    v = _Validator(source, Path(base_dir) if base_dir is not None else Path.cwd())
    known = {"name", "description", "params", "camera", "emitter", "ambient_irradiance_w_m2",
             "materials", "objects", "sensor", "effects", "render"}
    for key in d:
        if key not in known:
            raise InputFileError(f"unknown key {key!r}", file=source, field=str(key),
                                 expected="one of " + ", ".join(sorted(known)))
    params = v.params(d.get("params", {}))
    d = _substitute(d, params, source, "")
    camera, pose, f_number, focus = v.camera(v.require(d, "camera", "", "a camera mapping"))
    emitter = v.emitter(v.require(d, "emitter", "", "an emitter mapping"))
    materials = v.materials(v.require(d, "materials", "", "a mapping of material names"))
    objects = v.objects(v.require(d, "objects", "", "a list of objects"), materials)
    sensor = v.mapping(d.get("sensor", {}), "sensor")
    effects = v.mapping(d.get("effects", {}) or {}, "effects")
    for name, eff in effects.items():
        if eff is not None and not isinstance(eff, dict):
            raise InputFileError(f"got {eff!r}", file=source, field=f"effects.{name}",
                                 expected="a mapping of parameter values")
    render = v.render(d.get("render", {}) or {})
    return Scene(camera=camera, camera_pose=pose, f_number=f_number, focus_distance_m=focus,
                 emitter=emitter,
                 ambient_irradiance_w_m2=v.number(d.get("ambient_irradiance_w_m2", 0.0),
                                                  "ambient_irradiance_w_m2", lo=0.0),
                 objects=objects, materials=materials, sensor=sensor, effects=effects,
                 render=render, params=params, name=str(d.get("name", "")),
                 description=str(d.get("description", "")), source=source)


# --------------------------------------------------------------------------- helpers
def _deep_merge(base: dict, over: dict, source: str, prefix: str = "") -> dict:
    """Merge ``over`` into a copy of ``base`` (mappings recursively, everything else replaced)."""
    if not isinstance(over, dict):
        raise InputFileError(f"override got {over!r}", file=source, field=prefix or "overrides",
                             expected="a mapping")
    out = copy.deepcopy(base)
    for k, val in over.items():
        if isinstance(val, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], val, source, f"{prefix}{k}.")
        else:
            out[k] = copy.deepcopy(val)
    return out


_BINOPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
           ast.Div: operator.truediv, ast.Pow: operator.pow}


def _eval_expr(expr: str, params: dict[str, Any], source: str, fieldname: str) -> Any:
    """Evaluate ``name`` or a small arithmetic expression of parameters (no calls, no attributes)."""
    def ev(node: ast.AST) -> Any:
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
            return node.value
        if isinstance(node, ast.Name):
            if node.id not in params:
                raise InputFileError(f"unknown parameter {node.id!r}", file=source, field=fieldname,
                                     expected="one of the names in params: " + ", ".join(sorted(params)))
            return params[node.id]
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return _BINOPS[type(node.op)](ev(node.left), ev(node.right))
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            val = ev(node.operand)
            return -val if isinstance(node.op, ast.USub) else val
        raise InputFileError(f"cannot evaluate {expr!r}", file=source, field=fieldname,
                             expected="a parameter name or arithmetic (+ - * / **) of parameters")
    try:
        tree = ast.parse(expr, mode="eval")
    except SyntaxError:
        raise InputFileError(f"cannot parse {expr!r}", file=source, field=fieldname,
                             expected="${name} or ${arithmetic of params}") from None
    return ev(tree)


def _substitute(node: Any, params: dict[str, Any], source: str, path: str) -> Any:
    """Replace every string ``"${expr}"`` by the value of ``expr`` over ``params``."""
    if isinstance(node, dict):
        return {k: (node[k] if k == "params" and not path else
                    _substitute(node[k], params, source, f"{path}{k}" if not path else f"{path}.{k}"))
                for k in node}
    if isinstance(node, list):
        return [_substitute(x, params, source, f"{path}[{i}]") for i, x in enumerate(node)]
    if isinstance(node, str):
        s = node.strip()
        if s.startswith("${") and s.endswith("}"):
            return _eval_expr(s[2:-1], params, source, path)
    return node


def _rotation_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    """R = Rz @ Ry @ Rx (rotate about x first), angles in degrees."""
    ax, ay, az = np.radians([rx, ry, rz])
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_y @ r_x


def look_at_rotation(position: np.ndarray, target: np.ndarray,
                     up: np.ndarray = np.array([0.0, -1.0, 0.0])) -> np.ndarray:
    """Rotation whose local z points at ``target`` and local y is "down" (opposite ``up``)."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("up is parallel to the viewing direction")
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


class _Validator:
    """Field-by-field validation with errors naming the file, the field and the expectation."""

    def __init__(self, source: str, base_dir: Path) -> None:
        self.source = source
        self.base_dir = base_dir

    def err(self, msg: str, fieldname: str, expected: str | None = None) -> InputFileError:
        return InputFileError(msg, file=self.source, field=fieldname, expected=expected)

    def require(self, d: dict, key: str, prefix: str, expected: str) -> Any:
        if key not in d:
            raise self.err("missing", f"{prefix}{key}", expected)
        return d[key]

    def mapping(self, x: Any, fieldname: str) -> dict:
        if x is None:
            return {}
        if not isinstance(x, dict):
            raise self.err(f"got {x!r}", fieldname, "a mapping")
        return copy.deepcopy(x)

    def number(self, x: Any, fieldname: str, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False) -> float:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise self.err(f"got {x!r}", fieldname, "a number" + self._range(lo, hi, lo_open))
        x = float(x)
        if not math.isfinite(x) or (lo is not None and (x < lo or (lo_open and x == lo))) or \
                (hi is not None and x > hi):
            raise self.err(f"got {x!r}", fieldname, "a number" + self._range(lo, hi, lo_open))
        return x

    @staticmethod
    def _range(lo: float | None, hi: float | None, lo_open: bool) -> str:
        if lo is not None and hi is not None:
            return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
        if lo is not None:
            return f" {'>' if lo_open else '>='} {lo:g}"
        if hi is not None:
            return f" <= {hi:g}"
        return ""

    def integer(self, x: Any, fieldname: str, lo: int | None = None) -> int:
        if isinstance(x, bool) or not isinstance(x, int) or (lo is not None and x < lo):
            raise self.err(f"got {x!r}", fieldname, "an integer" + (f" >= {lo}" if lo is not None else ""))
        return int(x)

    def vector(self, x: Any, fieldname: str, n: int = 3) -> np.ndarray:
        if not isinstance(x, (list, tuple)) or len(x) != n or \
                any(isinstance(e, bool) or not isinstance(e, (int, float)) for e in x):
            raise self.err(f"got {x!r}", fieldname, f"a list of {n} numbers")
        return np.asarray(x, dtype=np.float64)

    def params(self, p: Any) -> dict[str, Any]:
        p = self.mapping(p, "params")
        for k, val in p.items():
            if isinstance(val, bool) or not isinstance(val, (int, float, str)):
                raise self.err(f"got {val!r}", f"params.{k}", "a number or a string")
        return p

    def pose(self, p: Any, fieldname: str) -> np.ndarray:
        if p is None:
            return np.eye(4)
        if not isinstance(p, dict):
            raise self.err(f"got {p!r}", fieldname,
                           "a mapping with position and rotation_deg or look_at, or matrix")
        allowed = {"position", "rotation_deg", "look_at", "up", "matrix"}
        for k in p:
            if k not in allowed:
                raise self.err(f"unknown key {k!r}", f"{fieldname}.{k}", "one of " + ", ".join(sorted(allowed)))
        if "matrix" in p:
            m = np.asarray(p["matrix"], dtype=object)
            try:
                m = np.asarray(p["matrix"], dtype=np.float64)
            except (TypeError, ValueError):
                m = np.zeros(0)
            if m.shape != (4, 4) or not np.allclose(m[3], [0, 0, 0, 1]) or \
                    not np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-6):
                raise self.err("not a rigid 4x4 transform", f"{fieldname}.matrix",
                               "4 rows of 4 numbers, orthonormal rotation, last row [0, 0, 0, 1]")
            return m
        pose = np.eye(4)
        pos = self.vector(p.get("position", [0, 0, 0]), f"{fieldname}.position")
        pose[:3, 3] = pos
        if "look_at" in p and "rotation_deg" in p:
            raise self.err("both look_at and rotation_deg given", fieldname, "one of them")
        if "look_at" in p:
            target = self.vector(p["look_at"], f"{fieldname}.look_at")
            up = self.vector(p.get("up", [0, -1, 0]), f"{fieldname}.up")
            try:
                pose[:3, :3] = look_at_rotation(pos, target, up)
            except (ValueError, FloatingPointError):
                raise self.err("look_at equals position or is parallel to up", f"{fieldname}.look_at",
                               "a target point away from position, not along up") from None
        elif "rotation_deg" in p:
            pose[:3, :3] = _rotation_xyz(*self.vector(p["rotation_deg"], f"{fieldname}.rotation_deg"))
        return pose

    def camera(self, c: Any) -> tuple[CameraModel, np.ndarray, float | None, float | None]:
        c = self.mapping(c, "camera")
        pose = self.pose(c.pop("pose", None), "camera.pose")
        f_number = c.pop("f_number", None)
        focus = c.pop("focus_distance_m", None)
        if f_number is not None:
            f_number = self.number(f_number, "camera.f_number", lo=0.0, lo_open=True)
        if focus is not None:
            focus = self.number(focus, "camera.focus_distance_m", lo=0.0, lo_open=True)
        if not c:
            c = {"preset": "holmlund_thesis"}
        camera = CameraModel.from_dict(c, source=self.source, prefix="camera.")
        return camera, pose, f_number, focus

    def emitter(self, e: Any) -> Emitter:
        e = self.mapping(e, "emitter")
        allowed = {"offset_m", "power_w", "profile", "waveform", "axis"}
        for k in e:
            if k not in allowed:
                raise self.err(f"unknown key {k!r}", f"emitter.{k}", "one of " + ", ".join(sorted(allowed)))
        power = self.number(self.require(e, "power_w", "emitter.", "optical power in W (a number > 0)"),
                            "emitter.power_w", lo=0.0, lo_open=True)
        offset = self.vector(e.get("offset_m", [0, 0, 0]), "emitter.offset_m")
        axis = self.vector(e.get("axis", [0, 0, 1]), "emitter.axis")
        if np.linalg.norm(axis) == 0:
            raise self.err("zero vector", "emitter.axis", "a non-zero direction in the camera frame")
        profile = self.profile(e.get("profile", {"type": "cos_n", "n": 1.0}))
        harmonics = self.waveform(e.get("waveform", {"harmonics": [[1, 1.0, 0.0]]}))
        return Emitter(power_w=power, offset_m=offset, profile=profile, harmonics=harmonics,
                       axis=axis / np.linalg.norm(axis))

    def profile(self, p: Any) -> BeamProfile:
        p = self.mapping(p, "emitter.profile")
        kind = p.get("type", "cos_n")
        if kind == "cos_n":
            return BeamProfile("cos_n", n=self.number(p.get("n", 1.0), "emitter.profile.n", lo=0.0))
        if kind == "table":
            th = p.get("theta_deg")
            val = p.get("relative_intensity")
            exp = "equal-length lists: theta_deg increasing in [0, 180], relative_intensity >= 0"
            if not isinstance(th, list) or not isinstance(val, list) or len(th) != len(val) or len(th) < 2:
                raise self.err("bad table", "emitter.profile.theta_deg", exp)
            th_a = np.array([self.number(x, f"emitter.profile.theta_deg[{i}]", 0, 180) for i, x in enumerate(th)])
            va_a = np.array([self.number(x, f"emitter.profile.relative_intensity[{i}]", lo=0.0)
                             for i, x in enumerate(val)])
            if np.any(np.diff(th_a) <= 0) or va_a.max() <= 0:
                raise self.err("not increasing or all zero", "emitter.profile.theta_deg", exp)
            return BeamProfile("table", theta_deg=tuple(float(x) for x in th_a),
                               values=tuple(float(x) for x in va_a))
        raise self.err(f"got {kind!r}", "emitter.profile.type", "'cos_n' or 'table'")

    def waveform(self, w: Any) -> tuple[tuple[int, float, float], ...]:
        w = self.mapping(w, "emitter.waveform")
        hs = w.get("harmonics")
        exp = "a list of [order h >= 1, amplitude >= 0, phase_rad] or {order, amplitude, phase_rad}"
        if not isinstance(hs, list) or not hs:
            raise self.err(f"got {hs!r}", "emitter.waveform.harmonics", exp)
        out = []
        for i, h in enumerate(hs):
            f = f"emitter.waveform.harmonics[{i}]"
            if isinstance(h, dict):
                h = [h.get("order"), h.get("amplitude"), h.get("phase_rad", 0.0)]
            if not isinstance(h, (list, tuple)) or len(h) not in (2, 3):
                raise self.err(f"got {h!r}", f, exp)
            order = self.integer(h[0], f + ".order", lo=1)
            amp = self.number(h[1], f + ".amplitude", lo=0.0)
            ph = self.number(h[2] if len(h) == 3 else 0.0, f + ".phase_rad")
            out.append((order, amp, ph))
        return tuple(out)

    def materials(self, m: Any) -> dict[str, Material]:
        if not isinstance(m, dict) or not m:
            raise self.err(f"got {m!r}", "materials", "a non-empty mapping name -> {reflectance, ...}")
        out = {}
        for name, spec in m.items():
            f = f"materials.{name}"
            if isinstance(spec, (int, float)) and not isinstance(spec, bool):
                spec = {"reflectance": spec}
            spec = self.mapping(spec, f)
            allowed = {"reflectance", "glossy", "texture"}
            for k in spec:
                if k not in allowed:
                    raise self.err(f"unknown key {k!r}", f"{f}.{k}", "one of " + ", ".join(sorted(allowed)))
            rho = self.number(self.require(spec, "reflectance", f + ".", "a number in [0, 1]"),
                              f + ".reflectance", 0.0, 1.0)
            gl = self.mapping(spec.get("glossy"), f + ".glossy")
            g_rho = self.number(gl.get("reflectance", 0.0), f + ".glossy.reflectance", 0.0, 1.0)
            g_n = self.number(gl.get("exponent", 20.0 if gl else 0.0), f + ".glossy.exponent", lo=0.0)
            if rho + g_rho > 1.0 + 1e-12:
                raise self.err(f"reflectance + glossy.reflectance = {rho + g_rho:g}", f,
                               "a total reflectance <= 1 (energy conservation)")
            tex = self.texture(spec.get("texture"), f + ".texture")
            out[str(name)] = Material(str(name), rho, g_rho, g_n, tex)
        return out

    def texture(self, t: Any, f: str) -> Texture | None:
        if t is None:
            return None
        t = self.mapping(t, f)
        kind = t.get("type")
        if kind == "checker":
            vals = t.get("reflectance", [0.8, 0.1])
            if not isinstance(vals, list) or len(vals) != 2:
                raise self.err(f"got {vals!r}", f + ".reflectance", "two reflectances [a, b] in [0, 1]")
            a, b = (self.number(x, f"{f}.reflectance[{i}]", 0.0, 1.0) for i, x in enumerate(vals))
            size = self.number(t.get("size_m", 0.1), f + ".size_m", lo=0.0, lo_open=True)
            return Texture("checker", size_m=size, values=(a, b))
        if kind == "image":
            file = self.require(t, "file", f + ".", "an image file (PNG, JPEG, TIFF) or .npy array")
            path = self._path(file, f + ".file")
            return Texture("image", file=str(path), image=self._read_image(path, f + ".file"))
        raise self.err(f"got {kind!r}", f + ".type", "'checker' or 'image'")

    def _path(self, file: Any, f: str) -> Path:
        if not isinstance(file, str) or not file:
            raise self.err(f"got {file!r}", f, "a file path")
        path = Path(file)
        if not path.is_absolute():
            path = self.base_dir / path
        if not path.is_file():
            raise self.err(f"no such file {str(path)!r}", f, "an existing file (relative to the scene file)")
        return path

    def _read_image(self, path: Path, f: str) -> np.ndarray:
        if path.suffix.lower() == ".npy":
            img = np.load(path).astype(np.float64)
        else:
            import cv2

            raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
            if raw is None:
                raise self.err("cannot read the image", f, "a PNG, JPEG or TIFF image, or a .npy array")
            scale = 65535.0 if raw.dtype == np.uint16 else 255.0 if raw.dtype == np.uint8 else 1.0
            img = raw.astype(np.float64) / scale
        if img.ndim == 3:
            img = img.mean(axis=2)
        if img.ndim != 2 or img.size == 0 or np.nanmin(img) < 0 or np.nanmax(img) > 1:
            raise self.err("image values outside [0, 1] or not 2-D", f, "a grey image with values in [0, 1]")
        return img

    def render(self, r: Any) -> dict[str, Any]:
        r = self.mapping(r, "render")
        allowed = {"samples_per_pixel": 1, "bounces": 0, "seed": 0, "subpixel": True, "sampler": "sobol"}
        for k in r:
            if k not in allowed:
                raise self.err(f"unknown key {k!r}", f"render.{k}", "one of " + ", ".join(sorted(allowed)))
        out = dict(r)
        if "samples_per_pixel" in r:
            out["samples_per_pixel"] = self.integer(r["samples_per_pixel"], "render.samples_per_pixel", lo=1)
        if "bounces" in r:
            out["bounces"] = self.integer(r["bounces"], "render.bounces", lo=0)
        if "seed" in r:
            out["seed"] = self.integer(r["seed"], "render.seed", lo=0)
        if "subpixel" in r and not isinstance(r["subpixel"], bool):
            raise self.err(f"got {r['subpixel']!r}", "render.subpixel", "true or false")
        if "sampler" in r and r["sampler"] not in ("sobol", "random"):
            raise self.err(f"got {r['sampler']!r}", "render.sampler", "'sobol' or 'random'")
        return out

    def objects(self, objs: Any, materials: dict[str, Material]) -> list[SceneObject]:
        if not isinstance(objs, list) or not objs:
            raise self.err(f"got {objs!r}", "objects", "a non-empty list of objects")
        out: list[SceneObject] = []
        names: set[str] = set()
        for i, o in enumerate(objs):
            f = f"objects[{i}]"
            o = self.mapping(o, f)
            kind = self.require(o, "type", f + ".", "one of " + ", ".join(OBJECT_TYPES))
            if kind not in OBJECT_TYPES:
                raise self.err(f"got {kind!r}", f + ".type", "one of " + ", ".join(OBJECT_TYPES))
            name = str(o.get("name", f"{kind}{i}"))
            if name in names:
                raise self.err(f"duplicate name {name!r}", f + ".name", "unique object names")
            names.add(name)
            mat = self.require(o, "material", f + ".", "a material name from materials")
            if isinstance(mat, dict):  # inline material
                mname = f"{name}__material"
                materials[mname] = self.materials({mname: mat})[mname]
                mat = mname
            if mat not in materials:
                raise self.err(f"unknown material {mat!r}", f + ".material",
                               "one of " + ", ".join(sorted(materials)))
            pose = self.pose(o.get("pose"), f + ".pose")
            params, mesh = self._shape(kind, o, f)
            out.append(SceneObject(name=name, type=kind, material=str(mat), pose=pose,
                                   params=params, mesh=mesh))
        return out

    def _shape(self, kind: str, o: dict, f: str) -> tuple[dict[str, Any], Any]:
        shape_keys = {"plane": {"size"}, "box": {"size"}, "sphere": {"radius", "subdivisions"},
                      "cylinder": {"radius", "height", "sections"}, "mesh": {"file", "scale"}}[kind]
        for k in o:
            if k not in shape_keys | {"name", "type", "material", "pose"}:
                raise self.err(f"unknown key {k!r} for a {kind}", f"{f}.{k}",
                               "one of " + ", ".join(sorted(shape_keys | {"name", "type", "material", "pose"})))
        if kind == "plane":
            size = self.vector(self.require(o, "size", f + ".", "[width, height] in m"), f + ".size", 2)
            if np.any(size <= 0):
                raise self.err(f"got {size.tolist()}", f + ".size", "two sizes > 0 in m")
            return {"size": size.tolist()}, None
        if kind == "box":
            size = self.vector(self.require(o, "size", f + ".", "[sx, sy, sz] in m"), f + ".size", 3)
            if np.any(size <= 0):
                raise self.err(f"got {size.tolist()}", f + ".size", "three sizes > 0 in m")
            return {"size": size.tolist()}, None
        if kind == "sphere":
            r = self.number(self.require(o, "radius", f + ".", "a radius in m"), f + ".radius", lo=0, lo_open=True)
            sub = self.integer(o.get("subdivisions", 4), f + ".subdivisions", lo=1)
            return {"radius": r, "subdivisions": sub}, None
        if kind == "cylinder":
            r = self.number(self.require(o, "radius", f + ".", "a radius in m"), f + ".radius", lo=0, lo_open=True)
            h = self.number(self.require(o, "height", f + ".", "a height in m"), f + ".height", lo=0, lo_open=True)
            sec = self.integer(o.get("sections", 64), f + ".sections", lo=3)
            return {"radius": r, "height": h, "sections": sec}, None
        path = self._path(self.require(o, "file", f + ".", "a mesh file (OBJ, PLY, STL, GLB)"), f + ".file")
        if path.suffix.lower() not in MESH_SUFFIXES:
            raise self.err(f"unsupported mesh format {path.suffix!r}", f + ".file",
                           "one of " + ", ".join(MESH_SUFFIXES))
        scale = o.get("scale", 1.0)
        if isinstance(scale, list):
            scale = self.vector(scale, f + ".scale").tolist()
        else:
            scale = self.number(scale, f + ".scale", lo=0, lo_open=True)
        import trimesh

        try:
            mesh = trimesh.load(str(path), force="mesh")
        except Exception as exc:  # trimesh raises many types for corrupt files
            raise self.err(f"cannot read mesh ({exc})", f + ".file", "a mesh file trimesh reads") from None
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise self.err("no triangles in the file", f + ".file", "a mesh with faces")
        return {"file": str(path), "scale": scale}, mesh
