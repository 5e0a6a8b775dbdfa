"""Analog Devices ToF SDK captures (ADSD3500 / ADTF3175 class modules) -> depth images.

Two layouts, both headerless, little-endian, row-major:

* **interleaved** depth/confidence/AB frames (``tools/Visualize/interleaved_data`` in
  analogdevicesinc/ToF): 5 bytes per pixel = depth uint16 (mm, 0 = no measurement),
  confidence uint8, active brightness (AB) uint16. A file may hold several frames back to
  back; its size must be a whole number of ``W*H*5`` byte frames.
* **raw image pairs** (``apps/http-server`` ``out_depth_*.bin`` / ``out_ir_*.bin``): one
  ``W*H`` uint16 image each, depth in mm and IR / active brightness.

Depth kind: ADI's depth is the **radial** distance along each pixel's ray. The SDK turns
it into points with per-pixel tables (``Algorithms::GenerateXYZTables`` / ``ComputeXYZ`` in
analogdevicesinc/ToF): ``X = depth * x/|(x, y, 1)|``, ``Z = depth * 1/|(x, y, 1)|``,
i.e. depth times the unit ray, which is the definition of radial distance. The shipped
near-plane capture agrees: a plane fit over its points is far flatter when the depth is
read as radial than as z (tests/test_import_adi.py).

No intrinsics ship with these frames: the default camera is the documented, assumed
preset ``adi_adtf3175_qmp`` (75 x 75 deg, 512 x 512); pass another with ``--camera``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from tofhil.errors import InputFileError

ADI_DEFAULT_CAMERA = "adi_adtf3175_qmp"
ADI_WIDTH = 512
ADI_HEIGHT = 512
INTERLEAVED_BYTES_PER_PIXEL = 5

#: The interleaved pixel: depth (uint16 LE), confidence (uint8), AB (uint16 LE), packed.
INTERLEAVED_DTYPE = np.dtype([("depth", "<u2"), ("conf", "u1"), ("ab", "<u2")])
assert INTERLEAVED_DTYPE.itemsize == INTERLEAVED_BYTES_PER_PIXEL


@dataclass
class AdiFrame:
    depth_mm: np.ndarray                 #: uint16 [H, W], radial, 0 = no measurement
    amplitude: np.ndarray                #: active brightness / IR, [H, W]
    confidence: np.ndarray | None = None  #: uint8 [H, W] (interleaved frames only)


def count_adi_interleaved(path: str | Path, width: int = ADI_WIDTH, height: int = ADI_HEIGHT) -> int:
    """Number of frames in an interleaved file; a size that is not whole frames is an error."""
    path = Path(path)
    frame_bytes = width * height * INTERLEAVED_BYTES_PER_PIXEL
    size = path.stat().st_size
    if size == 0 or size % frame_bytes:
        raise InputFileError(f"has {size} bytes", file=path, field="interleaved frame size",
                             expected=f"a multiple of {frame_bytes} ({width} x {height} pixels x 5 bytes: "
                                      "depth uint16, confidence uint8, AB uint16)")
    return size // frame_bytes


def iter_adi_interleaved(path: str | Path, width: int = ADI_WIDTH,
                         height: int = ADI_HEIGHT) -> Iterator[AdiFrame]:
    """Frames of an interleaved depth/confidence/AB file, one at a time (memory-mapped:
    each frame is split into its three images by one structured-array view)."""
    n = count_adi_interleaved(path, width, height)
    data = np.memmap(path, dtype=INTERLEAVED_DTYPE, mode="r", shape=(n, height, width))
    for f in data:
        yield AdiFrame(depth_mm=np.array(f["depth"]), amplitude=np.array(f["ab"]),
                       confidence=np.array(f["conf"]))


def read_adi_interleaved(path: str | Path, width: int = ADI_WIDTH, height: int = ADI_HEIGHT) -> list[AdiFrame]:
    """All frames of an interleaved file (use :func:`iter_adi_interleaved` for long files)."""
    return list(iter_adi_interleaved(path, width, height))


def _read_u16_image(path: Path, width: int, height: int, what: str) -> np.ndarray:
    size = path.stat().st_size
    if size != width * height * 2:
        raise InputFileError(f"has {size} bytes", file=path, field=what,
                             expected=f"{width * height * 2} ({width} x {height} uint16 little-endian)")
    return np.fromfile(path, dtype="<u2").reshape(height, width).astype(np.uint16)


def read_adi_pair(depth_path: str | Path, ir_path: str | Path, width: int = ADI_WIDTH,
                  height: int = ADI_HEIGHT) -> AdiFrame:
    """A headerless depth image and its IR / active-brightness image."""
    depth = _read_u16_image(Path(depth_path), width, height, "depth image")
    ir = _read_u16_image(Path(ir_path), width, height, "IR image")
    return AdiFrame(depth_mm=depth, amplitude=ir)


_DEPTH_NAME = re.compile(r"^(?P<pre>.*_)depth(?P<post>.*)\.bin$", re.IGNORECASE)


_IR_NAME = re.compile(r"^(?P<pre>.*_)(ir|ab)(?P<post>.*)\.bin$", re.IGNORECASE)


def is_depth_name(path: str | Path) -> bool:
    return _DEPTH_NAME.match(Path(path).name) is not None


def partner_depth_path(ir_path: str | Path) -> Path | None:
    """``near_plane_ir.bin`` -> ``near_plane_depth.bin`` when that file exists, else None."""
    p = Path(ir_path)
    m = _IR_NAME.match(p.name)
    if m is None:
        return None
    cand = p.with_name(f"{m['pre']}depth{m['post']}.bin")
    return cand if cand.is_file() else None


def partner_ir_path(depth_path: str | Path) -> Path:
    """``near_plane_depth.bin`` -> ``near_plane_ir.bin`` (``*_depth*.bin`` -> ``*_ir*.bin``)."""
    p = Path(depth_path)
    m = _DEPTH_NAME.match(p.name)
    if m is None:
        raise InputFileError("name does not match *_depth*.bin", file=p, field="file name",
                             expected="an ADI depth image named like out_depth_0.bin")
    for ir in ("ir", "IR", "ab", "AB"):
        cand = p.with_name(f"{m['pre']}{ir}{m['post']}.bin")
        if cand.is_file():
            return cand
    raise InputFileError("has no matching IR image", file=p, field="IR partner",
                         expected=f"{p.with_name(m['pre'] + 'ir' + m['post'] + '.bin')} beside it")
