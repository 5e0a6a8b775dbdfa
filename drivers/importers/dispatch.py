"""Turn real captures from other tools into tofhil sessions (``tofhil import``).

Formats (detected from content and name, :func:`detect_format`):

==================  ==============================================================  ===========
format              what                                                            depth kind
==================  ==============================================================  ===========
``adi-interleaved`` ADI ToF SDK frames, 512x512x5 bytes each (depth, conf, AB)      radial
``adi-pair``        ADI ``*_depth*.bin`` + matching ``*_ir*.bin`` (uint16 images)   radial
``k4a-mkv``         Azure Kinect recording (.mkv, depth + IR + calibration.json)    z -> radial
``ros2-mcap``       ROS 2 bag (.mcap): sensor_msgs Image depth + IR, CameraInfo     z -> radial
``session``         a tofhil session (copied frame by frame: replay / repair)       radial
==================  ==============================================================  ===========

Every session written here stores ``depth/radial_m`` in metres, ``depth/amplitude`` = the
device's active brightness / IR in its own counts, ``depth/valid`` = depth > 0 (and the
device's own validity where it has one; booleans), ``depth/confidence`` = the device's own
confidence where the format has one (ADI interleaved: the confidence byte), and in the
``device`` attribute the source file,
its SHA-256, the format, what the file's depth kind was and where the camera model came
from. Nothing existing is overwritten without ``force``.
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import h5py
import numpy as np

from tofhil.camera import CameraModel, load_camera_preset
from tofhil.drivers.importers import adi, ros2
from tofhil.errors import InputFileError, TofhilError
from tofhil.frames import DepthFrame
from tofhil.outputs import partial_path, refuse_existing, remove_partial
from tofhil.session import SessionWriter, open_session

FORMATS = ("adi-interleaved", "adi-pair", "k4a-mkv", "ros2-mcap", "session")

_EBML_MAGIC = b"\x1a\x45\xdf\xa3"
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


@dataclass
class ImportResult:
    out: Path
    format: str
    n_frames: int
    camera: CameraModel
    notes: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- detection
def detect_format(path: str | Path) -> str:
    """The format of ``path`` (one of :data:`FORMATS`), from its content, size and name."""
    p = Path(path)
    if not p.is_file():
        raise InputFileError("no such file", file=p, expected="a capture to import (" + ", ".join(FORMATS) + ")")
    with open(p, "rb") as fh:
        head = fh.read(8)
    if head[:4] == _EBML_MAGIC:
        return "k4a-mkv"
    if head == ros2.MCAP_MAGIC:
        return "ros2-mcap"
    if p.suffix.lower() == ".mcap":
        raise InputFileError(f"is not an MCAP file (starts {head.hex()})", file=p, field="magic",
                             expected="a ROS 2 bag in MCAP, starting 89 4D 43 41 50 30 0D 0A")
    if head == _HDF5_MAGIC or h5py.is_hdf5(p):
        return "session"
    size = p.stat().st_size
    frame = adi.ADI_WIDTH * adi.ADI_HEIGHT
    if p.suffix.lower() == ".bin":
        if adi.is_depth_name(p) or adi.partner_depth_path(p) is not None:
            return "adi-pair"
        if size > 0 and size % (frame * adi.INTERLEAVED_BYTES_PER_PIXEL) == 0:
            return "adi-interleaved"
        if size == frame * 2:
            raise InputFileError("looks like a single ADI uint16 image but its name does not say depth",
                                 file=p, field="file name",
                                 expected="name it *_depth*.bin with a matching *_ir*.bin beside it")
    raise InputFileError(f"format not recognised ({size} bytes, starts {head[:4].hex()})", file=p,
                         expected="an ADI interleaved .bin (512*512*5 bytes per frame), an ADI "
                                  "*_depth*.bin + *_ir*.bin pair, an Azure Kinect .mkv, a ROS 2 .mcap bag, "
                                  "or a tofhil session")


# --------------------------------------------------------------------------- helpers
def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def resolve_camera(camera: str | Path | CameraModel | None, default: str | CameraModel,
                   shape: tuple[int, int], source: Path) -> tuple[CameraModel, str]:
    """A camera model and a note on where it came from; its size must match the images."""
    if camera is None:
        cam = load_camera_preset(default) if isinstance(default, str) else default
        origin = f"preset {default} (assumed)" if isinstance(default, str) else "file"
    elif isinstance(camera, CameraModel):
        cam, origin = camera, "given"
    else:
        cam, origin = load_camera_preset(camera), f"--camera {camera}"
    if cam.shape != shape:
        raise InputFileError(f"camera {cam.name or camera} is {cam.width}x{cam.height}", file=source,
                             field="--camera", expected=f"a camera of the image size {shape[1]}x{shape[0]}")
    return cam, origin


def _write(out: Path, camera: CameraModel, device: dict[str, Any], items: Iterable[tuple[Any, Any]],
           force: bool, n_total: int, on_frame: Callable[[int, int], None] | None,
           scene_text: str = "", tap_dtype: Any = None) -> int:
    """Write ``(raw, depth)`` frames to a new session.

    The session is written beside ``out`` under a temporary name and renamed onto ``out``
    only when complete, so a failed import leaves neither a half-written file nor (with
    ``--force``) a destroyed previous one.
    """
    refuse_existing(out, force, recorded=True)
    tmp = partial_path(out)
    writer = SessionWriter(tmp, camera, device=device, scene_text=scene_text, force=True, tap_dtype=tap_dtype)
    try:
        for i, (raw, depth) in enumerate(items):
            writer.append(raw=raw, depth=depth)
            if on_frame is not None:
                on_frame(i + 1, n_total)
        n = writer.n_frames
        writer.close()
        if n == 0:
            raise InputFileError("no frames to import", field="frames", expected="at least one complete frame")
        os.replace(tmp, out)
    except BaseException:
        writer.close()
        remove_partial(tmp)  # our temporary file, never the user's
        raise
    return n


# --------------------------------------------------------------------------- per format
def _adi_frames(frames: Iterable[adi.AdiFrame], camera: CameraModel,
                max_confidence: int | None) -> Any:
    for i, f in enumerate(frames):
        valid = f.depth_mm > 0
        if max_confidence is not None and f.confidence is not None:
            valid &= f.confidence <= max_confidence
        # ADI depth is radial (see importers.adi): store it as is, in metres.
        yield DepthFrame(distance_m=np.where(valid, f.depth_mm * 1e-3, 0.0).astype(np.float32), kind="radial",
                         camera=camera, amplitude=f.amplitude.astype(np.float32), valid=valid,
                         confidence=None if f.confidence is None else f.confidence.astype(np.float32),
                         timestamp_s=math.nan, sequence=i)


def _import_k4a(rec: Any, src: Path, out: Path, camera: str | Path | CameraModel | None, force: bool,
                device: dict[str, Any], notes: list[str], on_frame: Callable[[int, int], None] | None) -> ImportResult:
    fmt = "k4a-mkv"
    if rec.truncated:
        notes.append(f"truncated recording: {rec.truncated}; imported its {len(rec)} complete frames")
    cam, origin = resolve_camera(camera, rec.camera, rec.camera.shape, src)
    device.update({"vendor": "Microsoft", "model": "Azure Kinect DK",
                   "serial": rec.tags.get("K4A_DEVICE_SERIAL_NUMBER", ""),
                   "firmware": rec.tags.get("K4A_DEPTH_FIRMWARE_VERSION", ""),
                   "depth_mode": rec.depth_mode, "depth_kind_in_file": "z", "depth_unit_in_file": "mm",
                   "depth_conversion": ("radial = z * |(x, y, 1)| with the factory rational model's rays"
                                        if camera is None else f"radial = z / ray_z of {origin}"),
                   "amplitude": "active IR, device counts",
                   "camera_source": (f"calibration.json ({rec.fit.method})" if camera is None else origin),
                   "camera_fit": rec.fit.to_dict(), "k4a_tags": rec.tags, "k4a_calibration": rec.calibration,
                   "timestamps": "device time = block time + K4A_START_OFFSET_NS"})
    exact = rec.fit.camera.distortion_model == "rational"
    notes.append(f"lens: {'factory rational model kept exactly' if exact else 'rational model refit to OpenCV 5-parameter'}"
                 f", max residual {rec.fit.max_residual_px:.3g} px (rms {rec.fit.rms_residual_px:.3g} px) over "
                 f"{rec.fit.n_pixels} pixels")

    def k4a_frames() -> Any:
        for i, (t, z_mm, ir) in enumerate(rec.iter_frames()):
            if camera is None:
                radial, valid = rec.radial_m(z_mm)
            else:
                valid = z_mm > 0
                radial = np.where(valid, cam.z_to_radial(z_mm * 1e-3), 0.0)
            amp = ir.astype(np.float32) if ir is not None else None
            yield None, DepthFrame(distance_m=radial.astype(np.float32), kind="radial", camera=cam,
                                   amplitude=amp, valid=valid, timestamp_s=t, sequence=i)

    n = _write(out, cam, device, k4a_frames(), force, len(rec), on_frame)
    return ImportResult(out, fmt, n, cam, notes)


def _import_ros2(src: Path, out: Path, camera: str | Path | CameraModel | None, force: bool, salvage: bool,
                 topics: dict[str, str | None], depth_kind: str | None, device: dict[str, Any], notes: list[str],
                 on_frame: Callable[[int, int], None] | None) -> ImportResult:
    unknown = set(topics) - {"depth", "amplitude", "confidence", "info"}
    if unknown:
        raise TofhilError(f"unknown topic roles {sorted(unknown)}", field="topics",
                          expected="depth, amplitude, confidence, info")
    given = camera if camera is None or isinstance(camera, CameraModel) else load_camera_preset(camera)
    bag = ros2.read_bag(src, camera=given, depth_topic=topics.get("depth"), amplitude_topic=topics.get("amplitude"),
                        confidence_topic=topics.get("confidence"), info_topic=topics.get("info"),
                        depth_kind=depth_kind, salvage=salvage)
    device.update(bag.device)
    if camera is not None:
        device["camera_source"] = f"--camera {camera}" if not isinstance(camera, CameraModel) else "given"
    notes.extend(bag.notes)
    n = _write(out, bag.camera, device, bag.frames(), force, bag.n_frames, on_frame)
    return ImportResult(out, "ros2-mcap", n, bag.camera, notes)


def import_file(path: str | Path, out: str | Path, *, camera: str | Path | CameraModel | None = None,
                force: bool = False, fmt: str | None = None, salvage: bool = False,
                adi_max_confidence: int | None = None, topics: Mapping[str, str | None] | None = None,
                depth_kind: str | None = None,
                on_frame: Callable[[int, int], None] | None = None) -> ImportResult:
    """Import one capture into a new session file ``out``.

    ``camera`` overrides the camera model (preset name, YAML path or CameraModel); files
    with their own calibration (Azure Kinect, a ROS 2 bag's CameraInfo) use theirs by default,
    ADI files the assumed preset ``adi_adtf3175_qmp``. ``salvage`` imports the complete frames
    of a truncated recording instead of refusing it. ROS 2 bags: ``topics`` names the
    ``depth``, ``amplitude``, ``confidence`` and ``info`` (CameraInfo) topics (each found
    when unambiguous if not given), ``depth_kind`` (``z`` or ``radial``) what the depth
    images hold (default: the bag's tofhil metadata, else z as ROS depth images are).
    """
    src = Path(path)
    out = Path(out)
    fmt = fmt or detect_format(src)
    if fmt not in FORMATS:
        raise TofhilError(f"unknown format {fmt!r}", field="--format", expected=" | ".join(FORMATS))
    if out.exists() and out.resolve() == src.resolve():
        raise InputFileError("the output must differ from the input", file=out, field="--out")
    refuse_existing(out, force, recorded=True)
    if not out.parent.is_dir():
        raise InputFileError("directory does not exist", file=out.parent, field="--out",
                             expected="an existing directory")
    device: dict[str, Any] = {"driver": "import", "format": fmt, "source_file": str(src.resolve()),
                              "source_sha256": _sha256(src)}
    notes: list[str] = []

    if fmt in ("adi-interleaved", "adi-pair"):
        if fmt == "adi-interleaved":
            n_total = adi.count_adi_interleaved(src)
            frames: Iterable[adi.AdiFrame] = adi.iter_adi_interleaved(src)
        else:
            depth_src = adi.partner_depth_path(src) if not adi.is_depth_name(src) else None
            if depth_src is not None:  # the IR image was named: import its pair
                src = depth_src
                device["source_file"], device["source_sha256"] = str(src.resolve()), _sha256(src)
            ir = adi.partner_ir_path(src)
            frames = [adi.read_adi_pair(src, ir)]
            n_total = 1
            device["source_ir_file"] = str(ir.resolve())
        cam, origin = resolve_camera(camera, adi.ADI_DEFAULT_CAMERA,
                                     (adi.ADI_HEIGHT, adi.ADI_WIDTH), src)
        device.update({"vendor": "Analog Devices", "model": "ADI ToF SDK capture (ADSD3500 class, 512x512)",
                       "depth_kind_in_file": "radial", "depth_unit_in_file": "mm",
                       "amplitude": "active brightness (AB / IR), device counts",
                       "camera_source": origin, "timestamps": "none in file (NaN)"})
        if adi_max_confidence is not None:
            device["adi_max_confidence"] = int(adi_max_confidence)
        if origin.endswith("(assumed)"):
            notes.append(f"camera model is the assumed preset {adi.ADI_DEFAULT_CAMERA} "
                         "(no intrinsics in ADI files); pass --camera to use a calibration")
        items = ((None, d) for d in _adi_frames(frames, cam, adi_max_confidence))
        n = _write(out, cam, device, items, force, n_total, on_frame)
        return ImportResult(out, fmt, n, cam, notes)

    if fmt == "ros2-mcap":
        return _import_ros2(src, out, camera, force, salvage, dict(topics or {}), depth_kind, device, notes,
                            on_frame)

    if fmt == "k4a-mkv":
        from tofhil.drivers.importers.k4a import read_k4a_recording

        with read_k4a_recording(src, salvage=salvage) as rec:
            return _import_k4a(rec, src, out, camera, force, device, notes, on_frame)

    # fmt == "session": copy (a replay that also repairs: only complete frames are copied)
    with open_session(src, need_frames=True) as s:
        cam, origin = resolve_camera(camera, s.camera, s.camera.shape, src)
        device = dict(s.device) | {"imported_from": device}
        if camera is not None:
            device["camera_source"] = origin
        def session_items() -> Any:
            for i in range(s.n_frames):
                raw = s.raw_frame(i) if s.has_raw else None
                if raw is not None:
                    raw.camera = cam
                d = s.depth_frame(i) if s.has_depth else None
                if d is not None:
                    d = DepthFrame(distance_m=d.distance_m, kind="radial", camera=cam, amplitude=d.amplitude,
                                   intensity=d.intensity, valid=d.valid, confidence=d.confidence,
                                   timestamp_s=d.timestamp_s,
                                   sequence=d.sequence, temperature_c=d.temperature_c)
                yield raw, d

        n = _write(out, cam, device, session_items(), force, s.n_frames, on_frame, scene_text=s.scene_text,
                   tap_dtype=s.integer_tap_dtype)      # integer taps stay in their type
        if s.n_frames < max(s.dataset_lengths.values()):
            notes.append(f"source had {max(s.dataset_lengths.values())} partly written frames; "
                         f"copied the {s.n_frames} complete ones")
    return ImportResult(out, fmt, n, cam, notes)
