"""Read a point cloud into an [N, 3] float64 array (metres).

Accepted sources:
- ``*.ply``, ``*.pcd`` (any PCD/PLY Open3D reads: ascii, binary, binary_compressed),
- text xyz: ``*.xyz``, ``*.txt``, ``*.csv``, ``*.pts`` -- the first three numeric columns,
  whitespace or comma separated, ``#`` comments; ``*.npy`` -- an [N, >=3] array,
- a session frame ``SESSION.h5[:FRAME]`` (``.h5``/``.hdf5``; frame default 0, negative
  counts from the end): the camera-frame points of the frame's valid depth pixels.

Non-finite points are dropped. Every failure raises :class:`InputFileError` naming the
file (and the field) and what was expected.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from tofhil.errors import InputFileError

TEXT_SUFFIXES = (".xyz", ".txt", ".csv", ".pts")
SESSION_SUFFIXES = (".h5", ".hdf5")
_SESSION_SPEC = re.compile(r"^(?P<path>.+\.(?:h5|hdf5))(?::(?P<frame>-?\d+))?$", re.IGNORECASE)


def parse_session_spec(spec: str) -> tuple[Path, int] | None:
    """``'s.h5:3'`` -> ``(Path('s.h5'), 3)``; ``'s.h5'`` -> frame 0; other paths -> None."""
    m = _SESSION_SPEC.match(str(spec))
    if not m:
        return None
    return Path(m.group("path")), int(m.group("frame") or 0)


def _finite(points: np.ndarray, source: str | Path) -> np.ndarray:
    p = points[np.all(np.isfinite(points), axis=1)]
    if p.shape[0] == 0:
        raise InputFileError("contains no finite points", file=source, expected="a non-empty point cloud")
    return p


def _read_open3d(path: Path) -> np.ndarray:
    from tofhil.open3d_loader import open3d

    o3d = open3d()
    # Open3D prints a warning and returns an empty cloud on unreadable files; check the
    # header ourselves for PCD so the message says what is wrong.
    if path.suffix.lower() == ".pcd":
        head = path.read_bytes()[:4096]
        if b"FIELDS" not in head or b"DATA" not in head:
            raise InputFileError("is not a PCD file", file=path, field="header",
                                 expected="a PCD header with FIELDS ... and DATA lines")
    else:
        if not path.read_bytes()[:3] == b"ply":
            raise InputFileError("is not a PLY file", file=path, field="header", expected="a file starting with 'ply'")
    cloud = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(cloud.points, dtype=np.float64)
    if pts.shape[0] == 0:
        raise InputFileError("has no readable points", file=path, field="vertex",
                             expected="x, y, z point fields Open3D can read")
    return pts


def _read_text(path: Path) -> np.ndarray:
    text = path.read_text(errors="replace")
    delim = "," if path.suffix.lower() == ".csv" or ("," in text.split("\n", 1)[0]) else None
    try:
        arr = np.loadtxt(path, delimiter=delim, comments="#", ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise InputFileError(f"is not numeric text ({exc})", file=path,
                             expected="rows of at least 3 numbers x y z in metres") from None
    if arr.size == 0:
        raise InputFileError("is empty", file=path, expected="rows of x y z")
    if arr.shape[1] < 3:
        raise InputFileError(f"has {arr.shape[1]} columns", file=path, expected="at least 3 columns x y z")
    return arr[:, :3]


def _read_npy(path: Path) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise InputFileError(f"is not a numpy file ({exc})", file=path, expected="an .npy array [N, 3]") from None
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InputFileError(f"has shape {arr.shape}", file=path, expected="an [N, 3] array")
    return np.asarray(arr[:, :3], dtype=np.float64)


def _read_session(path: Path, frame: int) -> np.ndarray:
    from tofhil.session import open_session

    with open_session(path) as s:
        if not s.has_depth:
            raise InputFileError("has no depth frames", file=path, field="depth/radial_m",
                                 expected="a session with depth (run 'tofhil depth' first)")
        if not -s.n_frames <= frame < s.n_frames:
            raise InputFileError(f"has no frame {frame}", file=path, field="frame",
                                 expected=f"a frame index in 0..{s.n_frames - 1}")
        return s.depth_frame(frame).points()


def load_cloud(source: str | Path) -> np.ndarray:
    """Read ``source`` (see module docstring) as an [N, 3] float64 array of finite points."""
    spec = str(source)
    sess = parse_session_spec(spec)
    if sess is not None:
        path, frame = sess
        if not path.is_file():
            raise InputFileError("does not exist", file=path, expected="a session file (.h5)")
        return _finite(_read_session(path, frame), spec)
    path = Path(source)
    if not path.exists():
        raise InputFileError("does not exist", file=path, expected="a PLY, PCD, xyz text or session file")
    if not path.is_file():
        raise InputFileError("is not a file", file=path, expected="a PLY, PCD, xyz text or session file")
    suffix = path.suffix.lower()
    if suffix in (".ply", ".pcd"):
        pts = _read_open3d(path)
    elif suffix in TEXT_SUFFIXES:
        pts = _read_text(path)
    elif suffix == ".npy":
        pts = _read_npy(path)
    else:
        raise InputFileError(f"has an unknown extension '{path.suffix}'", file=path,
                             expected="one of .ply .pcd .xyz .txt .csv .pts .npy .h5[:FRAME]")
    return _finite(pts, path)
