"""Camera model with OpenCV's lens models: rays, projection, radial <-> z, point clouds.

Conventions (ARCHITECTURE.md): x right, y down, z forward; intrinsics ``fx fy cx cy`` in
pixels with pixel centres at integer coordinates. Distortion: OpenCV's 5-parameter model
``(k1, k2, p1, p2, k3)`` (``plumb_bob``, the default), its rational model with optional thin
prism ``(k1, k2, p1, p2, k3, k4, k5, k6[, s1, s2, s3, s4])`` (``rational``) or ``cv2.fisheye``'s
equidistant model ``(k1, k2, k3, k4)`` (``fisheye``); the formulas are in
:mod:`tofhil.lens_models`.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field, replace
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
from tofhil import lens_models
from tofhil.errors import InputFileError
from tofhil.lens_models import DistortionModel
from tofhil.schema import Schema
from tofhil.yamlio import load_yaml_file

DistanceKind = Literal["radial", "z"]

#: Points from which :meth:`CameraModel.undistort_normalized` runs compiled (fewer: numpy,
#: no numba import for a handful of points).
_COMPILED_UNDISTORT_MIN = 4096


def _compiled(n_points: int) -> bool:
    """Invert compiled: many points, or the kernels loaded already (a fit renders the same few
    hundred pixels hundreds of times; numpy's per-iteration overhead on a pixel that needs
    many Newton steps took 75 of 79 CPU-s of a lens-distortion fit on a wrong scene)."""
    return n_points >= _COMPILED_UNDISTORT_MIN or "tofhil.camera_kernels" in sys.modules


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics, distortion and sensor geometry of a ToF camera.

    ``dist`` holds the coefficients of ``distortion_model`` in OpenCV's order
    (:data:`tofhil.lens_models.COEFFICIENTS`): 5 for ``plumb_bob``, 8 or 12 for ``rational``,
    4 for ``fisheye``. In files the model is the camera's ``model`` key.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    name: str = ""
    pixel_pitch_m: float | None = None
    #: Extra preset facts (modulation frequencies, wavelength, sources); not used in geometry.
    extra: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)
    #: ``plumb_bob`` | ``rational`` | ``fisheye`` (:mod:`tofhil.lens_models`).
    distortion_model: DistortionModel = "plumb_bob"

    def __post_init__(self) -> None:
        object.__setattr__(self, "dist", tuple(float(v) for v in self.dist))
        model = lens_models.ALIASES.get(self.distortion_model, self.distortion_model)
        object.__setattr__(self, "distortion_model", model)
        if model not in lens_models.COEFFICIENTS:
            raise ValueError(f"distortion model {model!r} is not one of {', '.join(lens_models.MODELS)}")
        if len(self.dist) not in {len(n) for n in lens_models.COEFFICIENTS[model]}:
            raise ValueError(f"dist has {len(self.dist)} numbers (expected {lens_models.expected_dist(model)})")
        if self.width <= 0 or self.height <= 0:
            raise ValueError("width and height must be positive")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError("fx and fy must be positive")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, vfov_deg: float | None = None,
                 **kwargs: Any) -> "CameraModel":
        """A camera with the principal point at the image centre whose image edges are at
        ``hfov_deg`` (and ``vfov_deg``): through the pinhole for ``plumb_bob``/``rational``
        (the distortion, if any, is not counted), through the fisheye mapping
        ``theta_d(theta)`` for ``fisheye``."""
        model = lens_models.ALIASES.get(kwargs.get("distortion_model", "plumb_bob"),
                                        kwargs.get("distortion_model", "plumb_bob"))
        if model == "fisheye":
            c = lens_models.kernel_coeffs(model, tuple(kwargs.get("dist", (0.0,) * 4)))

            def half(fov: float) -> float:
                return float(lens_models.fisheye_theta_d(np.radians(fov) / 2.0, c)[0])
        else:
            def half(fov: float) -> float:
                return float(np.tan(np.radians(fov) / 2.0))
        fx = (width / 2.0) / half(hfov_deg)
        fy = fx if vfov_deg is None else (height / 2.0) / half(vfov_deg)
        return cls(width=width, height=height, fx=float(fx), fy=float(fy),
                   cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, **kwargs)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def has_distortion(self) -> bool:
        """Whether pixels map to rays other than the pinhole's (a fisheye always does)."""
        return self.distortion_model == "fisheye" or any(v != 0.0 for v in self.dist)

    @property
    def is_fisheye(self) -> bool:
        return self.distortion_model == "fisheye"

    @property
    def coefficient_names(self) -> tuple[str, ...]:
        """Names of the ``dist`` coefficients, in order (``k1, k2, p1, p2, k3, ...``)."""
        return next(n for n in lens_models.COEFFICIENTS[self.distortion_model] if len(n) == len(self.dist))

    @cached_property
    def kernel_coeffs(self) -> np.ndarray:
        """``dist`` in the slots the lens arithmetic reads, and the model's reach
        (:func:`lens_models.kernel_coeffs`; computed once per camera)."""
        c = lens_models.kernel_coeffs(self.distortion_model, self.dist)
        c.setflags(write=False)
        return c

    def with_added_distortion(self, deltas: dict[str, float]) -> "CameraModel":
        """The camera with ``deltas`` (coefficient name -> value) added to its coefficients of
        those names. Names its model lacks are left out (a fisheye has no p1, p2; plumb_bob no
        k4..k6): they do not change this camera's rays."""
        names = self.coefficient_names
        dist = tuple(v + float(deltas.get(n, 0.0)) for n, v in zip(names, self.dist))
        return replace(self, dist=dist)

    def scaled(self, factor: float) -> "CameraModel":
        """The same lens on a sensor resampled by ``factor`` (binning < 1, supersampling > 1)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        return replace(self, width=w, height=h, fx=self.fx * factor, fy=self.fy * factor,
                       cx=(self.cx + 0.5) * factor - 0.5, cy=(self.cy + 0.5) * factor - 0.5,
                       pixel_pitch_m=None if self.pixel_pitch_m is None else self.pixel_pitch_m / factor)

    # ------------------------------------------------------------------ geometry
    def _fisheye_thetas(self, td: np.ndarray) -> np.ndarray:
        """Field angle of each distorted radius (compiled for many points)."""
        if _compiled(td.size):
            from tofhil.camera_kernels import fisheye_theta_arrays

            return fisheye_theta_arrays(td, self.kernel_coeffs)
        return lens_models.fisheye_theta(td, self.kernel_coeffs)

    def undistort_normalized(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates -> undistorted normalised image coordinates (x/z, y/z).

        Each point is inverted to convergence (Newton, :mod:`tofhil.lens_models`): exact to
        rounding at any field angle the model reaches. NaN where the model maps no ray to the
        pixel (beyond the fold of its radial function) and, for a fisheye, where the ray is
        90 degrees or more off axis (it has no x/z: use :meth:`pixel_rays`).
        """
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        xd = (u - self.cx) / self.fx
        yd = (v - self.cy) / self.fy
        if not self.has_distortion:
            return xd, yd
        if self.is_fisheye:
            td = np.hypot(xd, yd)
            theta = self._fisheye_thetas(td)
            with np.errstate(invalid="ignore", divide="ignore"):
                k = np.where(td > 0, np.tan(theta) / np.where(td > 0, td, 1.0), 1.0)
                k = np.where(theta < np.pi / 2, k, np.nan)
            return xd * k, yd * k
        # Many points: the same arithmetic compiled (bit-identical; numba imported only then).
        if _compiled(xd.size):
            from tofhil.camera_kernels import undistort_arrays

            return undistort_arrays(xd, yd, self.kernel_coeffs)
        return lens_models.brown_undistort(xd, yd, self.kernel_coeffs)

    def distort_normalized(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates -> distorted normalised coordinates."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        c = self.kernel_coeffs
        if self.is_fisheye:
            r = np.hypot(x, y)
            td, _ = lens_models.fisheye_theta_d(np.arctan(r), c)
            with np.errstate(invalid="ignore", divide="ignore"):
                k = np.where(r > 0, td / np.where(r > 0, r, 1.0), 1.0)
            return x * k, y * k
        return lens_models.brown_distort(x, y, c)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points ``[..., 3]`` -> pixel coordinates ``[..., 2]`` (with distortion).

        A fisheye projects by the angle to the optical axis, so points at or beyond 90 degrees
        (z <= 0) project too; the other models divide by z."""
        p = np.asarray(points, dtype=np.float64)
        if self.is_fisheye:
            rho = np.hypot(p[..., 0], p[..., 1])
            td, _ = lens_models.fisheye_theta_d(np.arctan2(rho, p[..., 2]), self.kernel_coeffs)
            with np.errstate(invalid="ignore", divide="ignore"):
                k = np.where(rho > 0, td / np.where(rho > 0, rho, 1.0), 0.0)
            xd, yd = p[..., 0] * k, p[..., 1] * k
        else:
            xd, yd = self.distort_normalized(p[..., 0] / p[..., 2], p[..., 1] / p[..., 2])
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)

    def pixel_rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit ray directions ``[..., 3]`` through (possibly subpixel) pixel coordinates
        (NaN where the model maps no ray to the pixel)."""
        if self.is_fisheye:
            xd = (np.asarray(u, dtype=np.float64) - self.cx) / self.fx
            yd = (np.asarray(v, dtype=np.float64) - self.cy) / self.fy
            td = np.hypot(xd, yd)
            theta = self._fisheye_thetas(td)
            with np.errstate(invalid="ignore", divide="ignore"):
                s = np.where(td > 0, np.sin(theta) / np.where(td > 0, td, 1.0), 1.0)
            return np.stack([xd * s, yd * s, np.cos(theta)], axis=-1)
        x, y = self.undistort_normalized(u, v)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    @cached_property
    def rays(self) -> np.ndarray:
        """Unit ray direction through each pixel centre, ``[H, W, 3]`` float64."""
        v, u = np.mgrid[0:self.height, 0:self.width].astype(np.float64)
        rays = self.pixel_rays(u, v)
        rays.setflags(write=False)
        return rays

    @cached_property
    def ray_z(self) -> np.ndarray:
        """z component of each pixel's unit ray: ``z = d * ray_z`` (``[H, W]``)."""
        rz = np.ascontiguousarray(self.rays[..., 2])
        rz.setflags(write=False)
        return rz

    def radial_to_z(self, radial_m: np.ndarray) -> np.ndarray:
        """Radial distance along each pixel ray -> depth along the optical axis."""
        return np.asarray(radial_m) * self.ray_z

    def z_to_radial(self, z_m: np.ndarray) -> np.ndarray:
        """Depth along the optical axis -> radial distance along each pixel ray."""
        return np.asarray(z_m) / self.ray_z

    def points(self, distance_m: np.ndarray, kind: DistanceKind = "radial",
               valid: np.ndarray | None = None) -> np.ndarray:
        """Image of distances ``[H, W]`` -> camera-frame points ``[N, 3]`` of valid pixels.

        Pixels are valid where ``valid`` is true (if given), the distance is finite and > 0.
        Points are returned in row-major pixel order.
        """
        d = np.asarray(distance_m, dtype=np.float64)
        if d.shape != self.shape:
            raise ValueError(f"distance image is {d.shape}, camera is {self.shape}")
        radial = d if kind == "radial" else self.z_to_radial(d)
        mask = self.valid_mask(d, valid)
        return self.rays[mask] * radial[mask][:, None]

    def valid_mask(self, distance_m: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Pixels with a point: ``valid`` (if given), a finite distance > 0, and a ray (a lens
        model maps none to the pixels beyond its fold)."""
        d = np.asarray(distance_m)
        mask = np.isfinite(d) & (d > 0)
        if valid is not None:
            mask &= np.asarray(valid, dtype=bool)
        if self.has_distortion and d.shape == self.shape:
            mask &= np.isfinite(self.ray_z)
        return mask

    def point_cloud(self, distance_m: np.ndarray, kind: DistanceKind = "radial",
                    valid: np.ndarray | None = None, amplitude: np.ndarray | None = None) -> Any:
        """An Open3D ``PointCloud``; amplitude (if given) becomes grey colours scaled to [0, 1]."""
        from tofhil.open3d_loader import open3d

        o3d = open3d()
        pts = self.points(distance_m, kind, valid)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        if amplitude is not None:
            a = np.asarray(amplitude, dtype=np.float64)[self.valid_mask(distance_m, valid)]
            top = np.percentile(a, 99.5) if a.size else 1.0
            g = np.clip(a / (top if top > 0 else 1.0), 0.0, 1.0)
            cloud.colors = o3d.utility.Vector3dVector(np.repeat(g[:, None], 3, axis=1))
        return cloud

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"width": self.width, "height": self.height, "fx": self.fx,
                             "fy": self.fy, "cx": self.cx, "cy": self.cy,
                             "model": self.distortion_model, "dist": list(self.dist)}
        if self.name:
            d["name"] = self.name
        if self.pixel_pitch_m is not None:
            d["pixel_pitch_m"] = self.pixel_pitch_m
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str | Path = "<camera>",
                  prefix: str = "") -> "CameraModel":
        """Build from a mapping; errors name ``source`` and the field."""
        if not isinstance(d, dict):
            raise InputFileError("camera is not a mapping", file=source, field=prefix or "camera",
                                 expected="a mapping with width, height, fx, fy, cx, cy, dist")
        if "preset" in d:
            base = load_camera_preset(str(d["preset"]))
            overrides = {k: v for k, v in d.items() if k != "preset"}
            if not overrides:
                return base
            # the preset's extra facts (frequencies, wavelength, taps) survive an override of
            # its geometry: a 940 nm preset with another resolution is still 940 nm
            merged = base.to_dict() | dict(base.extra) | overrides
            return cls.from_dict(merged, source=source, prefix=prefix)
        model = check_model(Schema(source), d.get("model", "plumb_bob"), f"{prefix}model")
        n_default = len(lens_models.COEFFICIENTS[model][0])
        dist = d.get("dist", [0.0] * n_default)
        try:
            dist_t = tuple(float(v) for v in dist)
        except (TypeError, ValueError):
            dist_t = ()
        if len(dist_t) not in {len(n) for n in lens_models.COEFFICIENTS[model]} \
                or not all(math.isfinite(v) for v in dist_t):
            raise InputFileError(f"got {dist!r}", file=source, field=f"{prefix}dist",
                                 expected=lens_models.expected_dist(model))
        if "hfov_deg" in d and "fx" not in d:
            try:
                cam = cls.from_fov(_pixel_count(d["width"], source, f"{prefix}width"),
                                   _pixel_count(d["height"], source, f"{prefix}height"), float(d["hfov_deg"]),
                                   None if d.get("vfov_deg") is None else float(d["vfov_deg"]),
                                   distortion_model=model, dist=dist_t)
            except KeyError as exc:
                raise InputFileError("missing", file=source, field=f"{prefix}{exc.args[0]}",
                                     expected="an integer") from None
            d = cam.to_dict() | {k: v for k, v in d.items() if k not in ("hfov_deg", "vfov_deg")}
        values: dict[str, Any] = {}
        for key, typ in (("width", int), ("height", int), ("fx", float), ("fy", float),
                         ("cx", float), ("cy", float)):
            if key not in d:
                raise InputFileError("missing", file=source, field=f"{prefix}{key}",
                                     expected=f"a {'positive integer' if typ is int else 'number'}")
            if typ is int:
                values[key] = _pixel_count(d[key], source, f"{prefix}{key}")
                continue
            try:
                values[key] = typ(d[key])
                if typ is float and not math.isfinite(values[key]):
                    raise ValueError
            except (TypeError, ValueError, OverflowError):
                raise InputFileError(f"got {d[key]!r}", file=source, field=f"{prefix}{key}",
                                     expected="a finite number") from None
        pitch = d.get("pixel_pitch_m")
        extra = {k: v for k, v in d.items()
                 if k not in ("width", "height", "fx", "fy", "cx", "cy", "dist", "model", "name", "pixel_pitch_m")}
        try:
            return cls(dist=dist_t, name=str(d.get("name", "")), distortion_model=model,
                       pixel_pitch_m=None if pitch is None else float(pitch), extra=extra, **values)
        except ValueError as exc:
            raise InputFileError(str(exc), file=source, field=prefix.rstrip(".") or "camera") from None

    @classmethod
    def from_json(cls, text: str, *, source: str | Path = "<camera>") -> "CameraModel":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputFileError(f"not valid JSON ({exc.msg})", file=source, field="camera",
                                 expected="JSON text with width, height, fx, fy, cx, cy, dist") from None
        return cls.from_dict(d, source=source)


def _pixel_count(value: Any, source: str | Path, field: str) -> int:
    """A width or height: an integer >= 1 (an integral float such as MATLAB's 160.0 too, never
    160.5, which ``int()`` would quietly read as 160)."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
    if ok:
        try:
            ok = math.isfinite(value) and float(value).is_integer() and value >= 1
        except OverflowError:
            ok = False
    if not ok:
        raise InputFileError(f"got {value!r}", file=source, field=field, expected="an integer >= 1")
    return int(value)


def check_model(schema: Schema, value: Any, field: str) -> str:
    """A camera's ``model`` (``plumb_bob`` | ``rational`` | ``fisheye``, or a ROS name of one)
    as its canonical name; anything else is an error naming ``field``."""
    schema.enum(value, field, lens_models.MODELS + tuple(lens_models.ALIASES))
    return lens_models.ALIASES.get(value, value)


def check_distortion(schema: Schema, camera: dict[str, Any], prefix: str, *, bound: float = 1e6
                     ) -> None:
    """A camera mapping's ``model`` and ``dist`` as a file states them (scene files and presets
    through :class:`tofhil.schema.Schema`): the model known, ``dist`` the model's length of
    numbers within +-``bound``. Errors name ``{prefix}model`` or ``{prefix}dist``."""
    model = check_model(schema, camera.get("model", "plumb_bob"), f"{prefix}model")
    if "dist" in camera:
        if "model" not in camera and "preset" in camera:
            # the preset's model decides the length: checked on the merged camera
            # (CameraModel.from_dict, the same field named)
            schema.numbers(camera["dist"], f"{prefix}dist", max_len=12, lo=-bound, hi=bound)
            return
        lengths = sorted({len(n) for n in lens_models.COEFFICIENTS[model]})
        schema.numbers(camera["dist"], f"{prefix}dist", min_len=lengths[0], max_len=lengths[-1],
                       lo=-bound, hi=bound, expected=lens_models.expected_dist(model))
        if len(camera["dist"]) not in lengths:
            raise schema.bad(camera["dist"], f"{prefix}dist", lens_models.expected_dist(model))


def camera_presets_dir() -> Path:
    """The bundled ``configs/cameras`` directory."""
    return Path(str(resources.files("tofhil.configs"))) / "cameras"


def list_camera_presets() -> list[str]:
    return sorted(p.stem for p in camera_presets_dir().glob("*.yaml"))


def load_camera_preset(name_or_path: str | Path) -> CameraModel:
    """Load a camera preset by name (``configs/cameras/NAME.yaml``) or from a YAML path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = camera_presets_dir() / f"{name_or_path}.yaml"
    if not path.is_file():
        raise InputFileError("no such camera preset", file=path, field="preset",
                             expected="one of " + ", ".join(list_camera_presets()))
    return CameraModel.from_dict(load_yaml_file(path), source=path)
