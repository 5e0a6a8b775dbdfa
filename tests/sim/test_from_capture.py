"""scene-from-capture: a twin scene built from a capture's depth and amplitude.

Synthetic: a session rendered by the twin from a known wall (distance, tilt, beam profile
cos^2) is turned back into a scene; the plane's pose, the beam exponent and the amplitude
must come back (independent truth: the scene the session was rendered from). Real: the ADI
near-plane capture (binned 4 x 4 to keep the test fast) gives a scene that loads, simulates,
puts its plane where an independent SVD plane fit of the cloud puts it, and names what it
cannot observe.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from tofhil.errors import TofhilError
from tofhil.frames import DepthFrame
from tofhil.session import SessionWriter, open_session
from tofhil.sim.from_capture import grid_mesh, read_capture_metadata, scene_from_capture
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene
from tests.real_data import ADI, CAPTURES, need


@pytest.fixture(scope="module")
def wall_session(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wall")
    # emitter at the lens centre: an offset emitter bends the apparent surface (the path is
    # emitter -> wall -> lens), which a plane fit would rightly report as a small tilt
    scene = load_scene("wall", overrides={"emitter": {"offset_m": [0.0, 0.0, 0.0]}, "objects": [{"name": "wall", "type": "plane", "size": [4.0, 3.0],
                                                       "material": "wall",
                                                       "pose": {"position": [0.0, 0.0, 1.2],
                                                                "rotation_deg": [10.0, 0.0, 0.0]}}]})
    scene = dataclasses.replace(scene, camera=scene.camera.scaled(0.5))
    path = tmp / "wall.h5"
    simulate_session(scene, path, frames=1, noise=False)
    return scene, path


def test_wall_comes_back_with_its_pose_beam_and_amplitude(wall_session, tmp_path):
    scene, path = wall_session
    res = scene_from_capture(path, tmp_path / "twin.yaml")
    assert len(res.planes) == 1
    p = res.planes[0]
    # the wall: local z tilted 10 deg about x, through (0, 0, 1.2)
    t = math.radians(10.0)
    n_true = np.array([0.0, -math.sin(t), math.cos(t)])
    if p.normal @ n_true < 0:
        n_true = -n_true
    assert math.degrees(math.acos(min(1.0, float(p.normal @ n_true)))) < 0.2
    assert p.offset_m == pytest.approx(float(n_true @ np.array([0.0, 0.0, 1.2])), abs=0.002)
    rad = res.metadata["radiometry"]
    # beam cos^2 (the wall scene's emitter), fitted from the amplitude's fall-off over the wall
    assert rad["beam_exponent_n"] == pytest.approx(2.0, abs=0.3)
    # the fitted scene renders the session's amplitude (one object: its ratio is 1 by fit,
    # the spread over the wall says the fall-off is right)
    assert rad["log_amplitude_residual_mad"] < 0.02
    twin = load_scene(res.scene_path)
    assert twin.sensor.freq_hz == tuple(scene.sensor.freq_hz)  # from the session's raw taps
    assert "range_offset" in read_capture_metadata(res.scene_path)["unobservable"]


def test_refuses_to_overwrite_and_asks_for_a_frequency(wall_session, tmp_path):
    _, path = wall_session
    out = tmp_path / "twin.yaml"
    scene_from_capture(path, out)
    with pytest.raises(TofhilError, match="refusing to overwrite"):
        scene_from_capture(path, out)
    # a depth-only session records no frequency: the option is named
    with open_session(path) as s:
        d = s.depth_frame(0)
        cam = s.camera
    depth_only = tmp_path / "d.h5"
    with SessionWriter(depth_only, cam) as w:
        w.append(depth=d)
    with pytest.raises(TofhilError, match="--freq-hz"):
        scene_from_capture(depth_only, tmp_path / "x.yaml")
    assert not (tmp_path / "x.yaml").exists()


def test_grid_mesh_joins_neighbours_and_not_depth_steps():
    h, w = 10, 12
    pts = np.zeros((h, w, 3))
    v, u = np.mgrid[0:h, 0:w].astype(float)
    pts[..., 0], pts[..., 1], pts[..., 2] = 0.01 * u, 0.01 * v, 1.0
    pts[:, 6:, 2] = 2.0  # a step half way across
    verts, tris = grid_mesh(pts, np.ones((h, w), bool), stride=1)
    # (h-1) x (w-1) quads of 2 triangles, less the column of quads across the step
    assert len(tris) == 2 * (h - 1) * (w - 1) - 2 * (h - 1)


@pytest.fixture(scope="module")
def near_plane_small(tmp_path_factory):
    """The ADI near-plane capture, imported and binned 4 x 4 (128 x 128)."""
    from tofhil.drivers.importers.dispatch import import_file

    tmp = tmp_path_factory.mktemp("adi")
    full = import_file(need(ADI / "near_plane_depth.bin"), tmp / "full.h5").out
    with open_session(full) as s:
        d = s.depth_frame(0)
        cam = s.camera.scaled(0.25)
    b = 4
    small = tmp / "small.h5"
    with SessionWriter(small, cam, device={"model": "binned ADI near plane"}) as w:
        w.append(depth=DepthFrame(distance_m=np.asarray(d.radial_m)[1::b, 1::b], kind="radial", camera=cam,
                                  amplitude=np.asarray(d.amplitude)[1::b, 1::b], valid=d.valid[1::b, 1::b]))
    return small


def test_real_near_plane_scene_loads_simulates_and_sits_on_the_cloud(near_plane_small, tmp_path):
    near = CAPTURES["near"]
    res = scene_from_capture(near_plane_small, tmp_path / "np.yaml", freq_hz=[near.freq_hz],
                             wavelength_m=near.wavelength_m)
    assert res.planes, "the near-plane capture shows a plane"
    with open_session(near_plane_small) as s:
        d = s.depth_frame(0)
        cam = s.camera
    # independent check: an SVD plane through the cloud's central pixels
    p = res.planes[0]
    pts = cam.points(np.asarray(d.radial_m), valid=p.pixels & d.valid)
    c = pts.mean(axis=0)
    n = np.linalg.svd(pts - c, full_matrices=False)[2][2]
    n = n if n @ p.normal > 0 else -n
    assert math.degrees(math.acos(min(1.0, float(n @ p.normal)))) < 1.0
    assert float(p.normal @ c) == pytest.approx(p.offset_m, abs=0.003)
    meta = json.loads(res.metadata_path.read_text())
    assert set(meta["unobservable"]) >= {"range_offset", "pose"}
    # the scene loads and simulates; on the plane's pixels its depth is the capture's
    twin = load_scene(res.scene_path)
    out = simulate_session(twin, tmp_path / "twin.h5", frames=1, noise=False)
    with open_session(out) as s:
        t = s.depth_frame(0)
    m = p.pixels & d.valid & t.valid
    assert np.median(np.abs(np.asarray(t.radial_m)[m] - np.asarray(d.radial_m)[m])) < 0.004


def test_cli_writes_the_scene_and_refuses_bad_input_in_one_line(wall_session, tmp_path, tofhil_cli):
    _, path = wall_session
    out = tmp_path / "cli.yaml"
    r = tofhil_cli("scene-from-capture", path, "--out", out, "--max-planes", "2")
    assert r.returncode == 0, r.stderr
    assert out.is_file() and (tmp_path / "cli.capture.json").is_file() and (tmp_path / "cli_valid.npy").is_file()
    assert "range_offset" in r.stdout
    for args, field in ((["--target", "charuco"], "--target"), (["--freq-hz", "abc"], "--freq-hz")):
        r = tofhil_cli("scene-from-capture", path, "--out", tmp_path / "bad.yaml", *args)
        assert r.returncode == 2 and field in r.stderr and "Traceback" not in r.stderr
        assert not (tmp_path / "bad.yaml").exists()
