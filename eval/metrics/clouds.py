"""Read a point cloud into an [N, 3] float64 array (metres).

Accepted sources:
- ``*.ply``, ``*.pcd`` (any PCD/PLY Open3D reads: ascii, binary, binary_compressed; an
  uncompressed binary PCD is read from its bytes, without importing Open3D),
- text xyz: ``*.xyz``, ``*.txt``, ``*.csv``, ``*.pts`` -- the first three numeric columns,
  whitespace or comma separated, ``#`` comments; ``*.npy`` -- an [N, >=3] array,
- a session frame ``SESSION.h5[:FRAME]`` (``.h5``/``.hdf5``; frame default 0, negative
  counts from the end): the camera-frame points of the frame's valid depth pixels.

NaN points (the holes of an organised cloud) are dropped; an infinite coordinate or one
beyond :data:`MAX_COORDINATE_M` is refused with the file and the point's row. A PLY file's
data must hold as many vertices as its header declares (Open3D reads a truncated file
leniently, filling the missing points with garbage). Every failure raises
:class:`InputFileError` naming the file (and the field) and what was expected.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from tofhil.errors import InputFileError, require_input_file

TEXT_SUFFIXES = (".xyz", ".txt", ".csv", ".pts")
SESSION_SUFFIXES = (".h5", ".hdf5")
#: Largest accepted |coordinate| [m]: a ToF cloud spans metres, not thousands of kilometres.
MAX_COORDINATE_M = 1.0e6

_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}

_SESSION_SPEC = re.compile(r"^(?P<path>.+\.(?:h5|hdf5))(?::(?P<frame>-?\d+))?$", re.IGNORECASE)


def parse_session_spec(spec: str) -> tuple[Path, int] | None:
    """``'s.h5:3'`` -> ``(Path('s.h5'), 3)``; ``'s.h5'`` -> frame 0; other paths -> None."""
    m = _SESSION_SPEC.match(str(spec))
    if not m:
        return None
    return Path(m.group("path")), int(m.group("frame") or 0)


def _finite(points: np.ndarray, source: str | Path) -> np.ndarray:
    """Drop NaN points (holes); refuse infinite or absurd coordinates, naming the row."""
    # The common case in two reductions, no temporaries (a NaN makes min and max NaN and
    # fails the test): the full check below makes ~10 passes over the cloud.
    if points.size and -MAX_COORDINATE_M <= points.min() and points.max() <= MAX_COORDINATE_M:
        return np.ascontiguousarray(points)
    with np.errstate(invalid="ignore"):
        bad = np.isinf(points).any(axis=1) | (np.abs(np.nan_to_num(points)) > MAX_COORDINATE_M).any(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise InputFileError(f"point {row} (0-based data row) is {points[row].tolist()}; {int(bad.sum())} point(s) "
                             "like it", file=source, field=f"point {row}",
                             expected=f"finite coordinates in metres, |x|, |y|, |z| <= {MAX_COORDINATE_M:g}")
    p = points[~np.isnan(points).any(axis=1)]
    if p.shape[0] == 0:
        raise InputFileError("contains no finite points", file=source, expected="a non-empty point cloud")
    return p


#: PCD TYPE/SIZE -> numpy dtype character (I signed, U unsigned, F float).
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def _read_pcd_binary(path: Path) -> np.ndarray | None:
    """x, y, z of an uncompressed binary PCD straight from its bytes (no Open3D import, which
    alone costs ~1.5 CPU-s; as PCL's reader: rows of FIELDS with SIZE, TYPE and COUNT,
    little-endian). None for anything else (ascii, binary_compressed, no x y z): Open3D
    reads those."""
    with path.open("rb") as fh:
        head = fh.read(4096)
    end = head.find(b"\nDATA ")
    if end < 0:
        return None
    line_end = head.find(b"\n", end + 1)
    if line_end < 0 or head[end + 6:line_end].strip() != b"binary":
        return None
    fields: dict[str, list[str]] = {}
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        t = line.split()
        if t and not t[0].startswith("#"):
            fields[t[0].upper()] = t[1:]
    try:
        names, sizes, types = fields["FIELDS"], [int(v) for v in fields["SIZE"]], fields["TYPE"]
        counts = [int(v) for v in fields.get("COUNT", ["1"] * len(names))]
        n = int(fields["POINTS"][0])
        dtype = np.dtype([(f"{name}_{i}", "<" + _PCD_TYPES[(ty.upper(), sz)], (c,))
                          for i, (name, sz, ty, c) in enumerate(zip(names, sizes, types, counts, strict=True))])
        cols = [names.index(a) for a in ("x", "y", "z")]
    except (KeyError, ValueError, IndexError):
        return None
    if any(counts[c] != 1 for c in cols):
        return None
    raw = np.fromfile(path, dtype=np.uint8, offset=line_end + 1)
    if raw.size < n * dtype.itemsize:
        raise InputFileError(f"holds {raw.size // dtype.itemsize} of the {n} points its header declares",
                             file=path, field="POINTS", expected="as many binary rows as POINTS")
    rows = raw[:n * dtype.itemsize].view(dtype)
    pts = np.empty((n, 3))
    for j, c in enumerate(cols):
        pts[:, j] = rows[dtype.names[c]][:, 0]
    if n == 0:
        raise InputFileError("has no readable points", file=path, field="vertex",
                             expected="x, y, z point fields Open3D can read")
    return pts


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
        _check_ply(path)
    cloud = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(cloud.points, dtype=np.float64)
    if pts.shape[0] == 0:
        raise InputFileError("has no readable points", file=path, field="vertex",
                             expected="x, y, z point fields Open3D can read")
    return pts


def _ply_header(path: Path, raw: bytes) -> tuple[str, list[tuple[str, int, list[str] | None]], int]:
    """The PLY header: format, elements ``(name, count, property types or None if a list
    property makes the size variable)`` and the offset where the data start."""
    if raw[:3] != b"ply":
        raise InputFileError("is not a PLY file", file=path, field="header", expected="a file starting with 'ply'")
    m = re.search(rb"end_header\r?\n", raw[:65536])
    if m is None:
        raise InputFileError("has no end_header line", file=path, field="header", expected="a complete PLY header")
    fmt = ""
    elements: list[tuple[str, int, list[str] | None]] = []
    for line in raw[:m.start()].decode("ascii", errors="replace").splitlines():
        t = line.split()
        if not t:
            continue
        if t[0] == "format" and len(t) >= 2:
            fmt = t[1]
        elif t[0] == "element" and len(t) == 3:
            try:
                count = int(t[2])
            except ValueError:
                raise InputFileError(f"declares {line.strip()!r}", file=path, field="header",
                                     expected="element NAME COUNT with an integer count") from None
            elements.append((t[1], count, []))
        elif t[0] == "property" and elements:
            name, count, props = elements[-1]
            if len(t) >= 2 and t[1] == "list" or props is None:
                elements[-1] = (name, count, None)
            elif len(t) >= 3 and t[1] in _PLY_SIZES:
                props.append(t[1])
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputFileError(f"has format {fmt!r}", file=path, field="header",
                             expected="ascii, binary_little_endian or binary_big_endian")
    return fmt, elements, m.end()


def _check_ply(path: Path) -> None:
    """Refuse a PLY whose data hold fewer vertices than its header declares."""
    raw = path.read_bytes()
    fmt, elements, start = _ply_header(path, raw)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise InputFileError("declares no vertex element", file=path, field="element vertex",
                             expected="element vertex N with x, y, z properties")
    body = raw[start:]
    declared = elements[names.index("vertex")][1]
    if fmt == "ascii":
        # one line per element item; the vertices follow the items of earlier elements
        skip = sum(c for _, c, _ in elements[:names.index("vertex")])
        lines = [ln for ln in body.splitlines() if ln.strip()]
        have = max(0, min(len(lines) - skip, declared))
        nprops = len(elements[names.index("vertex")][2] or [])
        if have == declared and nprops:
            short = [i for i, ln in enumerate(lines[skip:skip + declared]) if len(ln.split()) < nprops]
            have = short[0] if short else declared
    else:
        before = elements[:names.index("vertex") + 1]
        if any(p is None for _, _, p in before):
            return  # variable-size items before the vertices: Open3D's own checks must do
        sizes = [c * sum(_PLY_SIZES[t] for t in p) for _, c, p in before]
        stride = sum(_PLY_SIZES[t] for t in before[-1][2])
        if stride == 0:
            return
        have = min(declared, max(0, (len(body) - sum(sizes[:-1])) // stride))
    if have < declared:
        raise InputFileError(f"declares {declared} vertices in its header but its data hold only {have} "
                             "(truncated file?)", file=path, field="element vertex",
                             expected=f"{declared} complete vertices")


def _read_text(path: Path) -> np.ndarray:
    text = path.read_text(errors="replace")
    delim = "," if path.suffix.lower() == ".csv" or ("," in text.split("\n", 1)[0]) else None
    try:
        with warnings.catch_warnings():  # an empty file is reported below, without numpy's warning
            warnings.simplefilter("ignore", UserWarning)
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
        return s.requested_depth_frame(frame, field="frame").points()


def load_cloud(source: str | Path) -> np.ndarray:
    """Read ``source`` (see module docstring) as an [N, 3] float64 array of finite points."""
    spec = str(source)
    sess = parse_session_spec(spec)
    if sess is not None:
        path, frame = sess
        if not path.is_file():
            raise InputFileError("does not exist", file=path, expected="a session file (.h5)")
        return _finite(_read_session(path, frame), spec)
    path = require_input_file(source, expected="a PLY, PCD, xyz text or session file")
    suffix = path.suffix.lower()
    if suffix == ".pcd" and (pts := _read_pcd_binary(path)) is not None:
        pass
    elif suffix in (".ply", ".pcd"):
        pts = _read_open3d(path)
    elif suffix in TEXT_SUFFIXES:
        pts = _read_text(path)
    elif suffix == ".npy":
        pts = _read_npy(path)
    else:
        raise InputFileError(f"has an unknown extension '{path.suffix}'", file=path,
                             expected="one of .ply .pcd .xyz .txt .csv .pts .npy .h5[:FRAME]")
    return _finite(pts, path)
