"""Glass-slab scene for issue 16: a plane seen through a cover glass, in closed form and in Mitsuba.

The scene (camera frame, OpenCV axes, metres): a pinhole camera at the origin looking along
+z; a plane-parallel glass slab of index ``n`` and thickness ``t`` in front of the lens only
(faces at ``z = z0`` and ``z = z0 + t``, ``|x|, |y| <= half_width``), like a cover window;
the emitter beside it at ``emitter_m`` so that its light reaches the target directly; a
diffuse target plane (point ``p0``, normal ``nrm``) behind the slab.

Why the emitter sits beside the glass: a path tracer cannot connect a diffuse point to a
POINT emitter through a specular interface (the shadow ray is blocked, and a sampled
direction never hits a point). With the emitter outside the slab's footprint the returned
light crosses the glass on the camera leg only, and Mitsuba renders it exactly.

Closed form of the transmitted return, per pixel ray ``u`` (unit, camera frame):
Snell at the entrance face, ``t / cos(theta_t)`` of glass at index ``n``, the exit ray
parallel to ``u`` displaced sideways, then the target. The optical path length is

    L = |entry| + n t / cos(theta_t) + |hit - exit| + |emitter - hit|

and for the centre pixel of a target perpendicular to the axis it exceeds the slab-free path
by exactly ``(n - 1) t`` (the hit point does not move). The radial distance a ToF camera reads
is ``L / 2`` (camera and emitter legs averaged), so the centre pixel reads ``(n - 1) t / 2``
farther here; with the emitter behind the glass too (both legs through it) it would read
``(n - 1) t`` farther. Neglected: the internal double reflection (amplitude ~R^2 = 0.2 % for
n = 1.5, extra path 2 n t / cos(theta_t); its phase pull is < 0.1 mm at 44 MHz for t = 10 mm).

tofhil's renderer has no refraction yet (issue 16): ``tofhil_scene_without_slab`` is the same
scene without the glass; the future refractive renderer must reproduce ``opl_through_slab``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class GlassSlab:
    n: float = 1.5                    # refractive index of the glass
    t_m: float = 0.010                # thickness
    z0_m: float = 0.020               # distance of the entrance face from the pinhole
    half_width_m: float = 0.050       # the slab covers |x|, |y| <= this (the lens only)
    target_point_m: tuple[float, float, float] = (0.0, 0.0, 1.0)
    target_normal: tuple[float, float, float] = (0.0, 0.0, -1.0)
    emitter_m: tuple[float, float, float] = (0.15, 0.0, 0.0)
    albedo: float = 0.8
    target_size_m: float = 4.0
    extra: dict = field(default_factory=dict)

    def covers_view(self, rays: np.ndarray) -> bool:
        """Every pixel ray crosses the whole slab (enters and leaves through its faces)."""
        u = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        _, exit_ = _through(u.reshape(-1, 3), self.n, self.t_m, self.z0_m)
        return bool(np.all(np.abs(exit_[:, :2]) <= self.half_width_m))


def _through(u: np.ndarray, n: float, t: float, z0: float) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit points of rays ``u`` [N, 3] from the origin through the slab."""
    entry = u * (z0 / u[:, 2:3])
    # Snell in vector form at a face with normal +z: the tangential part scales by 1/n.
    v = np.concatenate([u[:, :2] / n, np.zeros((len(u), 1))], axis=1)
    v[:, 2] = np.sqrt(1.0 - np.sum(v[:, :2] ** 2, axis=1))
    exit_ = entry + v * (t / v[:, 2:3])
    return entry, exit_


def _hit_plane(o: np.ndarray, d: np.ndarray, p0: np.ndarray, nrm: np.ndarray) -> np.ndarray:
    s = ((p0 - o) @ nrm) / (d @ nrm)
    return o + s[:, None] * d


def opl_through_slab(slab: GlassSlab, rays: np.ndarray) -> np.ndarray:
    """Optical path length (m) emitter -> target -> slab -> pinhole for each pixel ray
    (``rays`` [..., 3] in the camera frame, any length)."""
    shape = rays.shape[:-1]
    u = (rays / np.linalg.norm(rays, axis=-1, keepdims=True)).reshape(-1, 3)
    p0, nrm = np.asarray(slab.target_point_m, float), np.asarray(slab.target_normal, float)
    entry, exit_ = _through(u, slab.n, slab.t_m, slab.z0_m)
    hit = _hit_plane(exit_, u, p0, nrm)              # the exit ray is parallel to u
    glass = slab.n * np.linalg.norm(exit_ - entry, axis=1)
    L = (np.linalg.norm(entry, axis=1) + glass + np.linalg.norm(hit - exit_, axis=1)
         + np.linalg.norm(np.asarray(slab.emitter_m) - hit, axis=1))
    return L.reshape(shape)


def opl_without_slab(slab: GlassSlab, rays: np.ndarray) -> np.ndarray:
    """The same path with the glass removed (straight camera ray)."""
    shape = rays.shape[:-1]
    u = (rays / np.linalg.norm(rays, axis=-1, keepdims=True)).reshape(-1, 3)
    p0, nrm = np.asarray(slab.target_point_m, float), np.asarray(slab.target_normal, float)
    hit = _hit_plane(np.zeros_like(u), u, p0, nrm)
    L = np.linalg.norm(hit, axis=1) + np.linalg.norm(np.asarray(slab.emitter_m) - hit, axis=1)
    return L.reshape(shape)


def tofhil_scene_without_slab(slab: GlassSlab, camera_preset: str = "holmlund_thesis",
                              freq_hz: float = 44.0e6) -> dict:
    """tofhil scene mapping of the slab-free scene (camera at the world origin, world = camera
    frame): the target and the emitter beside the lens."""
    nrm = np.asarray(slab.target_normal, float)
    # The plane's local +z is its normal: rotate +z onto -nrm's direction (faces the camera).
    ry = float(np.degrees(np.arctan2(-nrm[0], -nrm[2])))
    rx = float(np.degrees(np.arcsin(np.clip(nrm[1], -1, 1))))
    return {
        "name": "glass_slab_target",
        "camera": {"preset": camera_preset,
                   "pose": {"position": [0.0, 0.0, 0.0], "look_at": [0.0, 0.0, 1.0], "up": [0.0, -1.0, 0.0]}},
        "emitter": {"offset_m": list(slab.emitter_m), "power_w": 0.3,
                    "profile": {"type": "table", "theta_deg": [0.0, 180.0], "relative_intensity": [1.0, 1.0]}},
        "materials": {"white": {"reflectance": slab.albedo}},
        "objects": [{"name": "target", "type": "plane", "size": [slab.target_size_m, slab.target_size_m],
                     "material": "white",
                     "pose": {"position": list(slab.target_point_m), "rotation_deg": [rx, ry, 0.0]}}],
        "sensor": {"freq_hz": [freq_hz]},
    }


def mitsuba_slab_shape(slab: GlassSlab, to_world_of_camera: np.ndarray) -> dict:
    """Mitsuba shape dict of the slab (a dielectric box) given the camera-to-world 4x4 of the
    tofhil scene (Mitsuba's own camera flip is applied by the caller's sensor only)."""
    import mitsuba as mi

    centre = np.array([0.0, 0.0, slab.z0_m + slab.t_m / 2, 1.0])
    scale = np.diag([slab.half_width_m, slab.half_width_m, slab.t_m / 2, 1.0])
    M = to_world_of_camera @ np.array([[1, 0, 0, centre[0]], [0, 1, 0, centre[1]],
                                       [0, 0, 1, centre[2]], [0, 0, 0, 1]], float) @ scale
    return {"type": "cube", "to_world": mi.ScalarTransform4f(M.tolist()),
            "bsdf": {"type": "dielectric", "int_ior": slab.n, "ext_ior": 1.0}}
