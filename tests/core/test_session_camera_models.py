"""The session's camera JSON carries the lens model: rational and fisheye cameras round-trip,
files without ``model`` (older tofhil, other tools) read as plumb_bob, a bad one is refused."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.frames import DepthFrame
from tofhil.session import SessionWriter, open_session

RATIONAL = CameraModel(16, 12, 10.0, 10.1, 7.6, 5.4, distortion_model="rational", name="wide",
                       dist=(0.548, -0.021, 2e-5, -7e-5, -0.0027, 0.89, 0.086, -0.0139, 1e-3, -2e-4, 3e-4, -1e-4))
FISHEYE = CameraModel(16, 12, 6.0, 6.0, 7.5, 5.5, distortion_model="fisheye", dist=(-0.0134, 0.0352, -0.0281, 0.0079))


def write(path, cam: CameraModel) -> None:
    with SessionWriter(path, cam, device={"model": "unit"}) as w:
        w.append(depth=DepthFrame(distance_m=np.full(cam.shape, 1.5, np.float32), kind="radial", camera=cam,
                                  amplitude=np.ones(cam.shape, np.float32)))


@pytest.mark.parametrize("cam", [RATIONAL, FISHEYE], ids=["rational", "fisheye"])
def test_camera_model_round_trips_through_the_session(tmp_path, cam):
    path = tmp_path / "s.h5"
    write(path, cam)
    with h5py.File(path, "r") as f:
        stored = json.loads(f.attrs["camera"])
    assert stored["model"] == cam.distortion_model and stored["dist"] == list(cam.dist)
    with open_session(path) as s:
        assert s.camera == cam
        np.testing.assert_array_equal(s.camera.rays, cam.rays)
        assert s.summary()["camera"]["model"] == cam.distortion_model


def test_camera_without_model_reads_as_plumb_bob(tmp_path):
    path = tmp_path / "old.h5"
    cam = CameraModel(16, 12, 10.0, 10.0, 7.5, 5.5, dist=(0.01, 0.0, 0.0, 0.0, 0.0))
    write(path, cam)
    with h5py.File(path, "r+") as f:                  # as tofhil wrote it before the field existed
        old = json.loads(f.attrs["camera"])
        del old["model"]
        f.attrs["camera"] = json.dumps(old)
    with open_session(path) as s:
        assert s.camera.distortion_model == "plumb_bob" and s.camera == cam


def test_bad_model_in_a_session_names_the_field(tmp_path):
    path = tmp_path / "bad.h5"
    write(path, FISHEYE)
    with h5py.File(path, "r+") as f:
        d = json.loads(f.attrs["camera"])
        f.attrs["camera"] = json.dumps(d | {"model": "kannala"})
    with pytest.raises(InputFileError, match=r"bad\.h5: field 'model': got 'kannala' \(expected one of 'plumb_bob'"):
        open_session(path)
    with h5py.File(path, "r+") as f:
        f.attrs["camera"] = json.dumps(d | {"dist": [0.0] * 5})
    with pytest.raises(InputFileError, match=r"field 'dist'.*for model 'fisheye'"):
        open_session(path)
