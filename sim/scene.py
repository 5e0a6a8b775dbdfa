"""Scene files of the simulator twin: YAML -> a typed, validated :class:`Scene`.

A scene names objects (primitives or mesh files) with poses and materials, the camera with
its pose and lens, the emitter, ambient light, the sensor block, the effects block and the
render settings. :func:`load_scene` reads the file, merges overrides, substitutes ``${...}``
parameters (:mod:`tofhil.sim.scene_expressions`) and validates every part once; the types
live in :mod:`tofhil.sim.scene_model`. The schema and the radiometric conventions are
documented in ``docs/scene-format.md``.

Every user error raises :class:`tofhil.errors.InputFileError` naming the file, the field
(a dotted path such as ``objects[2].material``) and what was expected.
"""

from __future__ import annotations

import copy
import math
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tofhil.camera import CameraModel, camera_presets_dir, check_distortion, list_camera_presets
from tofhil.errors import InputFileError
from tofhil.schema import Schema, to_plain
from tofhil.sim.scene_expressions import substitute
from tofhil.sim.scene_model import (DEFAULT_F_NUMBER, MESH_SUFFIXES, OBJECT_TYPES, BeamProfile, EffectSet,
                                    Emitter, Material, RenderSettings, Scene, SceneObject, SecondCamera, Texture)
from tofhil.sim.sensor import SENSOR_KEYS, SensorConfig
from tofhil.yamlio import load_yaml

__all__ = ["DEFAULT_F_NUMBER", "MESH_SUFFIXES", "OBJECT_TYPES", "BeamProfile", "EffectSet", "Emitter", "Material",
           "RenderSettings", "Scene", "SceneObject", "SecondCamera", "Texture", "bundled_scenes", "load_scene", "look_at_rotation",
           "scene_from_dict", "scene_from_yaml", "scene_to_yaml", "scenes_dir"]

#: Largest camera side accepted in a scene (pixels); memory is checked before a render.
MAX_CAMERA_SIDE_PX = 100_000
#: Largest scene file read (bytes): a scene is a page of YAML, not a data file.
MAX_SCENE_BYTES = 16 << 20
#: Most objects a scene may list. A bench holds tens; each object costs about a millisecond to
#: read, validate and render (10^4 small planes: 8.6 s and 0.3 GB for one frame), so beyond this a mesh file
#: is the way to bring many surfaces (checked before parameters are substituted).
MAX_SCENE_OBJECTS = 10_000
#: Most pixels of an image texture, read from the file's header before it is decoded. A
#: 4096 x 4096 reflectance map is finer than any bench target needs and takes 134 MB as
#: float64; a 1 MB PNG of 30000 x 30000 would otherwise decode to 0.9 GB and two 7 GB copies.
MAX_TEXTURE_PIXELS = 4096 * 4096
#: Most triangles of a mesh file, estimated from its header (PLY, binary STL) or its face
#: lines (OBJ, OFF) before it is loaded and checked again after. Loading and building the
#: renderer's structures take about 510 bytes a triangle (10^7 triangles: 38 s, 5.1 GB), so
#: two million keep a mesh near 1 GB.
MAX_MESH_TRIANGLES = 2_000_000

_TOP_KEYS = ("name", "description", "params", "camera", "emitter", "ambient_irradiance_w_m2",
             "materials", "objects", "sensor", "effects", "render", "rgb_camera", "direct_tof")
_CAMERA_KEYS = {"preset", "width", "height", "fx", "fy", "cx", "cy", "model", "dist", "name", "pixel_pitch_m",
                "hfov_deg", "vfov_deg", "pose", "f_number", "focus_distance_m", "lens"} | set(SENSOR_KEYS)


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
    if path.is_dir():
        raise InputFileError("is a directory", file=path, field="scene", expected="a scene YAML file")
    if not path.is_file():
        raise InputFileError("no such file", file=path, field="scene", expected="a scene YAML file")
    if path.stat().st_size > MAX_SCENE_BYTES:
        raise InputFileError(f"is {path.stat().st_size} bytes", file=path, field="scene",
                             expected=f"a scene YAML file of at most {MAX_SCENE_BYTES >> 20} MiB")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"is not UTF-8 text (byte {exc.start})", file=path, field="scene",
                             expected="a UTF-8 YAML file") from None
    except OSError as exc:
        raise InputFileError(f"cannot be read ({exc.strerror})", file=path, field="scene",
                             expected="a readable scene YAML file") from None
    return scene_from_yaml(text, source=str(path), base_dir=path.resolve().parent, overrides=overrides)


def scene_from_yaml(text: str, source: str = "<string>", base_dir: str | Path | None = None,
                    overrides: dict | None = None) -> Scene:
    """Parse YAML text into a Scene (relative mesh/texture paths resolve against ``base_dir``)."""
    try:
        data = load_yaml(text, source=source)       # reads 44.0e6 as a number (YAML 1.2 style)
    except RecursionError:
        raise InputFileError("is nested too deeply", file=source, expected="a scene YAML mapping") from None
    if not isinstance(data, dict):
        raise InputFileError("the file is not a mapping", file=source,
                             expected="a YAML mapping with camera, emitter, materials, objects")
    if overrides:
        _check_declared_params(data, overrides, source)
        data = _deep_merge(data, overrides, source)
    scene = scene_from_dict(data, source=source, base_dir=base_dir)
    scene.text = text if not overrides else scene_to_yaml(scene)
    return scene


def _check_declared_params(data: dict, overrides: dict, source: str) -> None:
    """A parameter set from outside (``--param NAME=V``, a sweep axis) must be one the scene
    declares: an unknown name would otherwise change nothing, silently."""
    given = overrides.get("params") or {}
    declared = data.get("params") if isinstance(data.get("params"), dict) else {}
    unknown = [name for name in given if name not in declared]
    if unknown:
        raise InputFileError(f"declares no parameter {unknown[0]!r}", file=source, field=f"params.{unknown[0]}",
                             expected=("one of " + ", ".join(sorted(map(str, declared)))) if declared
                             else "no --param: the scene has no params block")


def scene_to_yaml(scene: Scene) -> str:
    """YAML text of the scene with parameters resolved and the sensor block written in full;
    ``load_scene`` reads it back to an equal scene."""
    header = f"# tofhil scene written from {scene.source}\n"
    return header + yaml.safe_dump(to_plain(scene.to_dict()), sort_keys=False, default_flow_style=None)


def scene_from_dict(d: dict, source: str = "<dict>", base_dir: str | Path | None = None) -> Scene:
    """Validate a scene mapping (as read from YAML) and build the Scene."""
    p = _Parser(source, Path(base_dir) if base_dir is not None else Path.cwd())
    d = p.mapping(d, "", allowed=_TOP_KEYS, none_ok=False, expected="a scene mapping")
    params = p.params(d.get("params", {}))
    if isinstance(d.get("objects"), list) and len(d["objects"]) > MAX_SCENE_OBJECTS:
        raise p.error(f"lists {len(d['objects']):,} objects", "objects", f"at most {MAX_SCENE_OBJECTS:,} objects "
                      "(many surfaces belong in a mesh file)")
    d = substitute(d, params, source)
    camera, pose, f_number, focus = p.camera(p.require(d, "camera", "", "a camera mapping"))
    emitter = p.emitter(p.require(d, "emitter", "", "an emitter mapping"))
    materials = p.materials(p.require(d, "materials", "", "a mapping of material names"))
    objects = p.objects(p.require(d, "objects", "", "a list of objects"), materials)
    sensor = SensorConfig.from_dict(p.mapping(d.get("sensor"), "sensor"), source=source, camera=camera)
    effects = p.mapping(d.get("effects"), "effects")
    for name, eff in effects.items():
        if eff is not None and not isinstance(eff, dict):
            raise p.bad(eff, f"effects.{name}", "a mapping of parameter values")
    return Scene(camera=camera, camera_pose=pose, f_number=f_number, focus_distance_m=focus,
                 emitter=emitter,
                 ambient_irradiance_w_m2=p.number(d.get("ambient_irradiance_w_m2", 0.0),
                                                  "ambient_irradiance_w_m2", lo=0.0, hi=1e6),
                 objects=objects, materials=materials, sensor=sensor,
                 effects=EffectSet.parse(effects, source=source),
                 render=RenderSettings.from_dict(d.get("render"), source=source),
                 params=params, rgb_camera=p.second_camera(d.get("rgb_camera")),
                 direct_tof=_direct_tof(d, source),
                 name=p.string(d.get("name", ""), "name"),
                 description=p.string(d.get("description", ""), "description"), source=source)


# --------------------------------------------------------------------------- helpers
def _direct_tof(d: dict, source: str) -> Any:
    """The ``direct_tof:`` block (a pulsed emitter and a SPAD histogram sensor), or None."""
    if d.get("direct_tof") is None:
        return None
    from tofhil.sim.direct_tof import DirectToFConfig

    return DirectToFConfig.from_dict(d["direct_tof"], source=source)


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


#: Largest coordinate accepted in a pose or size (m): beyond it float32 ray tracing fails.
_MAX_COORD_M = 1e6


#: Material keys of glass and scattering media (tofhil.sim.dielectric).
_MEDIUM_KEYS = ("ior", "absorption_per_m", "scattering_per_m", "anisotropy")


class _Parser(Schema):
    """The scene's sections -> typed parts (numbers, vectors and mappings via the schema)."""

    def __init__(self, source: str, base_dir: Path) -> None:
        super().__init__(source)
        self.source = source
        self.base_dir = base_dir

    def params(self, p: Any) -> dict[str, Any]:
        p = self.mapping(p, "params")
        for k, val in p.items():
            if isinstance(val, str):
                continue
            self.number(val, f"params.{k}", expected="a finite number or a string")
        return p

    def position(self, x: Any, field: str) -> np.ndarray:
        return self.vector(x, field, 3, lo=-_MAX_COORD_M, hi=_MAX_COORD_M)

    def pose(self, p: Any, field: str) -> np.ndarray:
        if p is None:
            return np.eye(4)
        p = self.mapping(p, field, allowed=("position", "rotation_deg", "look_at", "up", "matrix"),
                         expected="a mapping with position and rotation_deg or look_at, or matrix")
        if "matrix" in p:
            rows = p["matrix"]
            exp = "4 rows of 4 finite numbers, orthonormal rotation, last row [0, 0, 0, 1]"
            if not isinstance(rows, list) or len(rows) != 4:
                raise self.bad(rows, f"{field}.matrix", exp)
            m = np.array([self.numbers(r, f"{field}.matrix[{i}]", n=4, expected=exp) for i, r in enumerate(rows)])
            if not np.allclose(m[3], [0, 0, 0, 1]) or not np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-6) \
                    or np.any(np.abs(m[:3, 3]) > _MAX_COORD_M):
                raise self.error("not a rigid 4x4 transform", f"{field}.matrix", exp)
            return m
        pose = np.eye(4)
        pos = self.position(p.get("position", [0, 0, 0]), f"{field}.position")
        pose[:3, 3] = pos
        if "look_at" in p and "rotation_deg" in p:
            raise self.error("both look_at and rotation_deg given", field, "one of them")
        if "look_at" in p:
            target = self.position(p["look_at"], f"{field}.look_at")
            up = self.vector(p.get("up", [0, -1, 0]), f"{field}.up", 3, lo=-1e6, hi=1e6)
            try:
                with np.errstate(all="ignore"):
                    rot = look_at_rotation(pos, target, up) if np.linalg.norm(target - pos) > 0 else None
            except ValueError:  # up along the viewing direction (or zero): no "down" to orient by
                rot = None
            if rot is None or not np.all(np.isfinite(rot)):
                raise self.error("look_at equals position or is parallel to up", f"{field}.look_at",
                                 "a target point away from position, not along up")
            pose[:3, :3] = rot
        elif "rotation_deg" in p:
            pose[:3, :3] = _rotation_xyz(*self.vector(p["rotation_deg"], f"{field}.rotation_deg", 3,
                                                      lo=-1e6, hi=1e6))
        elif "up" in p:
            raise self.error("up without look_at", f"{field}.up", "up only together with look_at")
        return pose

    def camera(self, c: Any) -> tuple[CameraModel, np.ndarray, float | None, float | None]:
        c = self.mapping(c, "camera", allowed=_CAMERA_KEYS)
        pose = self.pose(c.pop("pose", None), "camera.pose")
        f_number = c.pop("f_number", None)
        focus = c.pop("focus_distance_m", None)
        lens = c.pop("lens", None)
        if f_number is not None and lens is not None:
            raise self.error("f_number and lens both given", "camera.f_number",
                             "no f_number with a lens prescription (the lens gives it: EFL / entrance pupil)")
        if f_number is not None:
            f_number = self.number(f_number, "camera.f_number", lo=0.0, lo_open=True)
        if focus is not None:
            focus = self.number(focus, "camera.focus_distance_m", lo=0.0, lo_open=True, hi=_MAX_COORD_M)
        # Numbers are checked here (finite, in range) before the camera model reads them.
        for key in ("width", "height"):
            if key in c:
                self.integer(c[key], f"camera.{key}", lo=1, hi=MAX_CAMERA_SIDE_PX)
        for key in ("fx", "fy", "pixel_pitch_m"):
            if c.get(key) is not None:
                self.number(c[key], f"camera.{key}", lo=0.0, lo_open=True, hi=1e9)
        for key in ("cx", "cy"):
            if key in c:
                self.number(c[key], f"camera.{key}", lo=-1e9, hi=1e9)
        for key in ("hfov_deg", "vfov_deg"):
            if c.get(key) is not None:
                self.number(c[key], f"camera.{key}", lo=0.0, hi=180.0, lo_open=True, hi_open=True)
        check_distortion(self, c, "camera.")      # model known, dist of its length
        if "preset" in c:
            name = self.string(c["preset"], "camera.preset", nonempty=True, expected="a camera preset name or file")
            preset = Path(name) if Path(name).suffix else camera_presets_dir() / f"{name}.yaml"
            if not preset.is_file():
                raise self.error(f"no such camera preset {name!r}", "camera.preset",
                                 "one of " + ", ".join(list_camera_presets()) + " or a preset YAML file")
        if not c:
            c = {"preset": "holmlund_thesis"}
        camera = CameraModel.from_dict(c, source=self.source, prefix="camera.")
        if lens is not None:
            # A real lens (sim/optics.py): its chief rays, EFL and f-number replace the pinhole's.
            from tofhil.sim.optics import lens_camera, prescription_from_dict

            wl = camera.extra.get("wavelength_m")
            pres = prescription_from_dict(lens, source=self.source, wavelength_m=None if wl is None else float(wl))
            camera = lens_camera(camera, pres, source=self.source)
            f_number = camera.model.f_number
        return camera, pose, f_number, focus

    def second_camera(self, c: Any) -> SecondCamera | None:
        if c is None:
            return None
        c = dict(self.mapping(c, "rgb_camera", allowed={"preset", "width", "height", "fx", "fy", "cx", "cy", "model", "dist",
                                                          "name", "pixel_pitch_m", "hfov_deg", "vfov_deg", "pose",
                                                          "samples"}))
        pose = self.pose(c.pop("pose", None), "rgb_camera.pose")
        samples = self.integer(c.pop("samples", 4), "rgb_camera.samples", lo=1, hi=64)
        for key in ("width", "height"):
            if key in c:
                self.integer(c[key], f"rgb_camera.{key}", lo=1, hi=MAX_CAMERA_SIDE_PX)
        for key in ("fx", "fy", "cx", "cy"):
            if key in c:
                self.number(c[key], f"rgb_camera.{key}", lo=-1e9, hi=1e9)
        check_distortion(self, c, "rgb_camera.")
        camera = CameraModel.from_dict(c, source=self.source, prefix="rgb_camera.")
        return SecondCamera(camera=camera, pose=pose, samples=samples)

    def emitter(self, e: Any) -> Emitter:
        e = self.mapping(e, "emitter", allowed=("offset_m", "power_w", "profile", "waveform", "axis"))
        # 0 W is a dark frame (the emitter off: offset, ambient and dark current only), as
        # calibrate-taps takes them
        power = self.number(self.require(e, "power_w", "emitter", "optical power in W (a number >= 0)"),
                            "emitter.power_w", lo=0.0, hi=1e6)
        offset = self.position(e.get("offset_m", [0, 0, 0]), "emitter.offset_m")
        axis = self.vector(e.get("axis", [0, 0, 1]), "emitter.axis", 3, lo=-1e6, hi=1e6)
        if np.linalg.norm(axis) == 0:
            raise self.error("zero vector", "emitter.axis", "a non-zero direction in the camera frame")
        profile = self.profile(e.get("profile", {"type": "cos_n", "n": 1.0}))
        harmonics = self.waveform(e.get("waveform", {"harmonics": [[1, 1.0, 0.0]]}))
        return Emitter(power_w=power, offset_m=offset, profile=profile, harmonics=harmonics,
                       axis=axis / np.linalg.norm(axis))

    def profile(self, p: Any) -> BeamProfile:
        p = self.mapping(p, "emitter.profile", allowed=("type", "n", "theta_deg", "relative_intensity"))
        kind = self.enum(p.get("type", "cos_n"), "emitter.profile.type", ("cos_n", "table"))
        if kind == "cos_n":
            return BeamProfile("cos_n", n=self.number(p.get("n", 1.0), "emitter.profile.n", lo=0.0, hi=1e4))
        exp = "equal-length lists: theta_deg increasing in [0, 180], relative_intensity >= 0"
        th = self.numbers(p.get("theta_deg"), "emitter.profile.theta_deg", min_len=2, max_len=100_000,
                          lo=0.0, hi=180.0, expected=exp)
        va = self.numbers(p.get("relative_intensity"), "emitter.profile.relative_intensity", n=len(th),
                          lo=0.0, hi=1e12, expected=exp)
        if np.any(np.diff(th) <= 0) or max(va) <= 0:
            raise self.error("not increasing or all zero", "emitter.profile.theta_deg", exp)
        return BeamProfile("table", theta_deg=tuple(th), values=tuple(va))

    def waveform(self, w: Any) -> tuple[tuple[int, float, float], ...]:
        w = self.mapping(w, "emitter.waveform", allowed=("harmonics",))
        hs = w.get("harmonics")
        exp = "a list of [order h >= 1, amplitude >= 0, phase_rad] or {order, amplitude, phase_rad}"
        if not isinstance(hs, list) or not hs or len(hs) > 64:
            raise self.bad(hs, "emitter.waveform.harmonics", exp)
        out = []
        for i, h in enumerate(hs):
            f = f"emitter.waveform.harmonics[{i}]"
            if isinstance(h, dict):
                self.keys(h, f, ("order", "amplitude", "phase_rad"))
                h = [h.get("order"), h.get("amplitude"), h.get("phase_rad", 0.0)]
            if not isinstance(h, (list, tuple)) or len(h) not in (2, 3):
                raise self.bad(h, f, exp)
            order = self.integer(h[0], f + ".order", lo=1, hi=64)
            amp = self.number(h[1], f + ".amplitude", lo=0.0, hi=1e6)
            ph = self.number(h[2] if len(h) == 3 else 0.0, f + ".phase_rad", lo=-1e6, hi=1e6)
            out.append((order, amp, ph))
        return tuple(out)

    def materials(self, m: Any) -> dict[str, Material]:
        if not isinstance(m, dict) or not m:
            raise self.bad(m, "materials", "a non-empty mapping name -> {reflectance, ...}")
        out = {}
        for name, spec in m.items():
            f = f"materials.{name}"
            if isinstance(spec, (int, float)) and not isinstance(spec, bool):
                spec = {"reflectance": spec}
            spec = self.mapping(spec, f, allowed=("reflectance", "glossy", "texture") + _MEDIUM_KEYS, none_ok=False)
            if any(k in spec for k in _MEDIUM_KEYS):
                out[str(name)] = self.dielectric(spec, f, str(name))
                continue
            rho = self.number(self.require(spec, "reflectance", f, "a number in [0, 1]"),
                              f + ".reflectance", lo=0.0, hi=1.0)
            gl = self.mapping(spec.get("glossy"), f + ".glossy", allowed=("reflectance", "exponent"))
            g_rho = self.number(gl.get("reflectance", 0.0), f + ".glossy.reflectance", lo=0.0, hi=1.0)
            g_n = self.number(gl.get("exponent", 20.0 if gl else 0.0), f + ".glossy.exponent", lo=0.0, hi=1e6)
            if rho + g_rho > 1.0 + 1e-12:
                raise self.error(f"reflectance + glossy.reflectance = {rho + g_rho:g}", f,
                                 "a total reflectance <= 1 (energy conservation)")
            tex = self.texture(spec.get("texture"), f + ".texture")
            out[str(name)] = Material(str(name), rho, g_rho, g_n, tex)
        return out

    def dielectric(self, spec: dict, f: str, name: str) -> Material:
        """A smooth dielectric (glass: index and absorption) or a scattering medium (index 1,
        absorption, scattering, HG anisotropy); no diffuse keys."""
        for key in ("reflectance", "glossy", "texture"):
            if key in spec:
                raise self.error(f"{key!r} given with ior", f + "." + key,
                                 "either a diffuse material (reflectance, glossy, texture) or a dielectric "
                                 "(ior, absorption_per_m): a dielectric's reflection is Fresnel's")
        scat = "scattering_per_m" in spec
        n = self.number(spec["ior"] if "ior" in spec or not scat else 1.0, f + ".ior", lo=1.0, hi=4.0)
        sig = self.number(spec.get("absorption_per_m", 0.0), f + ".absorption_per_m", lo=0.0, hi=1e6)
        sig_s = self.number(spec.get("scattering_per_m", 0.0), f + ".scattering_per_m", lo=0.0, hi=1e6)
        g = self.number(spec.get("anisotropy", 0.0), f + ".anisotropy", lo=-0.99, hi=0.99)
        if "anisotropy" in spec and not scat:
            raise self.error("anisotropy without scattering_per_m", f + ".anisotropy",
                             "scattering_per_m > 0 with it (the phase function of a scattering medium)")
        if sig_s > 0 and n != 1.0:
            raise self.error(f"got {n:g} for a scattering medium", f + ".ior",
                             "1 (an index-matched boundary): refraction into a scattering medium is not modelled")
        if "ior" not in spec and not scat:
            raise self.error("missing", f + ".ior", "a refractive index in [1, 4] with absorption_per_m")
        return Material(name, 0.0, ior=n, absorption_per_m=sig, scattering_per_m=sig_s, anisotropy=g)

    def texture(self, t: Any, f: str) -> Texture | None:
        if t is None:
            return None
        t = self.mapping(t, f, allowed=("type", "size_m", "reflectance", "file"))
        kind = self.enum(t.get("type"), f + ".type", ("checker", "image"))
        if kind == "checker":
            a, b = self.numbers(t.get("reflectance", [0.8, 0.1]), f + ".reflectance", n=2, lo=0.0, hi=1.0,
                                expected="two reflectances [a, b] in [0, 1]")
            size = self.number(t.get("size_m", 0.1), f + ".size_m", lo=0.0, lo_open=True, hi=_MAX_COORD_M)
            return Texture("checker", size_m=size, values=(a, b))
        file = self.require(t, "file", f, "an image file (PNG, JPEG, TIFF) or .npy array")
        path = self._path(file, f + ".file")
        return Texture("image", file=str(path), image=self._read_image(path, f + ".file"))

    def _path(self, file: Any, f: str) -> Path:
        if not isinstance(file, str) or not file:
            raise self.bad(file, f, "a file path")
        path = Path(file)
        if not path.is_absolute():
            path = self.base_dir / path
        if not path.is_file():
            raise self.error(f"no such file {str(path)!r}", f, "an existing file (relative to the scene file)")
        return path

    def _read_image(self, path: Path, f: str) -> np.ndarray:
        shape = _image_shape(path)
        if shape is not None and math.prod(shape[:2]) > MAX_TEXTURE_PIXELS:
            raise self.error(f"image of {shape[1]} x {shape[0]} pixels", f,
                             f"a texture of at most {MAX_TEXTURE_PIXELS:,} pixels (4096 x 4096)")
        if path.suffix.lower() == ".npy":
            try:
                img = np.load(path).astype(np.float64)
            except Exception:  # numpy raises many types for a corrupt or pickled file
                raise self.error("cannot read the array", f, "a numeric .npy array") from None
        else:
            import cv2

            raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
            if raw is None:
                raise self.error("cannot read the image", f, "a PNG, JPEG or TIFF image, or a .npy array")
            scale = 65535.0 if raw.dtype == np.uint16 else 255.0 if raw.dtype == np.uint8 else 1.0
            img = raw.astype(np.float64) / scale
        if img.ndim == 3:
            img = img.mean(axis=2)
        if img.ndim != 2 or img.size == 0 or not np.all(np.isfinite(img)) or img.min() < 0 or img.max() > 1:
            raise self.error("image values outside [0, 1], not finite or not 2-D", f,
                             "a grey image with values in [0, 1]")
        return img

    def objects(self, objs: Any, materials: dict[str, Material]) -> list[SceneObject]:
        if not isinstance(objs, list) or not objs:
            raise self.bad(objs, "objects", "a non-empty list of objects")
        out: list[SceneObject] = []
        names: set[str] = set()
        for i, o in enumerate(objs):
            f = f"objects[{i}]"
            o = self.mapping(o, f, none_ok=False)
            kind = self.enum(self.require(o, "type", f, "one of " + ", ".join(OBJECT_TYPES)), f + ".type",
                             OBJECT_TYPES)
            name = o.get("name", f"{kind}{i}")
            if not isinstance(name, (str, int)) or isinstance(name, bool):
                raise self.bad(name, f + ".name", "a name (string)")
            name = str(name)
            if name in names:
                raise self.error(f"duplicate name {name!r}", f + ".name", "unique object names")
            names.add(name)
            if kind == "board" and "material" not in o:
                # a board's pattern sets its reflectance: the default paper is matte
                o = dict(o, material={"reflectance": 1.0})
            mat = self.require(o, "material", f, "a material name from materials")
            if isinstance(mat, dict):  # inline material
                mname = f"{name}__material"
                materials[mname] = self.materials({mname: mat})[mname]
                mat = mname
            if not isinstance(mat, str) or mat not in materials:
                raise self.error(f"unknown material {mat!r}", f + ".material",
                                 "one of " + ", ".join(sorted(materials)))
            if materials[mat].ior is not None and kind != "box":
                # the exact link to the point emitter is known through plane-parallel faces only
                raise self.error(f"a dielectric material ({mat!r}, ior) on a {kind}", f + ".type",
                                 "'box' (a glass slab or pane: the renderer connects the emitter through "
                                 "plane-parallel faces only, see docs/scene-format.md)")
            pose = self.pose(o.get("pose"), f + ".pose")
            params, mesh = self._shape(kind, o, f)
            out.append(SceneObject(name=name, type=kind, material=str(mat), pose=pose,
                                   params=params, mesh=mesh))
        return out

    def _size(self, o: dict, f: str, n: int, what: str) -> list[float]:
        size = self.require(o, "size", f, what)
        return self.numbers(size, f + ".size", n=n, lo=0.0, lo_open=True, hi=_MAX_COORD_M,
                            expected=f"a list of {n} numbers > 0 ({what})")

    def _shape(self, kind: str, o: dict, f: str) -> tuple[dict[str, Any], Any]:
        shape_keys = {"plane": {"size"}, "box": {"size"}, "sphere": {"radius", "subdivisions"},
                      "cylinder": {"radius", "height", "sections"}, "mesh": {"file", "scale"},
                      "board": {"target"}}[kind]
        self.keys(o, f, shape_keys | {"name", "type", "material", "pose"})
        if kind == "plane":
            return {"size": self._size(o, f, 2, "[width, height] in m")}, None
        if kind == "box":
            return {"size": self._size(o, f, 3, "[sx, sy, sz] in m")}, None
        if kind == "board":
            from tofhil.boards import BoardSpec

            target = self.require(o, "target", f, "a board: a mapping or KIND:COLSxROWS:SIZE_M[...]")
            if isinstance(target, str) and not target.lower().endswith((".yaml", ".yml")):
                spec = BoardSpec.parse(target, source=self.source, field=f + ".target")
            elif isinstance(target, str):
                spec = BoardSpec.parse(str(self._path(target, f + ".target")), field=f + ".target")
            else:
                spec = BoardSpec.from_dict(target, source=self.source, field=f + ".target")
            return {"target": spec.to_dict()}, None
        if kind == "sphere":
            r = self.number(self.require(o, "radius", f, "a radius in m"), f + ".radius", lo=0, lo_open=True,
                            hi=_MAX_COORD_M)
            sub = self.integer(o.get("subdivisions", 4), f + ".subdivisions", lo=1, hi=8)
            return {"radius": r, "subdivisions": sub}, None
        if kind == "cylinder":
            r = self.number(self.require(o, "radius", f, "a radius in m"), f + ".radius", lo=0, lo_open=True,
                            hi=_MAX_COORD_M)
            h = self.number(self.require(o, "height", f, "a height in m"), f + ".height", lo=0, lo_open=True,
                            hi=_MAX_COORD_M)
            sec = self.integer(o.get("sections", 64), f + ".sections", lo=3, hi=100_000)
            return {"radius": r, "height": h, "sections": sec}, None
        path = self._path(self.require(o, "file", f, "a mesh file (OBJ, PLY, STL, GLB)"), f + ".file")
        if path.suffix.lower() not in MESH_SUFFIXES:
            raise self.error(f"unsupported mesh format {path.suffix!r}", f + ".file",
                             "one of " + ", ".join(MESH_SUFFIXES))
        scale = o.get("scale", 1.0)
        if isinstance(scale, list):
            scale = self.numbers(scale, f + ".scale", n=3, lo=0, lo_open=True, hi=1e6)
        else:
            scale = self.number(scale, f + ".scale", lo=0, lo_open=True, hi=1e6)
        estimate = _mesh_triangles(path)
        if estimate is not None and estimate > MAX_MESH_TRIANGLES:
            raise self.error(f"mesh of {estimate:,} triangles", f + ".file",
                             f"a mesh of at most {MAX_MESH_TRIANGLES:,} triangles (about 1 GB to load and trace)")
        import trimesh

        try:
            mesh = trimesh.load(str(path), force="mesh")
        except Exception as exc:  # trimesh raises many types for corrupt files
            raise self.error(f"cannot read mesh ({exc})", f + ".file", "a mesh file trimesh reads") from None
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise self.error("no triangles in the file", f + ".file", "a mesh with faces")
        if len(mesh.faces) > MAX_MESH_TRIANGLES:
            raise self.error(f"mesh of {len(mesh.faces):,} triangles", f + ".file",
                             f"a mesh of at most {MAX_MESH_TRIANGLES:,} triangles (about 1 GB to load and trace)")
        if not np.all(np.isfinite(mesh.vertices)):
            raise self.error("vertices that are not finite", f + ".file", "a mesh with finite vertices")
        return {"file": str(path), "scale": scale}, mesh


def _image_shape(path: Path) -> tuple[int, ...] | None:
    """An image's (rows, columns, ...) from its header alone (None when the header cannot be
    read: the decoder then reports the file)."""
    if path.suffix.lower() == ".npy":
        fmt = np.lib.format
        try:
            with path.open("rb") as fh:
                major, _ = fmt.read_magic(fh)
                header = fmt.read_array_header_1_0 if major == 1 else fmt.read_array_header_2_0
                return tuple(header(fh)[0])
        except Exception:  # a corrupt file or another version: _read_image says so
            return None
    from PIL import Image

    Image.MAX_IMAGE_PIXELS = None  # the bound is ours (MAX_TEXTURE_PIXELS), with the file named
    try:
        with Image.open(path) as im:  # reads the header, decodes nothing
            return (im.height, im.width)
    except Exception:  # not an image Pillow knows: OpenCV may still read it
        return None


def _mesh_triangles(path: Path) -> int | None:
    """The number of triangles a mesh file declares, read without loading it: PLY's ``element
    face`` and binary STL's count from their headers, OBJ's and OFF's face lines counted (a
    polygon of n corners is n - 2 triangles, so the line count is a lower bound; scanning bytes
    runs at disk speed), ASCII STL's facets counted. None for formats whose count is only known
    after loading (GLB, glTF)."""
    suffix = path.suffix.lower()
    try:
        with path.open("rb") as fh:
            if suffix == ".ply":
                head = fh.read(65536)
                for line in head.split(b"\n"):
                    words = line.split()
                    if words[:2] == [b"element", b"face"] and len(words) == 3 and words[2].isdigit():
                        return int(words[2])
                    if line.strip() == b"end_header":
                        break
                return None
            if suffix == ".stl":
                head = fh.read(84)
                n = int(np.frombuffer(head[80:84], "<u4")[0]) if len(head) == 84 else -1
                if path.stat().st_size == 84 + 50 * n:  # binary: 50 bytes a triangle after the header
                    return n
                fh.seek(0)
                return _count_occurrences(fh, b"endfacet")  # ASCII
            if suffix == ".obj":
                return _count_occurrences(fh, b"\nf ", start=b"\n")
            if suffix == ".off":
                fh.readline()
                counts = fh.readline().split()
                return int(counts[1]) if len(counts) >= 2 and counts[1].isdigit() else None
    except OSError:
        return None
    return None


def _count_occurrences(fh: Any, needle: bytes, start: bytes = b"") -> int:
    """Occurrences of ``needle`` in a binary file (read in 16 MB blocks; ``start`` is put
    before the first block, so that ``b"\\nf "`` finds a face on the first line too)."""
    count, tail = 0, start
    while block := fh.read(16 << 20):
        data = tail + block
        count += data.count(needle)
        tail = data[-(len(needle) - 1):] if len(needle) > 1 else b""
    return count
