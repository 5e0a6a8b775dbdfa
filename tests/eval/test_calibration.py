"""Camera calibration end to end on the twin's data: board views rendered with a known camera
(off-centre principal point, fx != fy, barrel distortion), written as sessions, calibrated by
``tofhil calibrate-camera`` into a preset that scenes read; the preset matches the truth."""

from __future__ import annotations

import json

import pytest

from tofhil.camera import load_camera_preset
from tofhil.eval.calibration.camera import calibrate_camera, max_model_difference_px
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene

W, H = 160, 120
F = 116.667 * 1.02
TRUE_CAMERA = {"width": W, "height": H, "fx": F, "fy": F * 0.995, "cx": (W - 1) / 2 + 2.3,
               "cy": (H - 1) / 2 - 1.7, "dist": [-0.15, 0.0, 0.0, 0.0, 0.0]}
#: (tilt x, tilt y, roll) in degrees, distance, x, y in m: the board fills different parts
#: of the view at different tilts (as one would wave it before a camera)
POSES = [(25, 0, 0, 0.5, 0, 0), (-25, 0, 0, 0.5, 0, 0), (0, 25, 0, 0.5, 0, 0), (0, -25, 0, 0.5, 0, 0),
         (15, 15, 10, 0.45, 0.05, 0.03), (-15, 20, -10, 0.55, -0.05, 0.02), (20, -20, 30, 0.5, 0.04, -0.04),
         (-20, -15, -25, 0.5, -0.04, -0.03), (0, 0, 0, 0.42, 0, 0)]


def board_view(pose, spp: int = 16):
    tx, ty, rz, d, x, y = pose
    return load_scene("board", {"params": {"tilt_x_deg": tx, "tilt_y_deg": ty, "roll_deg": rz,
                                           "board_distance_m": d, "board_x_m": x, "board_y_m": y},
                                "camera": TRUE_CAMERA, "render": {"samples_per_pixel": spp}})


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("boards")
    paths = []
    for i, pose in enumerate(POSES):
        paths.append(simulate_session(board_view(pose), root / f"view{i}.h5", frames=2, seed=i, noise=True))
    # a view where the board is out of sight: rejected, with the reason
    away = simulate_session(board_view((0, 0, 0, 0.5, 0.6, 0.0), spp=1), root / "away.h5", frames=1, seed=99)
    return paths, away


@pytest.mark.slow
def test_calibrate_camera_cli_recovers_the_twin_camera(sessions, tofhil_cli, tmp_path):
    paths, away = sessions
    out = tmp_path / "cam.yaml"
    report = tmp_path / "cal.json"
    r = tofhil_cli("calibrate-camera", *paths, away, "--target", "checkerboard:9x6:0.03", "--model", "k1",
                   "--out", out, "--report", report, "--name", "twin-cal")
    assert r.returncode == 0, r.stderr
    cam = load_camera_preset(out)
    truth = board_view(POSES[0]).camera
    # the tolerances: focal length 0.5 %, principal point 0.5 px, distortion's
    # effect 0.3 px over the image (all of the model: max distance between the two
    # cameras' images of the same ray)
    assert cam.fx == pytest.approx(truth.fx, rel=5e-3) and cam.fy == pytest.approx(truth.fy, rel=5e-3)
    assert abs(cam.cx - truth.cx) < 0.5 and abs(cam.cy - truth.cy) < 0.5
    assert cam.dist[0] == pytest.approx(-0.15, abs=0.01)
    assert max_model_difference_px(truth, cam) < 0.5
    assert cam.name == "twin-cal" and cam.extra["freq_hz"] == [44.0e6]  # the preset's facts kept
    views = json.loads(report.read_text())["views"]
    assert [v["used"] for v in views] == [True] * len(POSES) + [False]
    assert "no checkerboard 9x6 board found" in views[-1]["reason"]
    assert all(v["rms_px"] < 0.1 for v in views[:-1])
    assert "rejected: no checkerboard" in r.stdout
    # the preset works in a scene
    scene = load_scene("board", {"camera": {"preset": str(out)}})
    assert scene.camera.fx == cam.fx


def test_refuses_to_overwrite_and_too_few_views(sessions, tofhil_cli, tmp_path):
    paths, away = sessions
    out = tmp_path / "cam.yaml"
    out.write_text("keep")
    r = tofhil_cli("calibrate-camera", paths[0], "--target", "checkerboard:9x6:0.03", "--out", out)
    assert r.returncode == 2 and "already exists" in r.stderr and out.read_text() == "keep"
    new = tmp_path / "new.yaml"
    r = tofhil_cli("calibrate-camera", paths[0], paths[1], away, "--target", "checkerboard:9x6:0.03", "--out", new)
    assert r.returncode == 2 and "only 2 usable views of 3" in r.stderr and not new.exists()
    r = tofhil_cli("calibrate-camera", paths[0], "--target", "checkerboard:6x6:0.03", "--out", new)
    assert r.returncode == 2 and "--target.grid" in r.stderr and r.stderr.count("\n") == 1


@pytest.mark.slow
def test_an_outlier_view_is_rejected_with_its_error():
    """A view that no single camera explains with the others (here: seen through a lens of
    strong pincushion distortion) is rejected as an outlier; the rest are kept."""
    from tofhil.depth import depth_from_raw
    from tofhil.sim.pipeline import simulate

    images = [(f"v{i}", depth_from_raw(simulate(board_view(pose), noise=False)[0]).amplitude)
              for i, pose in enumerate(POSES[:6])]
    odd = load_scene("board", {"params": {"tilt_x_deg": 10, "tilt_y_deg": -20, "roll_deg": 15,
                                          "board_distance_m": 0.45},
                               "camera": dict(TRUE_CAMERA, dist=[0.8, 0, 0, 0, 0]),
                               "render": {"samples_per_pixel": 16}})
    images.append(("odd", depth_from_raw(simulate(odd, noise=False)[0]).amplitude))
    cal = calibrate_camera(images, "checkerboard:9x6:0.03", base=odd.camera, model="k1", max_view_error_px=0.2)
    rejected = [v for v in cal.views if not v.used]
    assert [v.name for v in rejected] == ["odd"] and "outlier" in rejected[0].reason
    assert len(cal.used) == 6 and cal.rms_px < 0.1
