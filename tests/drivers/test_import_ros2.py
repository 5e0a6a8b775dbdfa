"""ROS 2 bags (MCAP) in and out: round trips from a twin session, z vs radial, the camera from
CameraInfo, pairing by stamp, finding topics, hostile bags, and ``tofhil export``.

Test bags are written with the same libraries a ROS 2 recording is read with (mcap and
mcap-ros2-support, CDR with ros2msg schemas, as rosbag2 writes them).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.drivers.importers import ros2
from tofhil.drivers.importers.dispatch import detect_format, import_file
from tofhil.errors import InputFileError
from tofhil.session import open_session

from tests.conftest import run_tofhil

DEFS = {ros2.IMAGE: ros2.IMAGE_DEF, ros2.CAMERA_INFO: ros2.CAMERA_INFO_DEF}
PERIOD_NS = 33_333_333  # 30 frames/s


# --------------------------------------------------------------------------- writing test bags
def header(stamp_ns: int, frame_id: str = "tof_optical") -> dict:
    return {"stamp": {"sec": stamp_ns // 10 ** 9, "nanosec": stamp_ns % 10 ** 9}, "frame_id": frame_id}


def image(stamp_ns: int, arr: np.ndarray, encoding: str, *, frame_id: str = "tof_optical", big: bool = False,
          data: bytes | None = None) -> dict:
    a = np.ascontiguousarray(arr)
    a = a.astype(a.dtype.newbyteorder(">" if big else "<"))
    h, w = a.shape[:2]
    step = a.strides[0]
    return {"header": header(stamp_ns, frame_id), "height": h, "width": w, "encoding": encoding,
            "is_bigendian": int(big), "step": step, "data": a.tobytes() if data is None else data}


def info(stamp_ns: int, cam: CameraModel, *, model: str | None = None, d: list[float] | None = None,
         frame_id: str = "tof_optical") -> dict:
    """The CameraInfo tofhil's export writes for ``cam``, with ``model`` / ``d`` replaced if given."""
    msg = ros2.camera_info_message(cam, stamp_ns, frame_id)
    if model is not None:
        msg["distortion_model"] = model
    msg["d"] = list(cam.dist) if d is None else d
    return msg


def write_bag(path: Path, messages: list[tuple[str, str, dict]], metadata: dict | None = None) -> Path:
    """``(topic, type, message)`` in order; log time = the header stamp. Small chunks (32 KiB),
    so that a cut file keeps complete chunks, as a long recording does."""
    from mcap_ros2.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=32 * 1024)
        schemas = {t: w.register_msgdef(t, d) for t, d in DEFS.items()}
        for topic, kind, msg in messages:
            st = msg["header"]["stamp"]
            t = st["sec"] * 10 ** 9 + st["nanosec"]
            w.write_message(topic, schemas[kind], msg, log_time=t, publish_time=t)
        if metadata:
            w.add_metadata("tofhil", metadata)
        w.finish()
    return path


def camera(dist=(-0.21, 0.06, 1.2e-3, -6e-4, -0.01)) -> CameraModel:
    return CameraModel(width=64, height=48, fx=52.0, fy=51.5, cx=31.7, cy=23.2, dist=dist, name="test_tof")


def plane_bag(path: Path, cam: CameraModel, z_m: float = 1.25, n: int = 3, encoding: str = "32FC1",
              model: str | None = None, d: list[float] | None = None, with_info: bool = True,
              depth_topic: str = "/tof/depth/image_raw", depth_encoding_override: str | None = None) -> Path:
    """A plane facing the camera at ``z_m``: ROS z-depth, IR amplitude, CameraInfo."""
    h, w = cam.shape
    z = np.full((h, w), z_m, np.float32)
    if encoding == "16UC1":
        z = np.full((h, w), round(z_m * 1000), np.uint16)
    amp = (np.arange(h * w, dtype=np.uint16).reshape(h, w) % 4000) + 100
    msgs = []
    for i in range(n):
        t = 1_700_000_000 * 10 ** 9 + i * PERIOD_NS
        if with_info:
            msgs.append(("/tof/depth/camera_info", ros2.CAMERA_INFO, info(t, cam, model=model, d=d)))
        msgs.append((depth_topic, ros2.IMAGE, image(t, z, depth_encoding_override or encoding)))
        msgs.append(("/tof/ir/image_raw", ros2.IMAGE, image(t, amp, "mono16")))
    return write_bag(path, msgs)


# --------------------------------------------------------------------------- a twin session
@pytest.fixture(scope="module")
def twin_session(tmp_path_factory) -> Path:
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import load_scene

    return simulate_session(load_scene("wall"), tmp_path_factory.mktemp("twin") / "wall.h5", frames=3, seed=4)


def test_twin_session_round_trip_is_bit_exact_in_32fc1_metres(twin_session, tmp_path):
    bag = ros2.write_session_mcap(twin_session, tmp_path / "wall.mcap").out
    assert detect_format(bag) == "ros2-mcap"
    res = import_file(bag, tmp_path / "back.h5")
    assert res.format == "ros2-mcap" and res.n_frames == 3 and not res.notes
    with open_session(twin_session) as a, open_session(res.out) as b:
        assert b.camera == a.camera and b.camera.pixel_pitch_m == a.camera.pixel_pitch_m
        assert b.device["depth_kind_in_file"] == "radial" and b.device["topics"]["depth"] == "/tofhil/depth/radial"
        for i in range(3):
            da, db = a.depth_frame(i), b.depth_frame(i)
            np.testing.assert_array_equal(db.valid, da.valid)
            assert np.array_equal(db.radial_m[da.valid], da.radial_m[da.valid])  # bit for bit
            assert np.array_equal(db.amplitude, da.amplitude)
            assert (db.timestamp_s, db.sequence) == (da.timestamp_s, da.sequence)


def test_twin_session_as_z_depth_comes_back_radial(twin_session, tmp_path):
    """``--depth-kind z`` writes ROS's convention; the import converts back with the camera's rays."""
    bag = ros2.write_session_mcap(twin_session, tmp_path / "z.mcap", depth_kind="z").out
    res = import_file(bag, tmp_path / "z.h5")
    with open_session(twin_session) as a, open_session(res.out) as b:
        assert b.device["depth_kind_in_file"] == "z"
        da, db = a.depth_frame(1), b.depth_frame(1)
        np.testing.assert_array_equal(db.valid, da.valid)
        np.testing.assert_allclose(db.radial_m[da.valid], da.radial_m[da.valid], rtol=3e-7)  # float32 rounding


def test_16uc1_millimetres_round_trip_within_half_a_millimetre(twin_session, tmp_path):
    """A bag as a ROS camera driver writes it: z in uint16 mm, IR mono16, the camera's CameraInfo."""
    msgs = []
    with open_session(twin_session) as s:
        cam = s.camera
        truth = [s.depth_frame(i) for i in range(s.n_frames)]
    for i, d in enumerate(truth):
        t = 10 ** 9 + i * PERIOD_NS
        z_mm = np.where(d.valid, np.round(d.z_m * 1000), 0).astype(np.uint16)
        msgs += [("/cam/depth/camera_info", ros2.CAMERA_INFO, info(t, cam)),
                 ("/cam/depth/image_raw", ros2.IMAGE, image(t, z_mm, "16UC1")),
                 ("/cam/ir/image_raw", ros2.IMAGE, image(t, np.round(d.amplitude).astype(np.uint16), "mono16"))]
    res = import_file(write_bag(tmp_path / "mm.mcap", msgs), tmp_path / "mm.h5")
    with open_session(res.out) as b:
        assert b.device["depth_kind_in_file"] == "z" and b.device["depth_unit_in_file"] == "mm"
        for i, d in enumerate(truth):
            got = b.depth_frame(i)
            v = d.valid
            np.testing.assert_array_equal(got.valid, v)
            assert np.abs(got.z_m[v] - d.z_m[v]).max() <= 0.5e-3 + 1e-6       # z rounded to the millimetre
            assert np.abs(got.radial_m[v] - d.radial_m[v]).max() <= 0.5e-3 / cam.ray_z.min() + 1e-6
            np.testing.assert_array_equal(got.amplitude, np.round(d.amplitude))
            assert got.timestamp_s == pytest.approx(1.0 + i * PERIOD_NS * 1e-9, abs=1e-9)


# --------------------------------------------------------------------------- z vs radial, camera
def _expected_radial(cam: CameraModel, z_m: float) -> np.ndarray:
    """z along the axis -> radial: z |(x, y, 1)| with (x, y) from OpenCV's own undistortion."""
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    pts = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    xy = cv2.undistortPoints(pts, cam.K, np.array(cam.dist),
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))[:, 0, :]
    return (z_m * np.sqrt(1 + xy[:, 0] ** 2 + xy[:, 1] ** 2)).reshape(cam.shape)


def test_z_depth_of_a_plane_becomes_radial_by_the_closed_form(tmp_path):
    cam = camera()
    res = import_file(plane_bag(tmp_path / "p.mcap", cam, z_m=1.25), tmp_path / "p.h5")
    assert res.camera.dist == cam.dist and (res.camera.fx, res.camera.cy) == (cam.fx, cam.cy)
    with open_session(res.out) as s:
        d = s.depth_frame(0)
        assert s.device["depth_kind_in_file"] == "z" and "REP 118" in s.device["depth_kind_source"]
        assert d.valid.all()
        np.testing.assert_allclose(d.radial_m, _expected_radial(cam, 1.25), atol=2e-6)
        np.testing.assert_allclose(d.points()[:, 2], 1.25, atol=2e-6)   # the points lie on the plane
        assert d.radial_m.max() > 1.25 * 1.2                               # corners: far from z
    # told that the images hold radial distance, the values are stored as they are
    res = import_file(tmp_path / "p.mcap", tmp_path / "r.h5", depth_kind="radial")
    with open_session(res.out) as s:
        assert np.array_equal(s.depth_frame(0).radial_m, np.full(cam.shape, 1.25, np.float32))
        assert s.device["depth_kind_in_file"] == "radial"


def test_rational_model_with_zero_k4_k6_is_plumb_bob_exactly(tmp_path):
    cam = camera()
    d = list(cam.dist) + [0.0, 0.0, 0.0]
    res = import_file(plane_bag(tmp_path / "r.mcap", cam, model="rational_polynomial", d=d), tmp_path / "r.h5")
    assert res.camera.dist == cam.dist
    d14 = list(cam.dist) + [0.0] * 9   # OpenCV's 14-coefficient form, thin prism and tilt all zero
    assert ros2.lens_from_camera_info("rational_polynomial", d14, source="x") == ("plumb_bob", cam.dist)


RATIONAL = (0.52, -2.60, 1.2e-4, -6e-5, 1.45, 0.40, -2.43, 1.38)  # an Azure Kinect NFOV-like lens
def wide_camera(kind: str) -> CameraModel:
    """A lens beyond the 5-parameter model: OpenCV's rational (+ thin prism) or fisheye."""
    if kind == "rational":
        return dataclasses.replace(camera(), dist=RATIONAL, distortion_model="rational")
    if kind == "thin_prism":
        return dataclasses.replace(camera(), dist=RATIONAL + (1e-3, -2e-4, 5e-4, 1e-4), distortion_model="rational")
    return dataclasses.replace(camera(), dist=(0.1, -0.02, 0.003, -4e-4), distortion_model="fisheye")


def _expected_radial_cv(cam: CameraModel, z_m: float) -> np.ndarray:
    """z along the axis -> radial, with OpenCV's own undistortion for the camera's model."""
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    pts = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    if cam.distortion_model == "fisheye":
        xy = cv2.fisheye.undistortPoints(pts, cam.K, np.array(cam.dist), criteria=crit)[:, 0, :]
    else:
        xy = cv2.undistortPoints(pts, cam.K, np.array(cam.dist), criteria=crit)[:, 0, :]
    return (z_m * np.sqrt(1 + xy[:, 0] ** 2 + xy[:, 1] ** 2)).reshape(cam.shape)


@pytest.mark.parametrize("kind, ros_model", [("rational", "rational_polynomial"), ("thin_prism", "rational_polynomial"),
                                             ("fisheye", "equidistant")])
def test_rational_and_fisheye_camera_info_round_trip_to_the_same_lens(tmp_path, kind, ros_model):
    """A bag written with mcap-ros2 from a camera with a rational or fisheye lens (the
    CameraInfo tofhil's export writes: REP 104's name, D in OpenCV's order) imports back to the
    same model and parameters exactly; z-depth becomes radial through that lens (OpenCV's)."""
    cam = wide_camera(kind)
    msg = ros2.camera_info_message(cam, 0)
    assert msg["distortion_model"] == ros_model and msg["d"] == list(cam.dist)
    res = import_file(plane_bag(tmp_path / "w.mcap", cam), tmp_path / "w.h5")
    same = dataclasses.replace(cam, name=res.camera.name)  # (named after the CameraInfo topic)
    assert res.camera == same and res.camera.distortion_model == cam.distortion_model
    assert res.camera.dist == cam.dist  # bit for bit
    with open_session(res.out) as s:
        assert s.camera == same
        np.testing.assert_allclose(s.depth_frame(0).radial_m, _expected_radial_cv(cam, 1.25), rtol=1e-6)
    # and tofhil's own export of that session names the same lens
    back = ros2.write_session_mcap(res.out, tmp_path / "e.mcap").out
    res2 = import_file(back, tmp_path / "e.h5")
    assert res2.camera.distortion_model == cam.distortion_model and res2.camera.dist == cam.dist


@pytest.mark.parametrize("model, d, field, word", [
    ("unknown_model", [0.0] * 5, "CameraInfo.distortion_model", "equidistant"),
    ("rational_polynomial", list(RATIONAL) + [0.0] * 4 + [0.01, 0.0], "CameraInfo.d", "tilt"),
    ("equidistant", [0.1, 0.01, 0.0, 0.0, 0.0], "CameraInfo.d", "4 (k1, k2, k3, k4"),
    ("rational_polynomial", [0.1, 0.0, 0.0], "CameraInfo.d", "8 or more")])
def test_models_tofhil_cannot_express_are_refused_naming_the_field(tmp_path, model, d, field, word):
    bag = plane_bag(tmp_path / "m.mcap", camera(), model=model, d=d)
    with pytest.raises(InputFileError) as e:
        import_file(bag, tmp_path / "m.h5")
    msg = str(e.value)
    assert e.value.field.endswith(field) and str(bag) in msg and word in msg
    assert not (tmp_path / "m.h5").exists() and not list(tmp_path.glob(".*partial"))


def test_a_given_camera_replaces_a_missing_camera_info(tmp_path):
    cam = camera()
    bag = plane_bag(tmp_path / "n.mcap", cam, with_info=False)
    with pytest.raises(InputFileError) as e:
        import_file(bag, tmp_path / "n.h5")
    assert e.value.field == "CameraInfo" and "--camera" in str(e.value)
    res = import_file(bag, tmp_path / "n.h5", camera=cam)
    assert res.camera == cam and res.n_frames == 3
    # and a CameraInfo tofhil cannot express is then not needed
    fish = plane_bag(tmp_path / "f.mcap", cam, model="kannala_brandt8", d=[0.1, 0.0, 0.0, 0.0])
    res = import_file(fish, tmp_path / "f.h5", camera=cam)
    assert res.camera == cam and any("not used" in n for n in res.notes)
    with open_session(res.out) as s:
        assert s.device["camera_source"] == "given"


# --------------------------------------------------------------------------- pairing, topics
def test_pairing_by_nearest_stamp_is_one_to_one_and_counted(tmp_path):
    cam = camera((0, 0, 0, 0, 0))
    z = np.full(cam.shape, 2000, np.uint16)
    msgs = [("/tof/camera_info", ros2.CAMERA_INFO, info(0, cam))]
    for i in range(6):
        t = 10 ** 9 + i * PERIOD_NS
        msgs.append(("/tof/depth", ros2.IMAGE, image(t, z + i, "16UC1")))
        if i == 3:
            continue                                   # this IR frame was dropped
        jitter = 0 if i % 2 == 0 else 3_000_000        # odd frames: IR stamped 3 ms late
        msgs.append(("/tof/ir", ros2.IMAGE, image(t + jitter, np.full(cam.shape, 100 + i, np.uint16), "mono16")))
    msgs.append(("/tof/ir", ros2.IMAGE, image(10 ** 9 + 20 * PERIOD_NS, np.zeros(cam.shape, np.uint16), "mono16")))
    res = import_file(write_bag(tmp_path / "j.mcap", msgs), tmp_path / "j.h5")
    assert res.n_frames == 5
    assert any("1 depth image(s) without one left out" in n and "1 amplitude image(s) without a depth image" in n
               for n in res.notes), res.notes
    with open_session(res.out) as s:
        pairing = s.device["pairing"]["amplitude"]
        assert (pairing["paired_exact"], pairing["paired_nearest"]) == (3, 2)
        assert pairing["tolerance_s"] == pytest.approx(PERIOD_NS * 1e-9 / 2)
        for k, i in enumerate([0, 1, 2, 4, 5]):                  # each depth with its own IR image
            f = s.depth_frame(k)
            assert f.sequence == i and f.amplitude[0, 0] == 100 + i
            assert f.radial_m[24, 32] == pytest.approx((2000 + i) * 1e-3 / cam.ray_z[24, 32], rel=1e-6)
    p = ros2.pair_by_stamp([0.0, 0.1, 0.2], [0.01, 0.02, 0.26], 0.1)
    assert p.partner.tolist() == [0, -1, -1] and (p.exact, p.nearest, p.unpaired_partner) == (0, 1, 2)


def _layout(tmp_path: Path, extra_depth: bool = False) -> Path:
    """A Kinect-like bag: depth 16UC1, IR mono16, colour bgra8, two CameraInfo topics."""
    cam = camera((0, 0, 0, 0, 0))
    msgs = []
    for i in range(2):
        t = 5 * 10 ** 9 + i * PERIOD_NS
        msgs += [("/rgb/camera_info", ros2.CAMERA_INFO, info(t, cam, frame_id="rgb")),
                 ("/depth/camera_info", ros2.CAMERA_INFO, info(t, cam)),
                 ("/depth/image_raw", ros2.IMAGE, image(t, np.full(cam.shape, 900, np.uint16), "16UC1")),
                 ("/ir/image_raw", ros2.IMAGE, image(t, np.full(cam.shape, 50, np.uint16), "mono16")),
                 ("/rgb/image_raw", ros2.IMAGE, image(t, np.zeros(cam.shape + (4,), np.uint8), "bgra8"))]
        if extra_depth:
            msgs.append(("/depth_to_rgb/image_raw", ros2.IMAGE, image(t, np.full(cam.shape, 901, np.uint16), "16UC1")))
    return write_bag(tmp_path / ("amb.mcap" if extra_depth else "k.mcap"), msgs)


def test_topics_are_found_when_unambiguous(tmp_path):
    res = import_file(_layout(tmp_path), tmp_path / "k.h5")
    with open_session(res.out) as s:
        assert s.device["topics"] == {"depth": "/depth/image_raw", "amplitude": "/ir/image_raw", "confidence": None,
                                      "camera_info": "/depth/camera_info"}
        assert s.device["encodings"] == {"/depth/image_raw": "16UC1", "/ir/image_raw": "mono16"}
        assert s.device["other_topics"] == {} and s.n_frames == 2


def test_ambiguous_depth_topics_are_listed_with_their_encodings(tmp_path):
    bag = _layout(tmp_path, extra_depth=True)
    with pytest.raises(InputFileError) as e:
        import_file(bag, tmp_path / "a.h5")
    msg = str(e.value)
    assert e.value.field == "--depth-topic" and "2 depth-like image topics" in msg
    for part in ("/depth/image_raw (16UC1, 64x48", "/depth_to_rgb/image_raw (16UC1", "/ir/image_raw (mono16",
                 "/rgb/image_raw (bgra8"):
        assert part in msg, msg
    res = import_file(bag, tmp_path / "a.h5", topics={"depth": "/depth_to_rgb/image_raw", "info": "/depth/camera_info"})
    with open_session(res.out) as s:
        assert s.depth_frame(0).z_m[0, 0] == pytest.approx(0.901, abs=1e-6)


# --------------------------------------------------------------------------- hostile bags
def test_truncated_bag_is_refused_unless_salvaged(tmp_path):
    bag = plane_bag(tmp_path / "t.mcap", camera(), n=40)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(bag.read_bytes()[: int(bag.stat().st_size * 0.6)])
    with pytest.raises(InputFileError) as e:
        import_file(cut, tmp_path / "c.h5")
    assert "truncated" in str(e.value) and "--salvage" in str(e.value) and e.value.field == "MCAP footer"
    assert not (tmp_path / "c.h5").exists()
    res = import_file(cut, tmp_path / "c.h5", salvage=True)
    assert 0 < res.n_frames < 40 and any("truncated" in n for n in res.notes)


def test_a_damaged_chunk_is_one_clear_error(tmp_path):
    bag = plane_bag(tmp_path / "d.mcap", camera(), n=40)
    data = bytearray(bag.read_bytes())
    data[len(data) // 2] ^= 0xFF              # inside a compressed chunk: its CRC no longer matches
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputFileError) as e:
        import_file(bad, tmp_path / "x.h5")
    assert e.value.field == "MCAP records" and str(bad) in str(e.value)
    assert not (tmp_path / "x.h5").exists() and not list(tmp_path.glob(".*partial"))


def test_wrong_encoding_on_the_depth_topic_names_the_topic_and_encoding(tmp_path):
    cam = camera()
    bag = plane_bag(tmp_path / "e.mcap", cam, encoding="32FC1", depth_encoding_override="rgb8")
    with pytest.raises(InputFileError) as e:          # found automatically: no depth-like topic
        import_file(bag, tmp_path / "e.h5")
    assert "no depth-like image topic" in str(e.value) and "/tof/depth/image_raw (rgb8" in str(e.value)
    with pytest.raises(InputFileError) as e:          # named: its encoding is wrong
        import_file(bag, tmp_path / "e.h5", topics={"depth": "/tof/depth/image_raw"})
    assert e.value.field == "/tof/depth/image_raw: Image.encoding" and "'rgb8'" in str(e.value)
    assert "16UC1" in str(e.value) and "32FC1" in str(e.value)


def test_an_image_whose_bytes_do_not_fit_its_size_is_refused(tmp_path):
    cam = camera()
    t = 10 ** 9
    msgs = [("/tof/camera_info", ros2.CAMERA_INFO, info(t, cam)),
            ("/tof/depth", ros2.IMAGE, image(t, np.ones(cam.shape, np.float32), "32FC1", data=b"\0" * 100))]
    with pytest.raises(InputFileError) as e:
        import_file(write_bag(tmp_path / "b.mcap", msgs), tmp_path / "b.h5")
    assert e.value.field == "/tof/depth: Image.data" and "100 bytes" in str(e.value)
    assert not (tmp_path / "b.h5").exists() and not list(tmp_path.glob(".*partial"))


def test_big_endian_and_padded_rows_decode(tmp_path):
    cam = camera((0, 0, 0, 0, 0))
    z = (np.arange(cam.height * cam.width, dtype=np.uint16).reshape(cam.shape) % 3000) + 500
    padded = np.zeros((cam.height, cam.width + 3), ">u2")
    padded[:, :cam.width] = z
    msg = image(10 ** 9, z, "16UC1", big=True)
    msg["step"], msg["data"] = padded.strides[0], padded.tobytes()
    bag = write_bag(tmp_path / "be.mcap", [("/tof/camera_info", ros2.CAMERA_INFO, info(10 ** 9, cam)),
                                           ("/tof/depth", ros2.IMAGE, msg)])
    res = import_file(bag, tmp_path / "be.h5")
    with open_session(res.out) as s:
        np.testing.assert_allclose(s.depth_frame(0).z_m, z * 1e-3, rtol=1e-6)


def test_cli_hostile_bags_are_one_line_exit_2(tmp_path):
    cam = camera()
    bag = plane_bag(tmp_path / "ok.mcap", cam, n=20)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    cases = {
        cut: ("truncated", "cut.mcap"),
        plane_bag(tmp_path / "rgb.mcap", cam, depth_encoding_override="rgb8"): ("rgb8", "--depth-topic"),
        plane_bag(tmp_path / "noinfo.mcap", cam, with_info=False): ("CameraInfo", "noinfo.mcap"),
        plane_bag(tmp_path / "fish.mcap", cam, model="kannala_brandt8", d=[0.1, 0, 0, 0]): (
            "CameraInfo.distortion_model", "kannala_brandt8"),
    }
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    cases[tmp_path / "junk.mcap"] = ("not an MCAP file", "junk.mcap")
    for src, words in cases.items():
        r = run_tofhil("import", src, "--out", tmp_path / "x.h5", timeout=120)
        assert r.returncode == 2, (src, r.stderr)
        assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        for w in words:
            assert w in r.stderr, (w, r.stderr)
        assert not (tmp_path / "x.h5").exists() and not list(tmp_path.glob(".*partial"))
    r = run_tofhil("import", bag, "--out", tmp_path / "x.h5", "--depth-topic", "/nope", timeout=120)
    assert r.returncode == 2 and "--depth-topic" in r.stderr and "/tof/depth/image_raw (32FC1" in r.stderr
    r = run_tofhil("import", bag, "--out", tmp_path / "x.h5", "--depth-topic", "/tof/depth/image_raw",
                   "--amplitude-topic", "/tof/ir/image_raw", "--info-topic", "/tof/depth/camera_info", timeout=120)
    assert r.returncode == 0, r.stderr
    assert "ros2-mcap" in r.stdout and "20 frame(s)" in r.stdout


# --------------------------------------------------------------------------- export
def _read(bag: Path) -> tuple[dict, dict, dict]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(bag, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        counts = {c.topic: summary.statistics.channel_message_counts[c.id] for c in summary.channels.values()}
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        msgs: dict[str, list] = {}
        for _, channel, _, msg in reader.iter_decoded_messages(log_time_order=True):
            msgs.setdefault(channel.topic, []).append(msg)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    return {"counts": counts, "schemas": schemas}, msgs, meta


def test_export_with_the_twin_reads_back_with_the_mcap_reader(twin_session, tmp_path):
    out = tmp_path / "wall.mcap"
    r = run_tofhil("export", twin_session, "--out", out, "--scene", "wall", timeout=300)
    assert r.returncode == 0, r.stderr
    assert "/tofhil/twin/depth/radial: 3 message(s)" in r.stdout
    info_, msgs, meta = _read(out)
    topics = {"/tofhil/depth/radial": ros2.IMAGE, "/tofhil/amplitude": ros2.IMAGE, "/tofhil/camera_info": ros2.CAMERA_INFO,
              "/tofhil/points": ros2.POINT_CLOUD2, "/tofhil/twin/depth/radial": ros2.IMAGE,
              "/tofhil/twin/amplitude": ros2.IMAGE, "/tofhil/twin/points": ros2.POINT_CLOUD2,
              "/tofhil/residual/depth/radial": ros2.IMAGE}
    assert info_["schemas"] == topics and set(info_["counts"].values()) == {3}
    tofhil_meta = {k: json.loads(v) if v[:1] in "{[" else v for k, v in meta["tofhil"].items()}
    assert tofhil_meta["depth_kind"] == "radial" and tofhil_meta["topics"]["/tofhil/depth/radial"]["kind"] == "radial"
    assert tofhil_meta["topics"]["/tofhil/residual/depth/radial"]["role"] == "residual_depth"
    with open_session(twin_session) as s:
        cam = s.camera
        for i in range(3):
            d = s.depth_frame(i)
            img = msgs["/tofhil/depth/radial"][i]
            assert (img.encoding, img.width, img.height, img.header.frame_id) == ("32FC1", cam.width, cam.height,
                                                                                   "tofhil_camera")
            depth = np.frombuffer(img.data, "<f4").reshape(cam.shape)
            assert np.array_equal(depth[d.valid], d.radial_m[d.valid]) and np.isnan(depth[~d.valid]).all()
            stamp = img.header.stamp.sec + img.header.stamp.nanosec * 1e-9
            assert stamp == pytest.approx(d.timestamp_s, abs=1e-9)
            amp = np.frombuffer(msgs["/tofhil/amplitude"][i].data, "<f4").reshape(cam.shape)
            assert np.array_equal(amp, d.amplitude)
            twin = np.frombuffer(msgs["/tofhil/twin/depth/radial"][i].data, "<f4").reshape(cam.shape)
            res = np.frombuffer(msgs["/tofhil/residual/depth/radial"][i].data, "<f4").reshape(cam.shape)
            both = d.valid & np.isfinite(twin)
            np.testing.assert_allclose(res[both], depth[both].astype(np.float64) - twin[both], atol=1e-6)
            assert abs(np.nanmedian(res)) < 0.01          # a wall against its own twin: noise only
            cloud = msgs["/tofhil/points"][i]
            assert cloud.width == int(d.valid.sum()) and cloud.point_step == 16
            pts = np.frombuffer(cloud.data, "<f4").reshape(-1, 4)
            np.testing.assert_allclose(pts[:, :3], d.points(), atol=1e-5)
            ci = msgs["/tofhil/camera_info"][i]
            assert ci.distortion_model == "plumb_bob" and list(ci.k) == [cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1]
    r = run_tofhil("export", twin_session, "--out", out, timeout=120)
    assert r.returncode == 2 and "--force" in r.stderr and "Traceback" not in r.stderr
    # the export (twin topics and all) imports back: the session's depth is found by its role
    res = import_file(out, tmp_path / "back.h5")
    with open_session(res.out) as b, open_session(twin_session) as s:
        assert b.device["topics"]["depth"] == "/tofhil/depth/radial" and b.camera == s.camera
        assert np.array_equal(b.depth_frame(2).radial_m[s.depth_frame(2).valid],
                              s.depth_frame(2).radial_m[s.depth_frame(2).valid])


def test_export_of_a_depth_session_without_timestamps(tmp_path):
    """ADI-like: depth only, NaN timestamps, confidence; exported as z with stated synthetic stamps."""
    from tofhil.frames import DepthFrame
    from tofhil.session import SessionWriter

    cam = camera()
    src = tmp_path / "adi.h5"
    radial = (1.0 / cam.ray_z).astype(np.float32)         # the plane z = 1 m
    with SessionWriter(src, cam, device={"model": "ADI-like"}) as w:
        for i in range(2):
            w.append(depth=DepthFrame(distance_m=radial, kind="radial", camera=cam,
                                      amplitude=np.full(cam.shape, 7.0 + i, np.float32),
                                      confidence=np.full(cam.shape, 3.0, np.float32),
                                      timestamp_s=float("nan"), sequence=i))
    res = ros2.write_session_mcap(src, tmp_path / "adi.mcap", depth_kind="z")
    assert set(res.counts) == {"/tofhil/depth/z", "/tofhil/amplitude", "/tofhil/confidence", "/tofhil/camera_info",
                               "/tofhil/points"}
    _, msgs, meta = _read(res.out)
    assert meta["tofhil"]["timestamps"].startswith("synthetic")
    z = np.frombuffer(msgs["/tofhil/depth/z"][1].data, "<f4").reshape(cam.shape)
    np.testing.assert_allclose(z, 1.0, atol=1e-6)
    assert msgs["/tofhil/depth/z"][1].header.stamp.nanosec == 100_000_000
    back = import_file(res.out, tmp_path / "back.h5")
    with open_session(back.out) as s:
        assert s.device["topics"]["confidence"] == "/tofhil/confidence"
        f = s.depth_frame(1)
        np.testing.assert_allclose(f.radial_m, radial, rtol=3e-7)
        assert f.amplitude[0, 0] == 8.0 and f.confidence[0, 0] == 3.0
