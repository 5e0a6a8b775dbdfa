"""A second, passive camera beside the ToF camera: the twin's grey image of the scene.

A pinhole camera (any :class:`tofhil.camera.CameraModel`, distortion included) at a pose
rigidly attached to the ToF camera (``tof_to_camera``: ToF frame -> this camera's frame)
sees each surface point with the radiance of a Lambertian reflector,
``L = rho / pi * (E_emitter + E_ambient)``: the ToF emitter's irradiance
``I(theta) cos(theta_s) / r^2`` (shadowed where something blocks the emitter) and the
scene's ambient irradiance, with ``rho`` the diffuse reflectance, textures and boards
applied. Reflectances are the scene's (at the emitter's wavelength); glossy lobes and
interreflections are left out. Each pixel averages ``samples`` x ``samples`` stratified
sub-pixel rays, so edges are anti-aliased. The image is radiance in W m^-2 sr^-1 (a camera's
grey value up to its exposure).
"""

from __future__ import annotations

import numpy as np

from tofhil.camera import CameraModel
from tofhil.errors import TofhilError
from tofhil.sim.geometry import RAY_EPSILON_M
from tofhil.sim.render import _Context, scene_geometry
from tofhil.sim.scene import Scene


def camera_pose_world(scene: Scene, tof_to_camera: np.ndarray) -> np.ndarray:
    """The passive camera's camera-to-world pose from the ToF camera's pose."""
    return scene.camera_pose @ np.linalg.inv(tof_to_camera)


def render_grey(scene: Scene, camera: CameraModel, tof_to_camera: np.ndarray, *, samples: int = 4) -> np.ndarray:
    """The grey (radiance) image ``[H, W]`` of a passive camera beside the ToF camera."""
    geom = scene_geometry(scene)
    # the ToF renderer's shading context: its reflectance lookup (textures, boards)
    ctx = _Context(scene, scene.camera, np.array([1.0]), (1,), 1, 0, 0, False, None, False, "random",
                   scene.camera_pose)
    if ctx.glass.any:      # this image is direct light off opaque surfaces only: glass would turn black
        i = int(np.flatnonzero(ctx.glass.ior > 0)[0])
        raise TofhilError("the RGB camera's image does not model glass or scattering media",
                          field=f"objects[{i}].material", expected="opaque materials in a scene with an rgb_camera")
    pose = camera_pose_world(scene, tof_to_camera)
    R, t = pose[:3, :3], pose[:3, 3]
    emitter = scene.emitter_position_world()
    axis = scene.camera_pose[:3, :3] @ scene.emitter.axis
    h, w = camera.shape
    off = (np.arange(samples) + 0.5) / samples - 0.5
    image = np.zeros(h * w)
    v0, u0 = np.mgrid[0:h, 0:w].astype(np.float64)
    for dv in off:
        for du in off:
            d = camera.pixel_rays(u0 + du, v0 + dv).reshape(-1, 3) @ R.T
            hits = geom.intersect(np.asarray(t, dtype=np.float64), d)
            idx = np.arange(len(d)) if hits.index is None else hits.index
            x = t + d[idx] * hits.t[:, None]
            n = hits.ng * np.sign(-np.einsum("ij,ij->i", hits.ng, d[idx]))[:, None]  # facing the camera
            obj = geom.tri_object[hits.prim]
            rho = ctx.reflectance(obj, x)
            to_e = emitter - x
            r = np.linalg.norm(to_e, axis=1)
            ld = to_e / r[:, None]
            cos_s = np.einsum("ij,ij->i", n, ld)
            cos_e = -ld @ axis
            irr = np.where(cos_s > 0, scene.emitter.intensity_w_sr(cos_e) * cos_s / (r * r), 0.0)
            lit = np.flatnonzero(irr > 0)
            if len(lit):
                origin = x[lit] + n[lit] * RAY_EPSILON_M
                shadow = geom.intersect(origin, ld[lit])
                blocked = np.zeros(len(lit), dtype=bool)
                hit_i = np.arange(len(lit)) if shadow.index is None else shadow.index
                blocked[hit_i] = shadow.t < r[lit][hit_i] - 2 * RAY_EPSILON_M
                irr[lit[blocked]] = 0.0
            image[idx] += rho / np.pi * (irr + scene.ambient_irradiance_w_m2)
    return (image / samples ** 2).reshape(h, w)
