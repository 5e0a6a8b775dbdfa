"""Board detection and pose from the twin's amplitude images: the pose solved from the
amplitude alone agrees with the board's pose in the scene (the truth the twin rendered)."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.depth import depth_from_raw
from tofhil.errors import TofhilError
from tofhil.targets import board_pose_from_amplitude, detect_board, to_8bit
from tofhil.sim.pipeline import simulate
from tofhil.sim.scene import load_scene


def board_scene(width: int, height: int, tilt=(0.0, 0.0, 0.0), distance: float = 0.6, spp: int = 16):
    """The bundled board scene at another resolution (same field of view) and pose."""
    f = 116.667 * width / 160
    return load_scene("board", {"params": {"tilt_x_deg": tilt[0], "tilt_y_deg": tilt[1], "roll_deg": tilt[2],
                                           "board_distance_m": distance},
                                "camera": {"width": width, "height": height, "fx": f, "fy": f,
                                           "cx": (width - 1) / 2, "cy": (height - 1) / 2},
                                "render": {"samples_per_pixel": spp}})


def true_board_to_camera(scene) -> np.ndarray:
    obj = scene.objects[scene.object_index("board")]
    return np.linalg.inv(scene.camera_pose) @ obj.pose @ obj.board.board_to_plane()


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error in mm, rotation error in degrees)."""
    dt = np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) * 1e3
    R = T_est[:3, :3].T @ T_true[:3, :3]
    return dt, float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("tilt, noise", [((20.0, -15.0, 5.0), True), ((0.0, 0.0, 0.0), False),
                                         ((-25.0, 10.0, -10.0), True)])
def test_checkerboard_pose_from_amplitude_within_1mm_and_0p1deg(tilt, noise):
    scene = board_scene(320, 240, tilt)
    frame = depth_from_raw(simulate(scene, noise=noise, seed=3)[0])
    pose = board_pose_from_amplitude(frame, scene.camera, scene.objects[0].board)
    dt, dr = pose_error(pose.board_to_camera, true_board_to_camera(scene))
    assert dt < 1.0 and dr < 0.1
    assert pose.detection.n == 8 * 5
    assert pose.rms_px < 0.05 and pose.errors_px.shape == (40,)


def test_detected_corners_are_where_the_true_pose_projects_them():
    scene = board_scene(160, 120, (10.0, 20.0, 0.0))
    frame = depth_from_raw(simulate(scene, noise=False)[0])
    det = detect_board(frame.amplitude, scene.objects[0].board)
    T = true_board_to_camera(scene)
    truth = scene.camera.project(det.object_points @ T[:3, :3].T + T[:3, 3])
    # the ids follow the board (not the detector's scan order): each corner near its truth
    assert np.abs(truth - det.image_points).max() < 0.15


def test_a_view_without_the_board_is_one_clear_error():
    scene = board_scene(80, 60, distance=0.6, spp=1)
    frame = depth_from_raw(simulate(scene, noise=False)[0])
    blank = np.full_like(frame.amplitude, 10.0)
    with pytest.raises(TofhilError, match="no checkerboard 9x6 board found"):
        board_pose_from_amplitude(blank, scene.camera, "checkerboard:9x6:0.03")


def test_to_8bit_ignores_hot_pixels_and_nan():
    img = np.tile(np.array([1.0, 2.0]), (50, 50))
    img[0, 0] = 1e6
    img[1, 1] = np.nan
    out = to_8bit(img)
    assert out.dtype == np.uint8 and out[0, 1] == 255 and out[0, 2] == 0 and out[1, 1] == 0
