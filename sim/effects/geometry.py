"""Scene-stage effects of the camera's geometry: its pose error and the lens distortion its
model lacks (both change the pixel rays, so both need a new render)."""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from tofhil.sim.effects.base import BENCH_CHANGE, Effect, Param, Separation
from tofhil.sim.effects.registry import register

# Diagnosis searches small pose errors: a bench camera is placed to a few centimetres and degrees.
_POSE_R: dict[str, Any] = {"fit": (-0.05, 0.05), "step": 1e-3}
_POSE_T: dict[str, Any] = {"fit": (-0.1, 0.1), "step": 1e-3}


@register
class PoseEffect(Effect):
    name = "pose"
    stage = "scene"
    rank = 10
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


@register
class LensDistortionEffect(Effect):
    name = "lens_distortion"
    mimicked_by = {"pose": Separation(BENCH_CHANGE, "known_target", "a tilted plane or a known target filling the view")}
    stage = "scene"
    rank = 20
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


@register
class EmitterPositionEffect(Effect):
    name = "emitter_position"
    stage = "scene"
    rank = 15
    summary = "the emitter displaced from where the scene puts it, in the camera frame: `offset_m + (dx, dy, dz)`"
    doc = ("The emitter (LED or VCSEL) elsewhere than the scene's `emitter.offset_m` says, in the camera frame "
           "(x right, y down, z forward): the optical path from the emitter to each surface changes (a range "
           "error that follows the geometry: half the extra emitter-to-surface length), and so do the "
           "irradiance (1/r^2 and the beam's angle) and the shadows the emitter casts. A bench set-up rarely "
           "knows the emitter's position to better than a few centimetres.")
    params = {
        "dx": Param(0.0, -0.3, 0.3, "m", "emitter displacement along camera x", fit=(-0.1, 0.1), step=2e-3),
        "dy": Param(0.0, -0.3, 0.3, "m", "emitter displacement along camera y", fit=(-0.1, 0.1), step=2e-3),
        "dz": Param(0.0, -0.3, 0.3, "m", "emitter displacement along the optical axis", fit=(-0.1, 0.1), step=2e-3),
    }

    def apply_scene(self, scene: Any, values: Mapping[str, Any]) -> Any:
        e = scene.emitter
        offset = np.asarray(e.offset_m, dtype=float) + np.array([values["dx"], values["dy"], values["dz"]], dtype=float)
        return dataclasses.replace(scene, emitter=dataclasses.replace(e, offset_m=offset))
