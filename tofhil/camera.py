"""Pinhole camera model with OpenCV distortion: rays, projection, radial <-> z, point clouds.

Conventions (ARCHITECTURE.md): x right, y down, z forward; intrinsics ``fx fy cx cy`` in
pixels with pixel centres at integer coordinates; distortion ``(k1, k2, p1, p2, k3)``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
from tofhil.errors import InputFileError
from tofhil.yamlio import load_yaml_file

DistanceKind = Literal["radial", "z"]

#: Points from which :meth:`CameraModel.undistort_normalized` runs compiled (fewer: numpy,
#: no numba import for a handful of points).
_COMPILED_UNDISTORT_MIN = 4096


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics, distortion and sensor geometry of a ToF camera."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    name: str = ""
    pixel_pitch_m: float | None = None
    #: Extra preset facts (modulation frequencies, wavelength, sources); not used in geometry.
    extra: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "dist", tuple(float(v) for v in self.dist))
        if len(self.dist) != 5:
            raise ValueError(f"dist must have 5 numbers (k1, k2, p1, p2, k3), got {len(self.dist)}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError("width and height must be positive")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError("fx and fy must be positive")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, vfov_deg: float | None = None,
                 **kwargs: Any) -> "CameraModel":
        """An undistorted camera with the principal point at the image centre."""
        fx = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        fy = fx if vfov_deg is None else (height / 2.0) / np.tan(np.radians(vfov_deg) / 2.0)
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
        return any(v != 0.0 for v in self.dist)

    def scaled(self, factor: float) -> "CameraModel":
        """The same lens on a sensor resampled by ``factor`` (binning < 1, supersampling > 1)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        return replace(self, width=w, height=h, fx=self.fx * factor, fy=self.fy * factor,
                       cx=(self.cx + 0.5) * factor - 0.5, cy=(self.cy + 0.5) * factor - 0.5,
                       pixel_pitch_m=None if self.pixel_pitch_m is None else self.pixel_pitch_m / factor)

    # ------------------------------------------------------------------ geometry
    def undistort_normalized(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates -> undistorted normalised image coordinates (x/z, y/z)."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        xd = (u - self.cx) / self.fx
        yd = (v - self.cy) / self.fy
        if not self.has_distortion:
            return xd, yd
        # Fixed-point inversion of the OpenCV model (as cv2.undistortPoints), run to
        # convergence: 20 iterations reach < 1e-10 px for realistic lenses. Many points: the
        # same arithmetic compiled (bit-identical, ~10x less CPU; numba imported only then).
        if xd.size >= _COMPILED_UNDISTORT_MIN:
            from tofhil.camera_kernels import undistort_arrays

            return undistort_arrays(xd, yd, self.dist, 20)
        k1, k2, p1, p2, k3 = self.dist
        x, y = xd.copy(), yd.copy()
        for _ in range(20):
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
        return x, y

    def distort_normalized(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates -> distorted normalised coordinates."""
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points ``[..., 3]`` -> pixel coordinates ``[..., 2]`` (with distortion)."""
        p = np.asarray(points, dtype=np.float64)
        x = p[..., 0] / p[..., 2]
        y = p[..., 1] / p[..., 2]
        xd, yd = self.distort_normalized(x, y)
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)

    def pixel_rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit ray directions ``[..., 3]`` through (possibly subpixel) pixel coordinates."""
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
        d = np.asarray(distance_m)
        mask = np.isfinite(d) & (d > 0)
        if valid is not None:
            mask &= np.asarray(valid, dtype=bool)
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
                             "fy": self.fy, "cx": self.cx, "cy": self.cy, "dist": list(self.dist)}
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
        if "hfov_deg" in d and "fx" not in d:
            try:
                cam = cls.from_fov(int(d["width"]), int(d["height"]), float(d["hfov_deg"]),
                                   None if d.get("vfov_deg") is None else float(d["vfov_deg"]))
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
            try:
                values[key] = typ(d[key])
                if typ is float and not math.isfinite(values[key]):
                    raise ValueError
            except (TypeError, ValueError, OverflowError):
                raise InputFileError(f"got {d[key]!r}", file=source, field=f"{prefix}{key}",
                                     expected="a finite number") from None
        dist = d.get("dist", [0.0] * 5)
        try:
            dist_t = tuple(float(v) for v in dist)
        except (TypeError, ValueError):
            dist_t = ()
        if len(dist_t) != 5 or not all(math.isfinite(v) for v in dist_t):
            raise InputFileError(f"got {dist!r}", file=source, field=f"{prefix}dist",
                                 expected="5 finite numbers (k1, k2, p1, p2, k3)")
        pitch = d.get("pixel_pitch_m")
        extra = {k: v for k, v in d.items()
                 if k not in ("width", "height", "fx", "fy", "cx", "cy", "dist", "name", "pixel_pitch_m")}
        try:
            return cls(dist=dist_t, name=str(d.get("name", "")),
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
