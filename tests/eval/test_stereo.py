"""ToF <-> second camera extrinsics from simultaneous board views rendered by the twin (ToF
amplitude through the sensor model, the second camera's grey image from sim/rgb.py)."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.depth import depth_from_raw
from tofhil.eval.calibration.camera import calibrate_stereo
from tofhil.sim.pipeline import simulate
from tofhil.sim.rgb import render_grey
from tofhil.sim.scene import _rotation_xyz, load_scene

POSES = [(20, 0, 0, 0.55), (-20, 5, 5, 0.55), (0, 20, -5, 0.5), (5, -20, 10, 0.5), (15, 15, 0, 0.6)]


@pytest.mark.slow
def test_stereo_extrinsics_within_2mm_and_0p2deg():
    # the colour camera 50 mm right of and 8 mm below the ToF camera, turned 2 deg about y, 1 about x
    truth = np.eye(4)
    truth[:3, :3] = _rotation_xyz(1.0, 2.0, 0.0)
    truth[:3, 3] = [-0.05, 0.008, 0.002]
    other = CameraModel.from_fov(240, 180, 62.0)
    pairs = []
    for i, (tx, ty, rz, d) in enumerate(POSES):
        scene = load_scene("board", {"params": {"tilt_x_deg": tx, "tilt_y_deg": ty, "roll_deg": rz,
                                                "board_distance_m": d},
                                     "render": {"samples_per_pixel": 16}})
        amp = depth_from_raw(simulate(scene, noise=True, seed=i)[0]).amplitude
        pairs.append((f"v{i}", amp, render_grey(scene, other, truth, samples=4)))
    cal = calibrate_stereo(pairs, "checkerboard:9x6:0.03", scene.camera, other)
    assert all(v.used for v in cal.views) and cal.rms_px < 0.1
    dt = np.linalg.norm(cal.tof_to_camera[:3, 3] - truth[:3, 3]) * 1e3
    R = cal.tof_to_camera[:3, :3].T @ truth[:3, :3]
    dr = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    assert dt < 2.0 and dr < 0.2, (dt, dr)


def test_grey_image_is_lambertian_under_the_emitter():
    """A fronto-parallel wall, emitter at the camera: the radiance at the image centre is
    rho/pi * I(0) / d^2 (closed form) when the passive camera sits at the ToF camera."""
    scene = load_scene("wall")
    cam = CameraModel.from_fov(41, 31, 40.0)
    g = render_grey(scene, cam, np.eye(4), samples=1)
    e = scene.emitter
    d = 1.0
    # the emitter is 15 mm beside the camera: the centre point is off its axis by atan(0.015)
    r2 = d * d + e.offset_m[0] ** 2
    cos = d / np.sqrt(r2)
    expect = 0.8 / np.pi * e.intensity_w_sr(np.array(cos)) * cos / r2
    assert abs(g[15, 20] / expect - 1) < 1e-6


def test_calibrate_stereo_cli_on_sessions_with_an_rgb_group(tofhil_cli, tmp_path):
    import yaml

    from tofhil.session_rgb import read_rgb, write_rgb
    from tofhil.sim.pipeline import simulate_session

    truth = np.eye(4)
    truth[:3, 3] = [-0.04, 0.0, 0.0]
    other = CameraModel.from_fov(200, 150, 60.0)
    paths = []
    for i, (tx, ty, rz, d) in enumerate(POSES[:4]):
        scene = load_scene("board", {"params": {"tilt_x_deg": tx, "tilt_y_deg": ty, "roll_deg": rz,
                                                "board_distance_m": d}, "render": {"samples_per_pixel": 8}})
        p = simulate_session(scene, tmp_path / f"v{i}.h5", seed=i)
        write_rgb(p, [render_grey(scene, other, truth, samples=3)], other)
        paths.append(p)
    assert read_rgb(paths[0]).tof_to_camera is None and read_rgb(paths[0]).camera == other
    out = tmp_path / "extr.yaml"
    r = tofhil_cli("calibrate-stereo", *paths, "--target", "checkerboard:9x6:0.03", "--out", out)
    assert r.returncode == 0, r.stderr
    T = np.asarray(yaml.safe_load(out.read_text())["tof_to_camera"])
    assert np.abs(T[:3, 3] - truth[:3, 3]).max() < 0.002
    r = tofhil_cli("calibrate-stereo", tmp_path / "v0.h5", "--target", "checkerboard:9x6:0.03", "--out", out)
    assert r.returncode == 2 and "already exists" in r.stderr


def test_scene_rgb_camera_block_is_rendered_into_the_session(tmp_path):
    from tofhil.errors import InputFileError
    from tofhil.session_rgb import read_rgb
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import scene_from_yaml, scene_to_yaml

    block = {"rgb_camera": {"width": 64, "height": 48, "hfov_deg": 60.0, "samples": 2,
                            "pose": {"position": [0.04, 0.0, 0.0]}},
             "render": {"samples_per_pixel": 1}}
    scene = load_scene("board", block)
    assert np.allclose(scene.rgb_camera.tof_to_camera[:3, 3], [-0.04, 0, 0])
    again = scene_from_yaml(scene_to_yaml(scene))
    assert again.rgb_camera.camera == scene.rgb_camera.camera and np.allclose(again.rgb_camera.pose, scene.rgb_camera.pose)
    p = simulate_session(scene, tmp_path / "s.h5")
    rgb = read_rgb(p)
    assert rgb.images.shape == (1, 48, 64) and np.allclose(rgb.tof_to_camera, scene.rgb_camera.tof_to_camera)
    # the board (ink and paper) is in the second camera's view: two levels of brightness
    assert rgb.images.max() > 5 * np.percentile(rgb.images[rgb.images > 0], 5)
    bad = {"rgb_camera": {"width": 64, "height": 48, "hfov_deg": 60.0, "samples": 0}}
    try:
        load_scene("board", bad)
    except InputFileError as exc:
        assert exc.field == "rgb_camera.samples"
    else:
        raise AssertionError("samples 0 accepted")
