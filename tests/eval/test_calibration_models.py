"""``calibrate-camera --model rational | fisheye`` on board views the twin renders through a
wide rational lens (the Azure Kinect's factory coefficients) and a 150-degree fisheye: the
fitted camera images every ray the boards covered where the true one does."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tofhil.camera import load_camera_preset
from tofhil.depth import depth_from_raw
from tofhil.eval.calibration import calibrate_camera, calibrate_sessions
from tofhil.sim.pipeline import simulate, simulate_session
from tofhil.sim.scene import load_scene

W, H = 160, 120
RATIONAL = {"width": W, "height": H, "fx": 100.0, "fy": 99.6, "cx": 81.3, "cy": 58.2, "model": "rational",
            "dist": [0.548, -0.021, 2e-5, -7e-5, -0.0027, 0.89, 0.086, -0.0139]}     # edges 46 / 34 deg off axis
FISHEYE = {"width": W, "height": H, "fx": 62.0, "fy": 61.8, "cx": 81.3, "cy": 58.2, "model": "fisheye",
           "dist": [-0.0134, 0.0352, -0.0281, 0.0079]}                              # edges 73 / 55 deg off axis


def poses(distance: float, ax_deg: float, ay_deg: float) -> list[tuple[float, ...]]:
    """Board poses (tilt x, tilt y, roll, distance, x, y): five on the axis, tilted, and eight
    around the field ``ax_deg`` / ``ay_deg`` off axis, each turned to face the camera."""
    out = [(0, 0, 0, distance, 0, 0), (25, 0, 0, distance, 0, 0), (-25, 0, 0, distance, 0, 0),
           (0, 25, 0, distance, 0, 0), (0, -25, 0, distance, 0, 0)]
    for sx, sy in ((-1, -1), (1, -1), (-1, 1), (1, 1), (-1, 0), (1, 0), (0, -1), (0, 1)):
        ax, ay = math.radians(ax_deg * sx), math.radians(ay_deg * sy)
        out.append((-math.degrees(ay), math.degrees(ax), 10 * sx * sy, distance,
                    distance * math.tan(ax), distance * math.tan(ay)))
    return out


def board_scene(camera: dict, pose: tuple[float, ...]):
    tx, ty, rz, d, x, y = pose
    return load_scene("board", {"params": {"tilt_x_deg": tx, "tilt_y_deg": ty, "roll_deg": rz,
                                           "board_distance_m": d, "board_x_m": x, "board_y_m": y},
                                "camera": camera, "render": {"samples_per_pixel": 16}})


def covered_difference_px(truth, fitted, cal) -> float:
    """Largest distance (px) between where the true and the fitted camera image the same ray,
    over the pixels inside the convex hull of every board corner the calibration used (a
    model is only determined where it saw corners)."""
    pts = np.concatenate([v.detection.image_points for v in cal.views if v.used]).astype(np.float32)
    hull = cv2.convexHull(pts)
    v, u = np.mgrid[0:truth.height, 0:truth.width].astype(np.float64)
    inside = np.array([cv2.pointPolygonTest(hull, (float(a), float(b)), False) >= 0
                       for a, b in zip(u.ravel(), v.ravel())]).reshape(truth.shape)
    assert inside.mean() > 0.35
    uv = fitted.project(truth.pixel_rays(u, v))
    return float(np.hypot(uv[..., 0] - u, uv[..., 1] - v)[inside].max())


@pytest.mark.slow
def test_rational_calibration_recovers_a_wide_rational_lens():
    images = [(f"v{i}", depth_from_raw(simulate(board_scene(RATIONAL, p), noise=False)[0]).amplitude)
              for i, p in enumerate(poses(0.45, 24.0, 17.0))]
    truth = board_scene(RATIONAL, poses(0.45, 0, 0)[0]).camera
    cal = calibrate_camera(images, "checkerboard:9x6:0.03", model="rational")
    cam = cal.camera
    assert cam.distortion_model == "rational" and len(cam.dist) == 8
    assert len(cal.used) == len(images) and cal.rms_px < 0.1
    assert cam.fx == pytest.approx(truth.fx, rel=5e-3) and cam.fy == pytest.approx(truth.fy, rel=5e-3)
    assert abs(cam.cx - truth.cx) < 0.5 and abs(cam.cy - truth.cy) < 0.5
    assert covered_difference_px(truth, cam, cal) < 0.3
    assert set(cal.std_intrinsics) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"}
    # the thin-prism variant fits 12 coefficients
    prism = calibrate_camera(images, "checkerboard:9x6:0.03", model="thin_prism")
    assert len(prism.camera.dist) == 12 and prism.camera.distortion_model == "rational"


@pytest.mark.slow
def test_fisheye_calibration_cli_writes_a_fisheye_preset(tmp_path, tofhil_cli):
    paths = [simulate_session(board_scene(FISHEYE, p), tmp_path / f"v{i}.h5", frames=1, seed=i, noise=False)
             for i, p in enumerate(poses(0.3, 30.0, 22.0))]
    out = tmp_path / "fish.yaml"
    r = tofhil_cli("calibrate-camera", *paths, "--target", "checkerboard:9x6:0.03", "--model", "fisheye",
                   "--out", out)
    assert r.returncode == 0, r.stderr
    assert "fisheye dist" in r.stdout
    cam = load_camera_preset(out)
    truth = board_scene(FISHEYE, poses(0.3, 0, 0)[0]).camera
    assert cam.distortion_model == "fisheye" and len(cam.dist) == 4
    assert cam.fx == pytest.approx(truth.fx, rel=1e-2) and cam.fy == pytest.approx(truth.fy, rel=1e-2)
    assert abs(cam.cx - truth.cx) < 0.5 and abs(cam.cy - truth.cy) < 0.5
    cal = calibrate_sessions(paths, "checkerboard:9x6:0.03", model="fisheye")   # what the CLI ran
    assert cal.camera.dist == cam.dist
    assert covered_difference_px(truth, cal.camera, cal) < 0.3
    # the preset works in a scene, as a fisheye
    scene = load_scene("board", {"camera": {"preset": str(out)}})
    assert scene.camera.is_fisheye and scene.camera.dist == cam.dist
