"""Reading clouds from PLY, PCD, text, npy and session frames; clear errors otherwise."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.eval.metrics.clouds import load_cloud, parse_session_spec
from tofhil.frames import DepthFrame
from tofhil.open3d_loader import open3d
from tofhil.session import SessionWriter

PTS = np.array([[0.1, -0.2, 1.0], [0.5, 0.25, 2.0], [-1.5, 0.0, 3.25], [0.0, 0.0, 0.5]])


def _write_o3d(path: Path, pts: np.ndarray, ascii: bool) -> None:
    o3d = open3d()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    assert o3d.io.write_point_cloud(str(path), pc, write_ascii=ascii)


@pytest.mark.parametrize("name,ascii", [("c.ply", False), ("c.ply", True), ("c.pcd", False), ("c.pcd", True)])
def test_ply_pcd(tmp_path, name, ascii):
    p = tmp_path / name
    _write_o3d(p, PTS, ascii)
    np.testing.assert_allclose(load_cloud(p), PTS, atol=1e-6)


def test_text_formats(tmp_path):
    (tmp_path / "a.xyz").write_text("# x y z intensity\n" + "\n".join(f"{x} {y} {z} 7" for x, y, z in PTS))
    (tmp_path / "b.csv").write_text("\n".join(f"{x},{y},{z}" for x, y, z in PTS))
    np.save(tmp_path / "c.npy", PTS)
    for name in ("a.xyz", "b.csv", "c.npy"):
        np.testing.assert_array_equal(load_cloud(tmp_path / name), PTS)


def test_nan_holes_dropped_infinite_and_absurd_points_refused(tmp_path):
    # NaN marks a hole of an organised cloud: dropped. Infinity or 1e30 m is a broken file.
    np.save(tmp_path / "c.npy", np.vstack([PTS, [np.nan, 0, 1]]))
    assert load_cloud(tmp_path / "c.npy").shape == (4, 3)
    np.save(tmp_path / "inf.npy", np.vstack([PTS, [np.inf, 1, 1]]))
    with pytest.raises(InputFileError, match=r"inf.npy: field 'point 4'"):
        load_cloud(tmp_path / "inf.npy")
    (tmp_path / "far.xyz").write_text("0 0 1\n1e30 0 0\n0 1 1\n")
    with pytest.raises(InputFileError, match=r"far.xyz: field 'point 1'.*1e\+30"):
        load_cloud(tmp_path / "far.xyz")


@pytest.mark.parametrize("ascii", [False, True])
def test_truncated_ply_is_refused(tmp_path, ascii):
    n = 100
    pts = np.random.default_rng(1).uniform(-1, 1, (n, 3))
    full = tmp_path / "full.ply"
    _write_o3d(full, pts, ascii)
    assert load_cloud(full).shape == (n, 3)
    raw = full.read_bytes()
    cut = tmp_path / "cut.ply"
    if ascii:
        lines = raw.decode().splitlines()
        cut.write_text("\n".join(lines[:-98]) + "\n")  # 2 of the 100 vertex lines left
    else:
        cut.write_bytes(raw[:len(raw) - 98 * 24])  # 3 doubles per vertex: 2 vertices left
    with pytest.raises(InputFileError, match="cut.ply: field 'element vertex': declares 100 vertices.*only 2"):
        load_cloud(cut)


def test_empty_text_cloud_gives_the_message_only(tmp_path, recwarn):
    (tmp_path / "c.xyz").write_text("# only a comment\n")
    with pytest.raises(InputFileError, match="c.xyz: is empty"):
        load_cloud(tmp_path / "c.xyz")
    assert not [w for w in recwarn if "loadtxt" in str(w.message)]


def test_session_frame(tmp_path):
    cam = CameraModel.from_fov(8, 6, 60.0)
    path = tmp_path / "s.h5"
    d0 = np.full((6, 8), 1.0)
    d1 = np.full((6, 8), 2.0)
    d1[0, 0] = 0.0                       # invalid pixel
    with SessionWriter(path, cam) as w:
        w.append(depth=DepthFrame(d0, "radial", cam))
        w.append(depth=DepthFrame(d1, "radial", cam))
    p0 = load_cloud(path)
    p1 = load_cloud(f"{path}:1")
    assert p0.shape == (48, 3) and p1.shape == (47, 3)
    np.testing.assert_allclose(np.linalg.norm(p0, axis=1), 1.0)      # radial distance 1 m
    np.testing.assert_allclose(np.linalg.norm(p1, axis=1), 2.0)
    np.testing.assert_allclose(load_cloud(f"{path}:-1"), p1)
    with pytest.raises(InputFileError, match="frame 5"):
        load_cloud(f"{path}:5")


def test_session_spec_parsing():
    assert parse_session_spec("a/b.h5:3") == (Path("a/b.h5"), 3)
    assert parse_session_spec("b.hdf5") == (Path("b.hdf5"), 0)
    assert parse_session_spec("b.ply") is None


def test_errors_name_the_file(tmp_path):
    with pytest.raises(InputFileError, match="nope.ply: no such file"):
        load_cloud(tmp_path / "nope.ply")
    with pytest.raises(InputFileError, match="does not exist"):
        load_cloud(f"{tmp_path / 'nope.h5'}:2")
    (tmp_path / "e.xyz").write_text("")
    with pytest.raises(InputFileError, match="e.xyz: is empty"):
        load_cloud(tmp_path / "e.xyz")
    (tmp_path / "two.xyz").write_text("1 2\n3 4\n")
    with pytest.raises(InputFileError, match="2 columns"):
        load_cloud(tmp_path / "two.xyz")
    (tmp_path / "words.txt").write_text("a b c\n")
    with pytest.raises(InputFileError, match="not numeric"):
        load_cloud(tmp_path / "words.txt")
    (tmp_path / "bad.pcd").write_text("hello\n")
    with pytest.raises(InputFileError, match="bad.pcd: field 'header'"):
        load_cloud(tmp_path / "bad.pcd")
    (tmp_path / "bad.ply").write_bytes(b"\x00\x01garbage")
    with pytest.raises(InputFileError, match="not a PLY"):
        load_cloud(tmp_path / "bad.ply")
    (tmp_path / "x.obj").write_text("v 0 0 0\n")
    with pytest.raises(InputFileError, match="unknown extension"):
        load_cloud(tmp_path / "x.obj")
    np.save(tmp_path / "nan.npy", np.full((3, 3), np.nan))
    with pytest.raises(InputFileError, match="no finite points"):
        load_cloud(tmp_path / "nan.npy")
    (tmp_path / "empty.pcd").write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                                        "WIDTH 0\nHEIGHT 1\nPOINTS 0\nDATA ascii\n")
    with pytest.raises(InputFileError, match="empty.pcd"):
        load_cloud(tmp_path / "empty.pcd")


def test_session_without_depth(tmp_path):
    from tofhil.frames import RawFrame

    cam = CameraModel.from_fov(4, 3, 60.0)
    path = tmp_path / "raw.h5"
    with SessionWriter(path, cam) as w:
        w.append(raw=RawFrame(np.ones((1, 4, 3, 4)), np.array([20e6]), np.arange(4) * np.pi / 2, 1e-3, cam))
    with pytest.raises(InputFileError, match="no depth"):
        load_cloud(path)


def _write_pcd_binary(path: Path, rows: np.ndarray, fields: str, sizes: str, types: str, n: int) -> None:
    head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {' '.join('1' * len(fields.split()))}\n"
            f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")
    path.write_bytes(head.encode() + rows.tobytes())


def test_binary_pcd_read_without_open3d_equals_open3d(tmp_path):
    """An uncompressed binary PCD is read from its bytes (no Open3D import): the same points
    as Open3D reads, also with other fields before and between x, y, z and float64 x y z."""
    from tofhil.eval.metrics import clouds

    rng = np.random.default_rng(4)
    p = tmp_path / "o3d.pcd"
    _write_o3d(p, rng.normal(size=(500, 3)), ascii=False)
    direct = clouds._read_pcd_binary(p)
    assert direct is not None
    np.testing.assert_array_equal(direct, clouds._read_open3d(p))
    np.testing.assert_array_equal(load_cloud(p), direct)
    dt = np.dtype([("rgb", "<u4"), ("x", "<f8"), ("i", "<u2"), ("y", "<f8"), ("z", "<f8")])
    rows = np.zeros(40, dt)
    pts = rng.normal(size=(40, 3))
    rows["x"], rows["y"], rows["z"], rows["rgb"], rows["i"] = pts[:, 0], pts[:, 1], pts[:, 2], 7, 9
    q = tmp_path / "mixed.pcd"
    _write_pcd_binary(q, rows, "rgb x intensity y z", "4 8 2 8 8", "U F U F F", 40)
    np.testing.assert_array_equal(load_cloud(q), pts)
    # ascii: not this reader's (Open3D reads it)
    a = tmp_path / "a.pcd"
    _write_o3d(a, pts, ascii=True)
    assert clouds._read_pcd_binary(a) is None


def test_truncated_binary_pcd_is_refused(tmp_path):
    rows = np.zeros((10, 3), "<f4")
    p = tmp_path / "short.pcd"
    _write_pcd_binary(p, rows[:7], "x y z", "4 4 4", "F F F", 10)
    with pytest.raises(InputFileError, match="short.pcd: field 'POINTS'"):
        load_cloud(p)
