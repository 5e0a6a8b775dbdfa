"""The two frame types every part of tofhil exchanges: raw correlation taps and depth."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tofhil.camera import CameraModel, DistanceKind


@dataclass
class RawFrame:
    """Correlation samples of one exposure: ``taps[F, K, H, W]``.

    Tap model (after conversion at the driver edge): ``c_k = B + A*cos(phi - theta_k)``
    with ``phi = 2*pi*f*L/c``.
    """

    taps: np.ndarray
    freq_hz: np.ndarray
    theta_rad: np.ndarray
    integration_time_s: float
    camera: CameraModel
    timestamp_s: float = 0.0
    sequence: int = 0
    temperature_c: float = math.nan
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.taps = np.asarray(self.taps)
        self.freq_hz = np.atleast_1d(np.asarray(self.freq_hz, dtype=np.float64))
        self.theta_rad = np.atleast_1d(np.asarray(self.theta_rad, dtype=np.float64))
        if self.taps.ndim != 4:
            raise ValueError(f"taps must be [F, K, H, W], got shape {self.taps.shape}")
        f, k, h, w = self.taps.shape
        if self.freq_hz.shape != (f,):
            raise ValueError(f"freq_hz has {self.freq_hz.shape}, taps have F={f}")
        if self.theta_rad.shape != (k,):
            raise ValueError(f"theta_rad has {self.theta_rad.shape}, taps have K={k}")
        if (h, w) != self.camera.shape:
            raise ValueError(f"taps are {h}x{w}, camera is {self.camera.height}x{self.camera.width}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.taps.shape[-2:]  # type: ignore[return-value]


@dataclass
class DepthFrame:
    """A depth image: distance (``kind`` says radial or z), amplitude, offset, validity."""

    distance_m: np.ndarray
    kind: DistanceKind
    camera: CameraModel
    amplitude: np.ndarray | None = None
    intensity: np.ndarray | None = None
    valid: np.ndarray | None = None
    timestamp_s: float = 0.0
    sequence: int = 0
    temperature_c: float = math.nan
    #: Per-pixel flag: the modulation frequencies disagreed during unwrapping.
    unwrap_conflict: np.ndarray | None = None
    #: The device's own per-pixel confidence, in its own unit (e.g. ADI's confidence byte).
    confidence: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in ("radial", "z"):
            raise ValueError(f"kind must be 'radial' or 'z', got {self.kind!r}")
        self.distance_m = np.asarray(self.distance_m)
        if self.distance_m.shape != self.camera.shape:
            raise ValueError(f"distance is {self.distance_m.shape}, camera is {self.camera.shape}")
        if self.valid is None:
            self.valid = np.isfinite(self.distance_m) & (self.distance_m > 0)
        else:
            self.valid = np.asarray(self.valid, dtype=bool)

    @property
    def radial_m(self) -> np.ndarray:
        return self.distance_m if self.kind == "radial" else self.camera.z_to_radial(self.distance_m)

    @property
    def z_m(self) -> np.ndarray:
        return self.distance_m if self.kind == "z" else self.camera.radial_to_z(self.distance_m)

    def points(self) -> np.ndarray:
        """Camera-frame points ``[N, 3]`` of the valid pixels."""
        return self.camera.points(self.distance_m, self.kind, self.valid)

    def point_cloud(self) -> Any:
        """An Open3D point cloud, amplitude as grey intensity when known."""
        return self.camera.point_cloud(self.distance_m, self.kind, self.valid, self.amplitude)


@dataclass
class DepthWithColor:
    """A depth image with its rays and a colour image with its camera and the ToF -> colour
    transform: what colouring a cloud needs, from a session's ``rgb/`` group or a recording."""

    z_m: np.ndarray                  # [H, W] depth along the optical axis (NaN or invalid where not valid)
    valid: np.ndarray                # [H, W] bool
    pixel_to_ray: Any                # (u, v) -> (x, y, ok): normalised ray coordinates of depth pixels
    tof_to_color: np.ndarray         # 4x4
    color_camera: Any
    rgb: np.ndarray                  # [h, w, 3] uint8

    def points(self) -> np.ndarray:
        """Depth-camera points ``[N, 3]`` of the valid pixels (row-major)."""
        v, u = np.mgrid[0:self.z_m.shape[0], 0:self.z_m.shape[1]].astype(np.float64)
        x, y, _ = self.pixel_to_ray(u, v)
        z = self.z_m
        return np.stack([x * z, y * z, z], axis=-1)[self.valid]
