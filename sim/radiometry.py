"""Closed-form radiometry of the twin: the camera equation, and a plane lit by the camera's emitter.

The renderer (:mod:`tofhil.sim.render`) applies these laws ray by ray (docs/scene-format.md):
radiant intensity ``I(theta_e) = P p(theta_e) / norm`` (the emitter's beam profile),
irradiance ``E = I cos(theta_s) / r^2`` (inverse square, cosine of incidence), Lambertian
radiance ``L = (rho / pi) E``, pixel power ``P_pix = L A_ap cos^4(alpha) a_pix`` with ``a_pix``
the pixel's area in normalised image coordinates (``1/(fx fy)`` without distortion) and
``A_ap = pi (f / 2N)^2``. For a plane the sum has one term per pixel and a closed form:
:func:`plane_view`. The analytic sources of the drivers (the emulator's wall, the DepthAI
host plane) are this closed form, so they have the twin's radiometry by construction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tofhil.camera import CameraModel
from tofhil.errors import TofhilError
from tofhil.sim.scene import BeamProfile

#: Pixel pitch assumed for the camera equation when the camera model gives none (m).
DEFAULT_PIXEL_PITCH_M = 10e-6


def pixel_area_normalized(camera: CameraModel, u: np.ndarray | None = None,
                          v: np.ndarray | None = None) -> np.ndarray:
    """|det d(x, y)/d(u, v)| per pixel: the pixel's area in undistorted normalised coordinates
    (of every pixel ``[H, W]``, or of the pixels at ``u``, ``v``).

    The pixel's solid angle is ``cos^3(alpha)`` times this; ``1/(fx fy)`` without distortion.
    """
    if u is not None and v is not None:
        u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
    if not camera.has_distortion:
        return np.full(camera.shape if u is None else u.shape, 1.0 / (camera.fx * camera.fy))
    if u is None or v is None:
        v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    h = 0.5
    xu1, yu1 = camera.undistort_normalized(u + h, v)
    xu0, yu0 = camera.undistort_normalized(u - h, v)
    xv1, yv1 = camera.undistort_normalized(u, v + h)
    xv0, yv0 = camera.undistort_normalized(u, v - h)
    return np.abs((xu1 - xu0) * (yv1 - yv0) - (xv1 - xv0) * (yu1 - yu0)) / (4 * h * h)


def aperture_area_m2(camera: CameraModel, f_number: float) -> float:
    """Entrance pupil area ``pi (f / 2N)^2``, with ``f = fx * pixel pitch``."""
    focal_m = camera.fx * (camera.pixel_pitch_m or DEFAULT_PIXEL_PITCH_M)
    return math.pi * (focal_m / (2.0 * f_number)) ** 2


@dataclass(frozen=True)
class Plane:
    """The plane ``n . X = distance_m`` in the camera frame (``n`` unit, pointing away from the
    camera), Lambertian with diffuse reflectance ``albedo``."""

    distance_m: float
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    albedo: float = 1.0

    @classmethod
    def tilted(cls, distance_m: float, tilt_deg: float = 0.0, albedo: float = 1.0) -> "Plane":
        """A plane at ``distance_m`` along its normal, the normal tilted by ``tilt_deg`` about x."""
        t = math.radians(tilt_deg)
        return cls(distance_m, (0.0, math.sin(t), math.cos(t)), albedo)


@dataclass
class PlaneView:
    """What each pixel of a camera sees of a :class:`Plane` (arrays ``[H, W]``)."""

    radial_m: np.ndarray         #: camera centre -> plane along the pixel's ray
    path_m: np.ndarray           #: optical path emitter -> plane -> camera (``2 d`` for a co-located emitter)
    irradiance_w_m2: np.ndarray  #: the emitter's irradiance on the plane at that point
    power_w: np.ndarray          #: emitter light reaching the pixel (camera equation)


def plane_view(camera: CameraModel, plane: Plane, *, power_w: float, profile: BeamProfile | None = None,
               emitter_offset_m: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
               emitter_axis: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0),
               aperture_m2: float = 1.0) -> PlaneView:
    """The twin's direct light from ``plane`` per pixel, in closed form (pixel-centre rays)."""
    profile = profile or BeamProfile()
    n = np.asarray(plane.normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    rays = camera.rays                       # unit, [H, W, 3]
    cos_view = rays @ n
    if not (plane.distance_m > 0 and np.all(cos_view > 0)):
        raise TofhilError("the plane does not cover the field of view", field="plane",
                          expected="a plane in front of the camera (distance > 0, tilt < 90 deg minus half the FOV)")
    d = plane.distance_m / cos_view
    to_point = rays * d[..., None] - np.asarray(emitter_offset_m, dtype=np.float64)
    r_e = np.linalg.norm(to_point, axis=-1)
    u = to_point / r_e[..., None]
    axis = np.asarray(emitter_axis, dtype=np.float64)
    cos_e = u @ (axis / np.linalg.norm(axis))          # angle off the beam axis
    cos_s = np.clip(u @ n, 0.0, None)                   # incidence on the plane (its lit side faces -n)
    intensity = power_w * profile.relative(cos_e) / profile.solid_angle_norm_sr
    irradiance = intensity * cos_s / r_e ** 2
    radiance = plane.albedo / math.pi * irradiance
    power = radiance * aperture_m2 * rays[..., 2] ** 4 * pixel_area_normalized(camera)
    return PlaneView(radial_m=d, path_m=r_e + d, irradiance_w_m2=irradiance, power_w=power)


def plane_relative_amplitude(camera: CameraModel, plane: Plane, profile: BeamProfile | None = None) -> np.ndarray:
    """Pixel power of ``plane`` (emitter at the camera centre) relative to the on-axis pixel of
    a white (albedo 1) fronto-parallel plane at 1 m: the scale-free radiometry analytic sources
    multiply by their brightness at 1 m."""
    profile = profile or BeamProfile()
    view = plane_view(camera, plane, power_w=1.0, profile=profile)
    # The same camera equation on the axis: cos = 1, r = 1 m, pixel area 1/(fx fy).
    ref = float(profile.relative(np.array(1.0))) / profile.solid_angle_norm_sr / math.pi / (camera.fx * camera.fy)
    return view.power_w / ref
