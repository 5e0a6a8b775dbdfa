"""scene-from-capture --target: a board's pose from the amplitude image makes a range offset observable.

A depth (+ amplitude) session rendered by the twin from the bundled ``board`` scene (tilted,
with a hidden range offset of 20 mm) is turned into a scene with and without the target.
Independent truth: the scene the session was rendered from (the board's pose) and the hidden
offset. With the target the board's pose comes back within 1 mm and 0.1 degree and the
diagnosis names the range offset at its size; without it the offset is reported unobservable
(the planes' poses, fitted to the same depth, absorb it) and not named.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tofhil.frames import DepthFrame
from tofhil.session import SessionWriter, open_session
from tofhil.sim.from_capture import scene_from_capture
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene

PATH_M = 0.04  # optical path: the radial distance reads 20 mm farther
TARGET = "checkerboard:9x6:0.03"
OVERRIDES = {"params": {"tilt_x_deg": 20.0, "tilt_y_deg": -10.0, "board_distance_m": 0.55},
             "emitter": {"offset_m": [0.0, 0.0, 0.0]}, "render": {"samples_per_pixel": 16},
             "sensor": {"integration_time_s": 1.0e-3}}


@pytest.fixture(scope="module")
def board_capture(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("board")
    scene = load_scene("board", overrides=OVERRIDES | {"effects": {"range_offset": {"path_m": PATH_M}}})
    simulate_session(scene, tmp / "raw.h5", frames=1, seed=3, noise=True)
    with open_session(tmp / "raw.h5") as s:
        d, cam = s.depth_frame(0), s.camera
    path = tmp / "depth.h5"  # what a depth camera delivers: depth and amplitude, no taps, no frequency
    with SessionWriter(path, cam) as w:
        w.append(depth=DepthFrame(distance_m=np.asarray(d.radial_m), kind="radial", camera=cam,
                                  amplitude=np.asarray(d.amplitude), valid=d.valid))
    board = next(o for o in scene.objects if o.name == "board")
    truth = np.asarray(board.pose) @ board.board.board_to_plane()
    with_target = scene_from_capture(path, tmp / "with.yaml", freq_hz=[44e6], wavelength_m=850e-9, target=TARGET)
    return path, truth, with_target, tmp


def test_board_pose_from_amplitude_within_1_mm_and_0_1_deg(board_capture):
    _, truth, res, _ = board_capture
    est = np.asarray(res.metadata["target"]["board_to_camera"])
    assert np.linalg.norm(est[:3, 3] - truth[:3, 3]) < 1e-3
    r = est[:3, :3].T @ truth[:3, :3]
    assert math.degrees(math.acos(min(1.0, (np.trace(r) - 1) / 2))) < 0.1
    # the pose did not come from the depth: the depth reads 20 mm farther than the board is
    assert res.metadata["unobservable"] == {} and not res.metadata["geometry_from_depth"]
    twin = load_scene(res.scene_path)
    assert any(o.type == "board" for o in twin.objects)


@pytest.mark.slow
def test_range_offset_named_with_target_and_unobservable_without(board_capture):
    from tofhil.eval.diagnose.run import diagnose

    path, _, with_target, tmp = board_capture
    without = scene_from_capture(path, tmp / "without.yaml", freq_hz=[44e6], wavelength_m=850e-9)
    kw = dict(candidates=["range_offset", "wiggling", "amplitude_dependent"], max_effects=1)
    res = diagnose(path, load_scene(with_target.scene_path), **kw)
    assert res.causes == ["range_offset"]
    assert res.params["range_offset"]["path_m"] == pytest.approx(PATH_M, abs=0.004)
    res0 = diagnose(path, load_scene(without.scene_path), **kw)
    assert "range_offset" not in res0.causes and "range_offset" not in {c["effect"] for c in res0.ranked}
    assert "range_offset" in res0.observability.unobservable
    assert json.loads(without.metadata_path.read_text())["unobservable"].get("range_offset")


def test_a_board_that_does_not_fit_its_spec_is_refused(board_capture, tmp_path):
    from tofhil.errors import TofhilError

    path = board_capture[0]
    # a 7x4 spec finds part of the 9x6 board; its corners do not reproject: refused, nothing written
    with pytest.raises(TofhilError, match="--target"):
        scene_from_capture(path, tmp_path / "x.yaml", freq_hz=[44e6], wavelength_m=850e-9,
                           target="checkerboard:7x4:0.03")
    assert not list(tmp_path.iterdir())
