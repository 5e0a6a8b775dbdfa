"""Wide-angle twins: a fisheye (and a rational) camera in front of a wall, rendered and
unprojected back onto the wall; the renderer's sub-pixel rays are the camera model's."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.sim import kernels
from tofhil.sim.render import render
from tofhil.sim.scene import scene_from_dict

F_HZ = 2.0e6            # unambiguous to 75 m: farther than any point of the 60 m wall seen
FISHEYE_DIST = [-0.0134, 0.0352, -0.0281, 0.0079]
#: 64 x 48 pixels, the image's corners 82 degrees off axis.
FISHEYE_CAMERA = {"width": 64, "height": 48, "fx": 27.0, "fy": 27.0, "cx": 31.5, "cy": 23.5,
                  "pixel_pitch_m": 20e-6, "model": "fisheye", "dist": FISHEYE_DIST}
#: The Azure Kinect's rational lens (factory coefficients) on 64 x 48 pixels, the corners 58
#: degrees off axis (inside the model's fold).
RATIONAL_CAMERA = {"width": 64, "height": 48, "fx": 40.0, "fy": 40.0, "cx": 31.5, "cy": 23.5,
                   "pixel_pitch_m": 20e-6, "model": "rational",
                   "dist": [0.548, -0.021, 2e-5, -7e-5, -0.0027, 0.89, 0.086, -0.0139]}


def wall_scene(camera: dict, *, distance: float = 1.0, tilt_deg: float = 0.0, **extra) -> dict:
    """A 60 m x 60 m wall (it fills any field short of 88 degrees at 1 m), tilted about y."""
    return {
        "camera": camera,
        "emitter": {"power_w": 1.0, "profile": {"type": "cos_n", "n": 0.0}},
        "materials": {"white": {"reflectance": 0.8}},
        "objects": [{"name": "wall", "type": "plane", "size": [60.0, 60.0], "material": "white",
                     "pose": {"position": [0.0, 0.0, distance], "rotation_deg": [0.0, tilt_deg, 0.0]}}],
        "sensor": {"freq_hz": [F_HZ]},
    } | extra


def phase_distance(res) -> np.ndarray:
    """Radial distance from the direct phasor: ``L = 2 d`` with the emitter at the pinhole."""
    phi = np.mod(np.angle(res.phasor[0, 0]), 2 * np.pi)
    return C_M_PER_S * phi / (4 * np.pi * F_HZ)


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0])
def test_fisheye_wall_unprojects_onto_the_wall(tilt_deg: float) -> None:
    scene = scene_from_dict(wall_scene(FISHEYE_CAMERA, tilt_deg=tilt_deg))
    cam = scene.camera
    assert cam.is_fisheye
    corner = cam.pixel_rays(np.array(0.0), np.array(0.0))
    assert math.degrees(math.acos(corner[2])) > 75.0          # a wide field: corners 82 deg off axis
    res = render(scene, samples_per_pixel=1, bounces=0)
    t = math.radians(tilt_deg)
    n = np.array([math.sin(t), 0.0, math.cos(t)])             # the wall: n . p = cos(tilt) (through z = 1 m)
    # independent of our inversion: the rays OpenCV's cv2.fisheye gives each pixel centre
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    und = cv2.fisheye.undistortPoints(np.stack([u.ravel(), v.ravel()], -1)[:, None, :], cam.K,
                                      np.array(cam.dist), criteria=(3, 1000, 1e-15))[:, 0]
    ray = np.column_stack([und, np.ones(len(und))])
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    facing = (ray @ n).reshape(cam.shape)
    # a tilted wall's horizon cuts the field (90 - tilt degrees off axis on one side): the
    # pixels that see the wall are those whose ray meets it within its 30 m half-size
    seen = np.isfinite(res.radial_m)
    assert np.all(seen[facing > 0.05]) and not np.any(seen[facing <= 0.0])
    assert np.all(res.power_w[seen] > 0) and (seen.all() if tilt_deg == 0 else seen.mean() > 0.7)
    for d in (res.radial_m, phase_distance(res)):
        pts = cam.points(np.where(seen, d, np.nan))
        assert np.abs(pts @ n - math.cos(t)).max() < 1e-4     # within 0.1 mm of the wall
    np.testing.assert_allclose(res.radial_m[seen], math.cos(t) / facing[seen], rtol=0, atol=1e-4)


def test_rational_wall_unprojects_onto_the_wall() -> None:
    scene = scene_from_dict(wall_scene(RATIONAL_CAMERA, tilt_deg=20.0))
    cam = scene.camera
    res = render(scene, samples_per_pixel=1, bounces=0)
    n = np.array([math.sin(math.radians(20.0)), 0.0, math.cos(math.radians(20.0))])
    h = n[2]                                                  # the wall through z = 1 m: n . p = cos(20 deg)
    for d in (res.radial_m, phase_distance(res)):
        assert np.abs(cam.points(d) @ n - h).max() < 1e-4
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    und = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], -1)[:, None, :], cam.K, np.array(cam.dist),
                              criteria=(3, 1000, 1e-15))[:, 0]
    ray = np.column_stack([und, np.ones(len(und))])
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    np.testing.assert_allclose(res.radial_m.ravel(), h / (ray @ n), rtol=0, atol=1e-4)


def test_pixels_without_a_ray_in_front_see_nothing() -> None:
    """An equidistant lens whose image corners look 100 degrees off axis: those pixels (and
    their sub-pixel samples) get no light, no distance and no object, the rest as usual."""
    cam = {"width": 40, "height": 40, "fx": 14.0, "fy": 14.0, "cx": 19.5, "cy": 19.5, "pixel_pitch_m": 20e-6,
           "model": "fisheye", "dist": [0.0, 0.0, 0.0, 0.0]}
    scene = scene_from_dict(wall_scene(cam, distance=0.5))
    theta = np.arccos(np.clip(scene.camera.rays[..., 2], -1, 1))
    behind = theta >= np.pi / 2 + 0.05
    front = theta < np.radians(80.0)
    assert behind.sum() > 20
    for spp in (1, 4):
        res = render(scene, samples_per_pixel=spp, bounces=0)
        assert np.all(res.power_w[behind] == 0) and np.all(np.isinf(res.radial_m[behind]))
        assert np.all(res.object_id[behind] == -1)
        assert np.all(res.power_w[front] > 0) and np.all(np.isfinite(res.radial_m[front]))
        assert np.all(np.isfinite(res.phasor))


@pytest.mark.parametrize("camera", [FISHEYE_CAMERA, RATIONAL_CAMERA], ids=["fisheye", "rational"])
def test_compiled_subpixel_rays_are_the_camera_models(camera: dict) -> None:
    cam = CameraModel.from_dict(camera)
    spp = 4
    rng = np.random.default_rng(5)
    pixels = np.arange(0, cam.width * cam.height, 3)
    U = rng.random((len(pixels) * spp, 6))
    weight = rng.random(cam.width * cam.height) + 0.5
    dirs, beta = np.empty((len(U), 3)), np.empty(len(U))
    kernels.subpixel_rays(pixels, spp, cam.width, U, cam.fx, cam.fy, cam.cx, cam.cy, np.asarray(cam.dist), 50,
                          np.eye(3), False, weight, dirs, beta, cam.is_fisheye)
    pix = np.repeat(pixels, spp)
    d_cam = cam.pixel_rays(pix % cam.width + U[:, 0] - 0.5, pix // cam.width + U[:, 1] - 0.5)
    front = d_cam[:, 2] > 0                                    # (NaN: no ray; both get weight 0)
    np.testing.assert_allclose(dirs[front], d_cam[front], rtol=0, atol=1e-14)
    np.testing.assert_allclose(beta[front], weight[pix][front] * d_cam[front, 2] ** 4, rtol=1e-13)
    assert np.all(beta[~front] == 0) and np.all(dirs[~front] == (0.0, 0.0, 1.0))


def test_fisheye_subpixel_render_agrees_with_the_centre_rays() -> None:
    """The compiled sub-pixel path renders the fisheye wall: each pixel's distance (the phase
    of its samples' sum) lies within the range of distances over its footprint (OpenCV's rays
    on a 5 x 5 grid over the pixel), and its power is the centre ray's to a few per cent."""
    scene = scene_from_dict(wall_scene(FISHEYE_CAMERA))
    cam = scene.camera
    ref = render(scene, samples_per_pixel=1, bounces=0)
    sub = render(scene, samples_per_pixel=64, bounces=0, subpixel=True)
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    g = np.linspace(-0.5, 0.5, 5)
    du, dv = np.meshgrid(g, g)
    pts = np.stack([(u[..., None] + du.ravel()).ravel(), (v[..., None] + dv.ravel()).ravel()], -1)
    und = cv2.fisheye.undistortPoints(pts[:, None, :], cam.K, np.array(cam.dist), criteria=(3, 1000, 1e-15))[:, 0]
    d = np.sqrt(1.0 + (und ** 2).sum(1)).reshape(cam.shape + (25,))     # D / cos(theta), D = 1 m
    inner = np.arccos(cam.rays[..., 2]) < np.radians(60.0)
    got = phase_distance(sub)
    assert np.all(got[inner] >= d.min(-1)[inner] - 5e-5) and np.all(got[inner] <= d.max(-1)[inner] + 5e-5)
    np.testing.assert_allclose(sub.power_w[inner], ref.power_w[inner], rtol=0.03)


def test_bad_camera_model_in_a_scene_is_one_field_error() -> None:
    with pytest.raises(InputFileError, match=r"field 'camera.model': got 'fish' \(expected one of 'plumb_bob', "
                                             r"'rational', 'fisheye'"):
        scene_from_dict(wall_scene(FISHEYE_CAMERA | {"model": "fish"}))
    with pytest.raises(InputFileError, match=r"field 'camera.dist'.*4 finite numbers \(k1, k2, k3, k4\)"):
        scene_from_dict(wall_scene(FISHEYE_CAMERA | {"dist": [0.0] * 5}))
    with pytest.raises(InputFileError, match=r"field 'camera.dist\[1\]'"):
        scene_from_dict(wall_scene(RATIONAL_CAMERA | {"dist": [0.0, "x", 0, 0, 0, 0, 0, 0]}))


def test_bundled_fisheye_wall_session_unprojects_onto_the_wall(tmp_path) -> None:
    """The bundled ``wall_fisheye`` twin (emitter moved onto the pinhole, so that the phase
    gives the radial distance; no fixed-pattern offsets, which shift the phase) simulated into
    a session without noise, demodulated and unprojected with the session's own camera: every
    pixel's point on the wall z = 1 m within 0.1 mm."""
    from tofhil.depth import depth_from_raw
    from tofhil.session import open_session
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import load_scene

    scene = load_scene("wall_fisheye", {"emitter": {"offset_m": [0.0, 0.0, 0.0]},
                                        "sensor": {"fixed_pattern": {"dsnu_e": 0.0, "prnu": 0.0}}})
    path = simulate_session(scene, tmp_path / "fish.h5", frames=1, noise=False)
    with open_session(path) as s:
        cam = s.camera
        assert cam == scene.camera and cam.is_fisheye
        d = depth_from_raw(s.raw_frame(0))
    corner = np.degrees(np.arccos(cam.rays[0, 0, 2]))
    assert corner > 80.0
    pts = cam.points(d.distance_m, valid=d.valid)
    assert len(pts) == cam.width * cam.height
    assert np.abs(pts[:, 2] - 1.0).max() < 1e-4
