"""Colouring ToF points from a colour camera beside it: colours land where the colour camera
sees each point, and points hidden from the colour camera by a nearer object are occluded."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.eval.rgb.colorize import colorize_points, write_ply
from tests.real_data import AZURE_KINECT_MKV, need


def scene_points() -> tuple[np.ndarray, np.ndarray]:
    """A wall at z = 1 m (x, y in [-0.5, 0.5]) and a 0.1 m square card at z = 0.5 m in front
    of its centre, sampled every 5 mm; returns points and which are on the card."""
    g = np.arange(-0.5, 0.5 + 1e-9, 0.005)
    X, Y = np.meshgrid(g, g)
    wall = np.stack([X.ravel(), Y.ravel(), np.ones(X.size)], axis=1)
    c = np.arange(-0.05, 0.05 + 1e-9, 0.005)
    CX, CY = np.meshgrid(c, c)
    card = np.stack([CX.ravel(), CY.ravel(), np.full(CX.size, 0.5)], axis=1)
    return np.concatenate([wall, card]), np.r_[np.zeros(len(wall), bool), np.ones(len(card), bool)]


def test_colours_follow_the_colour_camera_and_occlusion_hides_the_wall_behind_the_card():
    pts, on_card = scene_points()
    # colour camera 0.1 m to the right of the ToF camera (x_color = x_tof - 0.1)
    T = np.eye(4)
    T[0, 3] = -0.1
    cam = CameraModel(width=400, height=400, fx=300.0, fy=300.0, cx=199.5, cy=199.5)
    # the colour image: red where the card is, the wall's colour encodes its x (green ramp)
    v, u = np.mgrid[0:400, 0:400].astype(np.float64)
    rays = cam.pixel_rays(u, v)
    t_card = 0.5 / rays[..., 2]
    # in colour-camera coordinates the card is centred at x = -0.1
    hit_card = (np.abs(rays[..., 0] * t_card + 0.1) <= 0.05) & (np.abs(rays[..., 1] * t_card) <= 0.05)
    wall_x_tof = rays[..., 0] / rays[..., 2] * 1.0 + 0.1
    rgb = np.zeros((400, 400, 3), np.uint8)
    rgb[..., 1] = np.clip(np.round((wall_x_tof + 0.5) * 200), 0, 255).astype(np.uint8)
    rgb[hit_card] = [255, 0, 0]
    res = colorize_points(pts, T, cam, rgb, splat_px=2)
    # every card point is seen; those away from its edge (bilinear colours mix there) are red
    inner = on_card & (np.abs(pts[:, 0]) < 0.04) & (np.abs(pts[:, 1]) < 0.04)
    assert res.visible[on_card].all() and np.all(res.colors[inner] == [255, 0, 0])
    # wall points behind the card as the colour camera sees it (the card's shadow on the wall
    # from the colour camera's centre at x = +0.1: wall x in [-0.1 - ..., ...]): occluded
    wall = ~on_card
    # a wall point is hidden when the ray from the colour camera (x = 0.1) to it crosses the card
    xw, yw = pts[:, 0], pts[:, 1]
    xc = 0.1 + (xw - 0.1) * 0.5          # where that ray is at z = 0.5
    yc = yw * 0.5
    hidden = wall & (np.abs(xc) < 0.05 - 0.01) & (np.abs(yc) < 0.05 - 0.01)
    seen = wall & ((np.abs(xc) > 0.05 + 0.01) | (np.abs(yc) > 0.05 + 0.01))
    in_view = np.all(np.isfinite(res.uv), axis=1) & (np.abs(res.uv - 199.5) < 199).all(axis=1)
    assert res.occluded[hidden].all() and not res.visible[hidden].any()
    assert res.visible[seen & in_view].all()
    # a seen wall point takes the wall colour of its own x (the green ramp), not the card's
    g = res.colors[seen & in_view, 1].astype(float)
    expect = np.clip((xw[seen & in_view] + 0.5) * 200, 0, 255)
    assert np.abs(g - expect).max() <= 2 and np.all(res.colors[seen & in_view, 0] == 0)


def test_ply_is_readable_by_open3d(tmp_path):
    from tofhil.open3d_loader import open3d

    pts = np.array([[0.0, 0.0, 1.0], [0.1, 0.2, 1.5]])
    cols = np.array([[255, 0, 0], [0, 128, 255]], np.uint8)
    cloud = open3d().io.read_point_cloud(str(write_ply(tmp_path / "c.ply", pts, cols)))
    assert np.allclose(np.asarray(cloud.points), pts, atol=1e-6)
    assert np.allclose(np.asarray(cloud.colors) * 255, cols, atol=0.5)


def test_kinect_colour_lands_on_the_depth_with_the_factory_calibration():
    """The real recording: colour from the factory calibration. Most depth points are seen
    by the colour camera, and the wall beside the mug that the colour camera (32 mm to the
    side) cannot see is occluded."""
    from tofhil.drivers.importers.k4a_color import read_depth_with_color

    inp = read_depth_with_color(need(AZURE_KINECT_MKV))
    assert inp.rgb.shape == (720, 1280, 3)
    res = colorize_points(inp.points(), inp.tof_to_color, inp.color_camera, inp.rgb)
    assert res.visible.mean() > 0.9 and res.occluded.sum() > 1000


def test_colorize_cli_writes_the_visible_points_and_refuses_to_overwrite(tofhil_cli, tmp_path):
    from tofhil.open3d_loader import open3d

    path = need(AZURE_KINECT_MKV)
    out = tmp_path / "mug.ply"
    r = tofhil_cli("colorize", path, "--out", out, "--report", tmp_path / "rep")
    assert r.returncode == 0, r.stderr
    coloured = int(r.stdout.split(" of ")[0])
    cloud = open3d().io.read_point_cloud(str(out))
    assert len(cloud.points) == coloured > 200_000 and np.asarray(cloud.colors).max() > 0.5
    # the report: the edge misalignment with its self-check, and both figures
    import json

    rep = json.loads((tmp_path / "rep" / "colorize.json").read_text())["edge_alignment"]
    assert rep["self_check_passed"] and "misalignment at depth edges" in r.stdout
    html = (tmp_path / "rep" / "colorize.html").read_text()
    assert html.count("data:image/png;base64,") == 2
    r = tofhil_cli("colorize", path, "--out", out)
    assert r.returncode == 2 and "already exists" in r.stderr
    r = tofhil_cli("colorize", path, "--out", tmp_path / "x.ply", "--frame", "5")
    assert r.returncode == 2 and "COLOR" in r.stderr and not (tmp_path / "x.ply").exists()


def test_colorize_reads_a_session_with_an_rgb_group(tofhil_cli, tmp_path):
    """A twin session of the room with a second camera 40 mm to the right (its true extrinsics in
    the rgb/ group): colorize reads it directly, and the misalignment it measures at the boxes'
    left silhouettes is zero within a fraction of a pixel; a 5 mm wrong baseline shows as the
    predicted shift (the silhouettes re-projected with the wrong baseline). The right silhouettes are not
    compared: the colour camera, to the right, sees the boxes' right faces that the ToF camera
    does not, so its silhouette there is another physical edge (the face's far edge)."""
    import json

    from tofhil.eval.rgb.colorize import session_inputs
    from tofhil.eval.rgb.edge_alignment import edge_alignment
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import load_scene

    block = {"params": {"width_px": 80, "height_px": 60, "pitch_deg": -20.0},
             "rgb_camera": {"width": 160, "height": 120, "hfov_deg": 80.0, "samples": 3,
                            "pose": {"position": [0.04, 0.0, 0.0]}}}
    s = simulate_session(load_scene("room", block), tmp_path / "s.h5", frames=1)
    r = tofhil_cli("colorize", s, "--out", tmp_path / "c.ply", "--report", tmp_path / "rep")
    assert r.returncode == 0, r.stderr
    coloured, total = (int(x) for x in r.stdout.split(" depth points")[0].split(" of "))
    assert coloured > 0.8 * total
    edges = json.loads((tmp_path / "rep" / "colorize.json").read_text())["edge_alignment"]
    assert edges["left"]["n"] >= 15 and abs(edges["left"]["median_px"]) < 0.3, edges
    assert edges["right"]["median_px"] < -3.0     # the far edge of the right faces, 5-10 px left of it
    inp = session_inputs(s, 0)
    wrong = inp.tof_to_color.copy()
    wrong[0, 3] += 0.02
    e0 = edge_alignment(inp.z_m, inp.valid, inp.pixel_to_ray, inp.tof_to_color, inp.color_camera, inp.rgb)
    e = edge_alignment(inp.z_m, inp.valid, inp.pixel_to_ray, wrong, inp.color_camera, inp.rgb)
    left = e0.side < 0
    predicted = -np.median(e.depth_edges_uv[left, 0] - e0.depth_edges_uv[left, 0])
    assert e0.left.median_px == pytest.approx(edges["left"]["median_px"])
    assert e.left.median_px - e0.left.median_px == pytest.approx(predicted, abs=0.3)
