"""ROS 2 recordings (MCAP) <-> depth frames: the reader behind ``tofhil import BAG.mcap`` and
the session -> MCAP writer behind ``tofhil export``.

Read and written with Foxglove's ``mcap`` and ``mcap-ros2-support`` (CDR encoding of the
``ros2msg`` schemas a bag carries; no ROS installation). What is read:

* ``sensor_msgs/msg/Image`` depth: ``16UC1`` (millimetres) or ``32FC1`` (metres); 0, NaN,
  infinite or negative values are invalid. ROS depth images are **z-depth** (REP 118: along
  the optical axis), so ``radial = z / ray_z`` with each pixel's ray under the CameraInfo's
  camera (``CameraModel.z_to_radial``), as the Azure Kinect importer does; a bag that says it
  holds radial distance (tofhil's own export, or ``depth_kind="radial"``) is stored as it is.
* an IR / amplitude image (``mono16``, ``16UC1``, ``mono8``, ``8UC1``, ``32FC1``) and an
  optional confidence image, paired with the depth images by header stamp: the same stamp,
  or the nearest within half a frame period (the median step between depth stamps); a depth
  image without its partners is left out, and what was left out is counted.
* ``sensor_msgs/msg/CameraInfo``: K, D, width, height and the distortion model, mapped by
  :func:`lens_from_camera_info` (the one place that says which models tofhil takes:
  ``plumb_bob``, ``rational_polynomial``, ``equidistant``).
* frame timestamps: the header stamps, in seconds.

Topics are found when that is unambiguous (one depth-like image topic, one CameraInfo topic,
or one beside the depth topic); otherwise the error lists the image topics with their
encodings. TF and every other topic are ignored.

The writer (:func:`write_session_mcap`) puts a session's depth (32FC1 metres, radial as
the session stores it, or z on request; the kind is in the topic name and in the MCAP
metadata record ``tofhil``), amplitude, CameraInfo and a point cloud per frame as ROS 2
messages that Foxglove opens; the application layer adds the twin's render and the residual
(``tofhil.app.export``).
"""

from __future__ import annotations

import dataclasses
import errno
import json
import math
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.frames import DepthFrame

MCAP_MAGIC = b"\x89MCAP0\r\n"

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"

#: Depth encodings: numpy type and metres per unit.
DEPTH_ENCODINGS: dict[str, tuple[str, float]] = {"16UC1": ("u2", 1e-3), "32FC1": ("f4", 1.0)}
#: Encodings an amplitude / IR or confidence image may have (stored as float32 values).
VALUE_ENCODINGS: dict[str, str] = {"mono16": "u2", "16UC1": "u2", "mono8": "u1", "8UC1": "u1", "32FC1": "f4"}

#: The MCAP metadata record tofhil writes (and reads back: roles and depth kind per topic).
METADATA_NAME = "tofhil"
#: Stamps of a session without timestamps (ADI frames): frame i at i * this (s).
SYNTHETIC_PERIOD_S = 0.1
FRAME_ID = "tofhil_camera"
#: What a depth image may hold: radial distance along each pixel's ray, or z along the axis.
DEPTH_KINDS = ("radial", "z")


def check_depth_kind(kind: str | None) -> None:
    """``--depth-kind`` is radial or z (or None: the default)."""
    if kind is not None and kind not in DEPTH_KINDS:
        raise InputFileError(f"is {kind!r}", field="--depth-kind", expected=" or ".join(DEPTH_KINDS))

# --------------------------------------------------------------------------- message definitions
_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
_SEP = "=" * 80 + "\n"
IMAGE_DEF = ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
             "uint32 step\nuint8[] data\n" + _SEP + _HEADER + _SEP + _TIME)
CAMERA_INFO_DEF = ("std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n"
                   "float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
                   "sensor_msgs/RegionOfInterest roi\n" + _SEP + _HEADER + _SEP + _TIME + _SEP
                   + "MSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\n"
                     "uint32 width\nbool do_rectify\n")
POINT_CLOUD2_DEF = ("std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n"
                    "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"
                    + _SEP + _HEADER + _SEP + _TIME + _SEP
                    + "MSG: sensor_msgs/PointField\nuint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\n"
                      "uint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\n"
                      "uint32 offset\nuint8 datatype\nuint32 count\n")


#: The fields tofhil reads of each message type (dotted: nested), checked when a message is
#: decoded: a bag whose schema lacks one (an Image without ``header``) is one line naming the
#: topic and the field, not an AttributeError later.
READ_FIELDS = {
    IMAGE: ("header.stamp.sec", "header.stamp.nanosec", "header.frame_id", "height", "width", "encoding",
            "is_bigendian", "step", "data"),
    CAMERA_INFO: ("header.stamp.sec", "header.stamp.nanosec", "header.frame_id", "height", "width",
                  "distortion_model", "d", "k", "p"),
}


def missing_field(msg: Any, kind: str) -> str | None:
    """The first field of :data:`READ_FIELDS` ``msg`` lacks (None: it has them all)."""
    for dotted in READ_FIELDS.get(kind, ()):
        obj = msg
        parts = dotted.split(".")
        for i, part in enumerate(parts):
            if not hasattr(obj, part):
                return ".".join(parts[:i + 1])  # "header", not "header.stamp.sec"
            obj = getattr(obj, part)
    return None


def message_type(schema_name: str) -> str:
    """``sensor_msgs/Image`` and ``sensor_msgs/msg/Image`` -> ``sensor_msgs/msg/Image``."""
    parts = schema_name.split("/")
    return f"{parts[0]}/msg/{parts[-1]}" if len(parts) in (2, 3) else schema_name


# --------------------------------------------------------------------------- camera model
#: tofhil's lens model -> CameraInfo.distortion_model (REP 104 names; D in the same order).
ROS_DISTORTION_MODEL = {"plumb_bob": "plumb_bob", "rational": "rational_polynomial", "fisheye": "equidistant"}


def lens_from_camera_info(model: str, d: Sequence[float], *, source: str | Path,
                          topic: str = "") -> tuple[str, tuple[float, ...]]:
    """A CameraInfo's distortion as tofhil's lens model ``(model, dist)`` (:mod:`tofhil.lens_models`).

    * ``plumb_bob`` (0, 4 or 5 coefficients), and an empty model with no or zero
      coefficients (a pinhole): ``plumb_bob`` ``(k1, k2, p1, p2, k3)``, exactly;
    * ``rational_polynomial`` (8 or more: ``k1, k2, p1, p2, k3, k4, k5, k6``, then OpenCV's
      thin prism ``s1..s4`` and tilt ``tau_x, tau_y``): ``plumb_bob`` when k4..k6 and the rest
      are zero (the same lens, exactly), else ``rational`` with 8 coefficients, or 12 when a
      thin-prism term is in use; a tilted sensor (tau nonzero) is refused;
    * ``equidistant`` (4: ``k1..k4``, OpenCV's fisheye, as ``camera_calibration`` writes it):
      ``fisheye``, exactly.

    Anything else is refused naming ``CameraInfo.distortion_model`` or ``CameraInfo.d``."""
    where = f"{topic}: CameraInfo.distortion_model" if topic else "CameraInfo.distortion_model"
    d_field = f"{topic}: CameraInfo.d" if topic else "CameraInfo.d"
    supported = "plumb_bob, rational_polynomial or equidistant (OpenCV's 5-parameter, rational and fisheye models)"
    coeffs = [float(v) for v in d]
    if not all(math.isfinite(v) for v in coeffs):
        raise InputFileError(f"D holds non-finite values {coeffs}", file=source, field=d_field, expected="finite numbers")
    if model == "plumb_bob" or (model == "" and not any(coeffs)):
        if len(coeffs) not in (0, 4, 5):
            raise InputFileError(f"plumb_bob with {len(coeffs)} coefficients", file=source, field=d_field,
                                 expected="5 (k1, k2, p1, p2, k3), or 4 (k3 = 0)")
        return "plumb_bob", tuple(coeffs + [0.0] * (5 - len(coeffs)))
    if model == "rational_polynomial":
        if len(coeffs) < 8:
            raise InputFileError(f"rational_polynomial with {len(coeffs)} coefficients", file=source, field=d_field,
                                 expected="8 or more (k1, k2, p1, p2, k3, k4, k5, k6, ...)")
        if any(coeffs[12:]):
            raise InputFileError(f"rational_polynomial with a tilted sensor (tau_x, tau_y = {coeffs[12:]})",
                                 file=source, field=d_field,
                                 expected="k1..k6, p1, p2 and the thin prism s1..s4 (no tilt model in tofhil)")
        if not any(coeffs[5:]):
            return "plumb_bob", tuple(coeffs[:5])
        return "rational", tuple(coeffs[:12] if any(coeffs[8:12]) else coeffs[:8])
    if model == "equidistant":
        if len(coeffs) != 4:
            raise InputFileError(f"equidistant with {len(coeffs)} coefficients", file=source, field=d_field,
                                 expected="4 (k1, k2, k3, k4: OpenCV's fisheye model)")
        return "fisheye", tuple(coeffs)
    raise InputFileError(f"is {model!r}", file=source, field=where, expected=supported)


def camera_from_info(info: Any, *, source: str | Path, topic: str = "", name: str = "") -> CameraModel:
    """A ``sensor_msgs/msg/CameraInfo`` as a :class:`CameraModel` (K, D, width, height)."""
    def bad(fld: str, message: str, expected: str) -> InputFileError:
        return InputFileError(message, file=source, field=f"{topic}: CameraInfo.{fld}" if topic else f"CameraInfo.{fld}",
                              expected=expected)

    k = [float(v) for v in info.k]
    if len(k) != 9 or not all(math.isfinite(v) for v in k):
        raise bad("k", f"is {k}", "9 finite numbers (row-major 3 x 3 intrinsics)")
    if not any(k):
        raise bad("k", "is all zero (an uncalibrated camera)", "calibrated intrinsics, or pass --camera")
    fx, skew, cx, _, fy, cy = k[0], k[1], k[2], k[3], k[4], k[5]
    if not (fx > 0 and fy > 0):
        raise bad("k", f"has fx = {fx}, fy = {fy}", "positive focal lengths")
    if abs(skew) > 1e-9 * fx or k[3] or k[6] or k[7] or k[8] != 1.0:
        raise bad("k", f"is {k}", "[fx, 0, cx, 0, fy, cy, 0, 0, 1] (no skew)")
    if info.binning_x not in (0, 1) or info.binning_y not in (0, 1):
        raise bad("binning_x", f"binning {info.binning_x} x {info.binning_y}", "no binning (0 or 1)")
    roi = info.roi
    if roi.x_offset or roi.y_offset or (roi.width and roi.width != info.width) or (roi.height and roi.height != info.height):
        raise bad("roi", f"is {roi.width}x{roi.height} at ({roi.x_offset}, {roi.y_offset})", "the full image")
    if info.width <= 0 or info.height <= 0:
        raise bad("width", f"is {info.width}x{info.height}", "the image size in pixels")
    model, dist = lens_from_camera_info(str(info.distortion_model), info.d, source=source, topic=topic)
    return CameraModel(width=int(info.width), height=int(info.height), fx=fx, fy=fy, cx=cx, cy=cy, dist=dist,
                       distortion_model=model, name=name)


def camera_info_message(camera: CameraModel, stamp_ns: int, frame_id: str = FRAME_ID) -> dict[str, Any]:
    """A CameraInfo of ``camera``: its lens model under the ROS name (``plumb_bob``,
    ``rational_polynomial``, ``equidistant``) with D in OpenCV's order, which
    :func:`lens_from_camera_info` reads back exactly; R = I, P = [K | 0] (not rectified)."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    return {"header": _header(stamp_ns, frame_id), "height": camera.height, "width": camera.width,
            "distortion_model": ROS_DISTORTION_MODEL[camera.distortion_model], "d": list(camera.dist),
            "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            "p": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0], "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}


# --------------------------------------------------------------------------- images
def image_array(msg: Any, encodings: dict[str, Any], *, source: str | Path, topic: str, what: str) -> np.ndarray:
    """An Image message's pixels ``[H, W]`` in native byte order (row padding removed)."""
    enc = str(msg.encoding)
    if enc not in encodings:
        raise InputFileError(f"encoding is {enc!r}", file=source, field=f"{topic}: Image.encoding",
                             expected=f"a {what} image: " + ", ".join(encodings))
    code = encodings[enc]
    dt = np.dtype(code[0] if isinstance(code, tuple) else code).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * dt.itemsize
    data = msg.data
    if h <= 0 or w <= 0 or step < row or len(data) != step * h:
        raise InputFileError(f"a {w}x{h} {enc} image has step {step} and {len(data)} bytes", file=source,
                             field=f"{topic}: Image.data",
                             expected=f"step >= {row} and step x height bytes")
    rows = np.frombuffer(data, dtype=np.uint8, count=step * h).reshape(h, step)[:, :row]
    return np.ascontiguousarray(rows).view(dt).reshape(h, w).astype(dt.newbyteorder("="))


def depth_image(msg: Any, *, source: str | Path, topic: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(distance in metres float64 with 0 where invalid, valid, unit in file) of a depth Image."""
    raw = image_array(msg, DEPTH_ENCODINGS, source=source, topic=topic, what="depth (16UC1 mm or 32FC1 m)")
    _, scale = DEPTH_ENCODINGS[str(msg.encoding)]
    if raw.dtype.kind == "u":
        valid = raw > 0
        metres = raw.astype(np.float64) * scale
    else:
        valid = np.isfinite(raw) & (raw > 0)
        metres = raw.astype(np.float64)
    return np.where(valid, metres, 0.0), valid, "mm" if scale != 1.0 else "m"


def _header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": frame_id}


def _stamp_s(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def _raw_stamp_s(data: bytes) -> float | None:
    """The header stamp of a CDR message (plain CDR, either byte order) without decoding it."""
    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        return None
    sec, nsec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
    return sec + nsec * 1e-9


# --------------------------------------------------------------------------- reading a bag
@dataclass
class ImageTopic:
    topic: str
    count: int = 0
    encoding: str = ""
    width: int = 0
    height: int = 0
    frame_id: str = ""
    stamps: list[float] = field(default_factory=list)

    def describe(self) -> str:
        return f"{self.topic} ({self.encoding}, {self.width}x{self.height}, {self.count} message(s))"


@dataclass
class BagIndex:
    """What pass 1 over a bag found: the image and CameraInfo topics, their stamps, the
    CameraInfo messages, tofhil's metadata record, and whether the file was cut short."""

    path: Path
    images: dict[str, ImageTopic]
    infos: dict[str, list[Any]]
    other_topics: dict[str, str]
    metadata: dict[str, Any] | None
    truncated: str = ""
    profile: str = ""
    library: str = ""


class _Bag:
    """An MCAP file read message by message, twice at most (index, then frames)."""

    def __init__(self, path: Path, salvage: bool) -> None:
        self.path = path
        self.salvage = salvage
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(8)
            fh.seek(max(size - 8, 0))
            tail = fh.read(8)
        if head != MCAP_MAGIC:
            raise InputFileError("is not an MCAP file", file=path, field="magic",
                                 expected="an MCAP recording (ROS 2 bag), starting 89 4D 43 41 50 30 0D 0A")
        self.truncated = "" if size >= 16 and tail == MCAP_MAGIC else (
            "it does not end with the MCAP footer and magic (a recording cut short, or still being written)")
        if self.truncated and not salvage:
            raise InputFileError(f"is truncated: {self.truncated}", file=path, field="MCAP footer",
                                 expected="a complete recording, or --salvage to import its complete messages")
        self.header: Any = None
        self._decoders: dict[int, Callable[[bytes], Any]] = {}

    def _reader(self, fh: IO[bytes]) -> Any:
        from mcap.reader import NonSeekingReader, SeekingReader

        if self.truncated:
            return NonSeekingReader(fh, validate_crcs=True)
        return SeekingReader(fh, validate_crcs=True)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[Any, Any, Any]]:
        """``(schema, channel, message)`` in file order; a damaged file is one clear error (a
        truncated one, salvaged, just ends at its last complete record)."""
        with open(self.path, "rb") as fh:
            it = self._reader(fh).iter_messages(topics=None if topics is None else list(topics), log_time_order=False)
            while True:
                try:
                    item = next(it)
                except StopIteration:
                    return
                except Exception as exc:  # the mcap reader's errors on a damaged file, whatever their type
                    if self.truncated:
                        return  # salvage: the records before the cut are all there is
                    raise InputFileError(f"cannot be read ({type(exc).__name__}: {exc})", file=self.path,
                                         field="MCAP records", expected="an undamaged MCAP file") from None
                yield item

    def decode(self, schema: Any, channel: Any, message: Any, ordinal: int) -> Any:
        decoder = self._decoders.get(channel.id)
        if decoder is None:
            from mcap_ros2.decoder import DecoderFactory

            try:
                decoder = DecoderFactory().decoder_for(channel.message_encoding, schema)
            except Exception as exc:
                decoder = None
                why = f" ({exc})"
            else:
                why = ""
            if decoder is None:
                raise InputFileError(f"cannot be decoded{why}", file=self.path, field=f"{channel.topic}: schema",
                                     expected="a CDR-encoded ROS 2 message with its ros2msg schema")
            self._decoders[channel.id] = decoder
        try:
            msg = decoder(message.data)
        except Exception as exc:
            raise InputFileError(f"message {ordinal} cannot be decoded ({type(exc).__name__}: {exc})",
                                 file=self.path, field=f"{channel.topic}: {schema.name}",
                                 expected="a well-formed CDR message") from None
        kind = message_type(schema.name)
        lacking = missing_field(msg, kind)
        if lacking is not None:
            raise InputFileError("the message schema has no such field", file=self.path,
                                 field=f"{channel.topic}: {schema.name}.{lacking}",
                                 expected=f"a {kind} as ROS 2 defines it ({', '.join(READ_FIELDS[kind])})")
        return msg

    def metadata(self) -> dict[str, Any] | None:
        """tofhil's metadata record, if the bag has one (its JSON values decoded)."""
        if self.truncated:
            return None
        from mcap.reader import SeekingReader

        try:
            with open(self.path, "rb") as fh:
                reader = SeekingReader(fh)
                records = [m for m in reader.iter_metadata() if m.name == METADATA_NAME]
                header = reader.get_header()
        except Exception as exc:
            raise InputFileError(f"cannot be read ({type(exc).__name__}: {exc})", file=self.path,
                                 field="MCAP summary", expected="an undamaged MCAP file") from None
        self.header = header
        if not records:
            return None
        out: dict[str, Any] = {}
        for key, value in records[0].metadata.items():
            try:
                out[key] = json.loads(value)
            except json.JSONDecodeError:
                out[key] = value
        return out


def index_bag(bag: _Bag) -> BagIndex:
    """Pass 1: every Image and CameraInfo topic, each image message's header stamp (the first
    one decoded for its encoding and size), every CameraInfo message decoded."""
    images: dict[str, ImageTopic] = {}
    infos: dict[str, list[Any]] = {}
    other: dict[str, str] = {}
    for schema, channel, message in bag.messages():
        kind = message_type(schema.name) if schema is not None else ""
        topic = channel.topic
        if kind == IMAGE:
            t = images.setdefault(topic, ImageTopic(topic))
            stamp = _raw_stamp_s(message.data) if t.count else None
            if stamp is None:
                msg = bag.decode(schema, channel, message, t.count)
                stamp = _stamp_s(msg.header)
                if not t.count:
                    t.encoding, t.width, t.height = str(msg.encoding), int(msg.width), int(msg.height)
                    t.frame_id = str(msg.header.frame_id)
            t.stamps.append(stamp)
            t.count += 1
        elif kind == CAMERA_INFO:
            infos.setdefault(topic, []).append(bag.decode(schema, channel, message, len(infos.get(topic, []))))
        else:
            other.setdefault(topic, kind or "(no schema)")
    meta = bag.metadata()
    header = bag.header
    return BagIndex(bag.path, images, infos, other, meta, bag.truncated,
                    getattr(header, "profile", ""), getattr(header, "library", ""))


# --------------------------------------------------------------------------- finding topics
_AMPLITUDE_WORDS = {"ir", "infra", "infrared", "amplitude", "amp", "intensity", "brightness", "ab", "gray", "grey"}
_CONFIDENCE_WORDS = {"confidence", "conf"}


def _hint(topic: str) -> str:
    words = set(re.split(r"[^a-z0-9]+", topic.lower()))
    if words & _CONFIDENCE_WORDS:
        return "confidence"
    if words & _AMPLITUDE_WORDS:
        return "amplitude"
    return ""


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


@dataclass(frozen=True)
class Topics:
    depth: str
    amplitude: str | None
    confidence: str | None
    info: str | None
    depth_kind: str           #: "z" or "radial": what the depth image holds
    kind_source: str          #: why
    notes: tuple[str, ...] = ()


def _listing(index: BagIndex) -> str:
    return "; ".join(t.describe() for t in index.images.values()) or "none"


def find_topics(index: BagIndex, *, depth_topic: str | None = None, amplitude_topic: str | None = None,
                confidence_topic: str | None = None, info_topic: str | None = None,
                depth_kind: str | None = None, need_info: bool = True) -> Topics:
    """The topics to import: given ones checked, the others found when unambiguous."""
    src = index.path
    images = index.images
    notes: list[str] = []
    roles = {}
    if index.metadata and isinstance(index.metadata.get("topics"), dict):
        roles = {t: r for t, r in index.metadata["topics"].items() if isinstance(r, dict)}

    def given(topic: str, option: str) -> str:
        if topic not in images:
            raise InputFileError(f"no Image topic {topic!r}", file=src, field=option,
                                 expected=f"one of the bag's image topics: {_listing(index)}")
        return topic

    def by_role(role: str) -> str | None:
        found = [t for t, r in roles.items() if r.get("role") == role and t in images]
        return found[0] if len(found) == 1 else None

    # depth
    if depth_topic is not None:
        depth = given(depth_topic, "--depth-topic")
    elif (depth := by_role("depth")) is None:  # type: ignore[assignment]
        cands = [t.topic for t in images.values() if t.encoding in DEPTH_ENCODINGS and not _hint(t.topic)]
        if len(cands) != 1:
            what = "no depth-like image topic" if not cands else f"{len(cands)} depth-like image topics"
            raise InputFileError(f"{what} (16UC1 or 32FC1, not named like IR or confidence)", file=src,
                                 field="--depth-topic",
                                 expected=f"one depth topic named with --depth-topic; image topics: {_listing(index)}")
        depth = cands[0]
    dt = images[depth]
    if dt.encoding not in DEPTH_ENCODINGS:
        raise InputFileError(f"encoding is {dt.encoding!r}", file=src, field=f"{depth}: Image.encoding",
                             expected=f"a depth image: 16UC1 (mm) or 32FC1 (m); image topics: {_listing(index)}")

    def partner(option: str, topic: str | None, role: str, words: str) -> str | None:
        if topic is not None:
            t = given(topic, option)
        else:
            t = by_role(role)
            if t is None:
                cands = [i.topic for i in images.values() if i.topic != depth and i.encoding in VALUE_ENCODINGS
                         and (_hint(i.topic) == role or (role == "amplitude" and not _hint(i.topic)
                                                         and i.encoding in ("mono8", "mono16")))]
                if len(cands) > 1:
                    near = [c for c in cands if _namespace(_namespace(c)) == _namespace(_namespace(depth))]
                    cands = near if len(near) == 1 else cands
                if len(cands) > 1:
                    raise InputFileError(f"{len(cands)} {words} image topics: {', '.join(cands)}", file=src,
                                         field=option, expected=f"one named with {option}; image topics: "
                                                                + _listing(index))
                t = cands[0] if cands else None
        if t is not None:
            if images[t].encoding not in VALUE_ENCODINGS:
                raise InputFileError(f"encoding is {images[t].encoding!r}", file=src, field=f"{t}: Image.encoding",
                                     expected=f"a {words} image: " + ", ".join(VALUE_ENCODINGS))
            if (images[t].width, images[t].height) != (dt.width, dt.height):
                raise InputFileError(f"is {images[t].width}x{images[t].height}", file=src, field=f"{t}: Image.width",
                                     expected=f"the depth image's size {dt.width}x{dt.height} ({depth})")
        return t

    amplitude = partner("--amplitude-topic", amplitude_topic, "amplitude", "IR / amplitude")
    if amplitude is None:
        notes.append("no IR / amplitude image topic: the session has depth only")
    confidence = partner("--confidence-topic", confidence_topic, "confidence", "confidence")

    # camera info
    info = None
    if info_topic is not None:
        if info_topic not in index.infos:
            raise InputFileError(f"no CameraInfo topic {info_topic!r}", file=src, field="--info-topic",
                                 expected="one of: " + (", ".join(index.infos) or "none (the bag has no CameraInfo)"))
        info = info_topic
    elif not need_info:
        pass  # a camera was given: no CameraInfo is looked for
    elif index.infos:
        found = [t for t, r in roles.items() if r.get("role") == "camera_info" and t in index.infos]
        cands = found or list(index.infos)
        if len(cands) > 1:
            near = [c for c in cands if _namespace(c) == _namespace(depth)]
            cands = near if len(near) == 1 else cands
        if len(cands) > 1:
            raise InputFileError(f"{len(cands)} CameraInfo topics: {', '.join(cands)}", file=src, field="--info-topic",
                                 expected=f"the depth camera's, named with --info-topic (depth topic {depth})")
        info = cands[0]
    else:
        raise InputFileError(f"has no sensor_msgs/msg/CameraInfo topic (image topics: {_listing(index)})", file=src,
                             field="CameraInfo", expected="the depth camera's CameraInfo, or a camera given with --camera")

    # what the depth holds
    if depth_kind is not None:
        kind, why = depth_kind, "given (--depth-kind)"
    elif roles.get(depth, {}).get("kind") in ("z", "radial"):
        kind, why = roles[depth]["kind"], "the bag's tofhil metadata record"
    else:
        kind, why = "z", "ROS convention (REP 118: depth images hold z along the optical axis)"
    return Topics(depth, amplitude, confidence, info, kind, why, tuple(notes))


# --------------------------------------------------------------------------- pairing
@dataclass
class Pairing:
    """Which message of a partner topic goes with each depth message (-1: none)."""

    partner: np.ndarray
    exact: int
    nearest: int
    unpaired_depth: int
    unpaired_partner: int
    tolerance_s: float

    def summary(self) -> dict[str, Any]:
        return {"paired_exact": self.exact, "paired_nearest": self.nearest, "depth_without_partner": self.unpaired_depth,
                "partner_without_depth": self.unpaired_partner, "tolerance_s": self.tolerance_s}


def frame_period_s(stamps: Sequence[float]) -> float:
    """The median step between distinct sorted stamps (NaN with fewer than two)."""
    t = np.unique(np.asarray(stamps, dtype=np.float64))
    return float(np.median(np.diff(t))) if t.size >= 2 else math.nan


def pair_by_stamp(depth_s: Sequence[float], other_s: Sequence[float], period_s: float) -> Pairing:
    """Pair each depth stamp with the other topic's nearest stamp: exact, or within half a frame
    period (``period_s``; NaN: exact only). One-to-one: a message taken twice goes to the
    closer depth image."""
    d = np.asarray(depth_s, dtype=np.float64)
    o = np.asarray(other_s, dtype=np.float64)
    tol = period_s / 2 if math.isfinite(period_s) else 0.0
    best = np.full(d.size, -1, dtype=np.int64)
    gap = np.full(d.size, np.inf)
    if o.size:
        order = np.argsort(o, kind="stable")
        so = o[order]
        pos = np.searchsorted(so, d)
        for cand in (pos - 1, pos):
            ok = (cand >= 0) & (cand < so.size)
            c = np.clip(cand, 0, so.size - 1)
            g = np.where(ok, np.abs(so[c] - d), np.inf)
            better = g < gap
            best[better], gap[better] = order[c[better]], g[better]
    accept = (gap == 0) | (gap < tol)
    best[~accept] = -1
    # one-to-one: where two depth stamps took the same message, the closer keeps it
    for j in np.unique(best[best >= 0]):
        takers = np.flatnonzero(best == j)
        if takers.size > 1:
            keep = takers[np.argmin(gap[takers])]
            best[takers[takers != keep]] = -1
    paired = best >= 0
    exact = int(np.sum(paired & (gap == 0)))
    return Pairing(best, exact, int(paired.sum()) - exact, int((~paired).sum()), int(o.size - paired.sum()), tol)


# --------------------------------------------------------------------------- the import
@dataclass
class BagImport:
    """A bag ready to import: the camera, the frames (generated on iteration) and what the
    session's ``device`` attribute records."""

    camera: CameraModel
    n_frames: int
    device: dict[str, Any]
    notes: list[str]
    frames: Callable[[], Iterator[Any]]


def _info_camera(index: BagIndex, topics: Topics, src: Path, notes: list[str]) -> CameraModel:
    """The camera of the chosen CameraInfo topic: one model for the whole recording, or an error;
    tofhil's own export gives back the session's camera (its name and pixel pitch too)."""
    assert topics.info is not None
    msgs = index.infos[topics.info]
    first = msgs[0]
    cam = camera_from_info(first, source=src, topic=topics.info, name=f"ros2:{topics.info}")
    for i, m in enumerate(msgs[1:], 1):
        if (list(m.k), list(m.d), m.distortion_model, m.width, m.height) != (
                list(first.k), list(first.d), first.distortion_model, first.width, first.height):
            raise InputFileError(f"message {i} differs from the first (K, D, model or size)", file=src,
                                 field=f"{topics.info}: CameraInfo",
                                 expected="one camera model for the recording, or pass --camera")
    depth_frame_id = index.images[topics.depth].frame_id
    if str(first.header.frame_id) != depth_frame_id:
        notes.append(f"CameraInfo frame_id {first.header.frame_id!r} differs from the depth image's "
                     f"{depth_frame_id!r}")
    meta = index.metadata or {}
    if isinstance(meta.get("camera"), dict):
        try:
            recorded = CameraModel.from_dict(meta["camera"], source=src, prefix="tofhil metadata: camera.")
        except InputFileError:
            return cam
        if dataclasses.replace(recorded, name=cam.name, pixel_pitch_m=None) == cam:
            return recorded
    return cam


def _pair_partners(index: BagIndex, topics: Topics, src: Path,
                   notes: list[str]) -> tuple[list[int], dict[str, tuple[str, Pairing]]]:
    """The depth messages to import, in stamp order (those with every chosen partner), and each
    partner topic's pairing (:func:`pair_by_stamp`); what was left out goes to ``notes``."""
    d_stamps = np.asarray(index.images[topics.depth].stamps, dtype=np.float64)
    period = frame_period_s(d_stamps)
    partners: dict[str, tuple[str, Pairing]] = {}
    keep = np.ones(d_stamps.size, dtype=bool)
    for role, topic in (("amplitude", topics.amplitude), ("confidence", topics.confidence)):
        if topic is None:
            continue
        o_stamps = index.images[topic].stamps
        p = pair_by_stamp(d_stamps, o_stamps, period if math.isfinite(period) else frame_period_s(o_stamps))
        partners[role] = (topic, p)
        keep &= p.partner >= 0
        if p.unpaired_depth or p.unpaired_partner or p.nearest:
            notes.append(f"{role}: {p.exact} depth images paired by the same stamp, {p.nearest} by the nearest "
                         f"within {p.tolerance_s * 1e3:.3g} ms; {p.unpaired_depth} depth image(s) without one "
                         f"left out, {p.unpaired_partner} {role} image(s) without a depth image")
    plan = [int(i) for i in np.argsort(d_stamps, kind="stable") if keep[i]]
    if not plan:
        raise InputFileError("no depth image could be paired with its partner images", file=src,
                             field=f"{topics.depth}: header.stamp",
                             expected="IR / amplitude images with the depth images' stamps (or within half a frame period)")
    return plan, partners


def read_bag(path: str | Path, *, camera: CameraModel | None = None, depth_topic: str | None = None,
             amplitude_topic: str | None = None, confidence_topic: str | None = None, info_topic: str | None = None,
             depth_kind: str | None = None, salvage: bool = False) -> BagImport:
    """Index a ROS 2 bag, choose its topics, pair its images and build its camera model.

    ``camera`` replaces the CameraInfo's (which is then not needed); ``depth_kind`` ("z" or
    "radial") overrides what the depth images are taken to hold. The frames are decoded when
    ``BagImport.frames()`` is iterated (pass 2), so a long bag is not held in memory.
    """
    src = Path(path)
    check_depth_kind(depth_kind)
    bag = _Bag(src, salvage)
    index = index_bag(bag)
    if not index.images:
        raise InputFileError("has no sensor_msgs/msg/Image topic", file=src, field="topics",
                             expected="a depth image topic; topics: "
                                      + (", ".join(f"{t} ({k})" for t, k in index.other_topics.items()) or "none"))
    topics = find_topics(index, depth_topic=depth_topic, amplitude_topic=amplitude_topic,
                         confidence_topic=confidence_topic, info_topic=info_topic, depth_kind=depth_kind,
                         need_info=camera is None)
    notes = list(topics.notes)
    if camera is not None and index.infos:
        notes.append(f"CameraInfo ({', '.join(index.infos)}) not used: the camera was given")
    if index.truncated:
        notes.append(f"truncated bag ({index.truncated}): imported the messages before the cut")
    dt = index.images[topics.depth]
    cam = camera if camera is not None else _info_camera(index, topics, src, notes)
    if cam.shape != (dt.height, dt.width):
        fld = "--camera" if camera is not None else f"{topics.info}: CameraInfo.width"
        raise InputFileError(f"camera is {cam.width}x{cam.height}", file=src, field=fld,
                             expected=f"the depth image's size {dt.width}x{dt.height} ({topics.depth})")

    plan, partners = _pair_partners(index, topics, src, notes)
    d_stamps = dt.stamps

    encodings = {topics.depth: dt.encoding} | {t: index.images[t].encoding for t, _ in partners.values()}
    device: dict[str, Any] = {
        "vendor": "", "model": "ROS 2 recording (MCAP)", "frame_id": dt.frame_id,
        "topics": {"depth": topics.depth, "amplitude": topics.amplitude, "confidence": topics.confidence,
                   "camera_info": topics.info},
        "encodings": encodings,
        "depth_kind_in_file": topics.depth_kind, "depth_kind_source": topics.kind_source,
        "depth_unit_in_file": "mm" if dt.encoding == "16UC1" else "m",
        "depth_conversion": ("stored as recorded (radial)" if topics.depth_kind == "radial"
                             else "radial = z / ray_z with the camera's rays (CameraModel.z_to_radial)"),
        "camera_source": (f"CameraInfo on {topics.info} ({index.infos[topics.info][0].distortion_model or 'none'})"
                          if camera is None and topics.info else "given"),
        "amplitude": (f"{index.images[topics.amplitude].encoding} values of {topics.amplitude}, device units"
                      if topics.amplitude else "none in the bag"),
        "timestamps": "header stamps (s)",
        "sequence": "index of the depth message in the bag",
        "pairing": {role: {"topic": t} | p.summary() for role, (t, p) in partners.items()},
        "mcap_profile": index.profile, "mcap_library": index.library,
        "other_topics": index.other_topics,
    }
    if index.metadata is not None:
        device["tofhil_export"] = index.metadata
    if len(plan) < len(d_stamps):
        notes.append(f"imported {len(plan)} of {len(d_stamps)} depth images")

    def frames() -> Iterator[Any]:
        want = {(topics.depth, i) for i in plan}  # (topic, ordinal in the bag) of every message used
        want |= {(t, int(p.partner[i])) for t, p in partners.values() for i in plan}
        got: dict[tuple[str, int], Any] = {}
        counts: dict[str, int] = {}
        nxt = 0
        selected = [topics.depth] + [t for t, _ in partners.values()]
        for schema, channel, message in bag.messages(selected):
            t = channel.topic
            k = counts.get(t, 0)
            counts[t] = k + 1
            if (t, k) not in want:
                continue
            got[(t, k)] = bag.decode(schema, channel, message, k)
            while nxt < len(plan):
                i = plan[nxt]
                keys = [(topics.depth, i)] + [(tp, int(p.partner[i])) for tp, p in partners.values()]
                if not all(key in got for key in keys):
                    break
                parts = [got.pop(key) for key in keys]
                yield _frame(parts, list(partners), topics, cam, src, i)
                nxt += 1
        if nxt < len(plan):
            raise InputFileError(f"ended after {nxt} of {len(plan)} frames (the file changed while read?)", file=src,
                                 field="MCAP records", expected="the messages indexed in the first pass")

    return BagImport(cam, len(plan), device, notes, frames)


def _frame(parts: list[Any], roles: list[str], topics: Topics, cam: CameraModel, src: Path,
           ordinal: int) -> tuple[None, DepthFrame]:
    """(None, the depth frame) of a depth message and its partners' (``roles`` order)."""
    depth_msg = parts[0]
    metres, valid, _ = depth_image(depth_msg, source=src, topic=topics.depth)
    if metres.shape != cam.shape:
        raise InputFileError(f"message {ordinal} is {metres.shape[1]}x{metres.shape[0]}", file=src,
                             field=f"{topics.depth}: Image.width", expected=f"{cam.width}x{cam.height} as the first")
    if topics.depth_kind == "radial":
        radial = metres.astype(np.float32)  # 32FC1: float32 -> float64 -> float32 is bit for bit
    else:
        radial = np.where(valid, cam.z_to_radial(metres), 0.0).astype(np.float32)
    extra: dict[str, np.ndarray] = {}
    for role, msg in zip(roles, parts[1:]):
        topic = topics.amplitude if role == "amplitude" else topics.confidence
        arr = image_array(msg, VALUE_ENCODINGS, source=src, topic=str(topic), what=role)
        if arr.shape != cam.shape:
            raise InputFileError(f"a message is {arr.shape[1]}x{arr.shape[0]}", file=src, field=f"{topic}: Image.width",
                                 expected=f"the depth image's size {cam.width}x{cam.height}")
        extra[role] = arr.astype(np.float32)
    return None, DepthFrame(distance_m=radial, kind="radial", camera=cam, amplitude=extra.get("amplitude"),
                            confidence=extra.get("confidence"), valid=valid, timestamp_s=_stamp_s(depth_msg.header),
                            sequence=ordinal)


# --------------------------------------------------------------------------- writing a bag
class Ros2BagWriter:
    """ROS 2 ``Image``, ``CameraInfo`` and ``PointCloud2`` messages into an MCAP stream, with
    mcap-ros2-support's writer (CDR, ``ros2msg`` schemas: what rosbag2 writes, Foxglove reads)."""

    def __init__(self, stream: IO[bytes]) -> None:
        from mcap_ros2.writer import Writer

        self._w = Writer(stream)
        self._image = self._w.register_msgdef(IMAGE, IMAGE_DEF)
        self._info = self._w.register_msgdef(CAMERA_INFO, CAMERA_INFO_DEF)
        self._cloud = self._w.register_msgdef(POINT_CLOUD2, POINT_CLOUD2_DEF)
        self.counts: dict[str, int] = {}

    def _write(self, topic: str, schema: Any, msg: dict[str, Any], stamp_ns: int) -> None:
        n = self.counts.get(topic, 0)
        self._w.write_message(topic, schema, msg, log_time=stamp_ns, publish_time=stamp_ns, sequence=n)
        self.counts[topic] = n + 1

    def image(self, topic: str, stamp_ns: int, array: np.ndarray, encoding: str, frame_id: str = FRAME_ID) -> None:
        dtypes = {"32FC1": "<f4", "16UC1": "<u2", "mono16": "<u2", "mono8": "u1", "8UC1": "u1"}
        a = np.ascontiguousarray(array, dtype=dtypes[encoding])
        h, w = a.shape
        self._write(topic, self._image, {"header": _header(stamp_ns, frame_id), "height": h, "width": w,
                                         "encoding": encoding, "is_bigendian": 0, "step": w * a.itemsize,
                                         "data": a.tobytes()}, stamp_ns)

    def camera_info(self, topic: str, stamp_ns: int, camera: CameraModel, frame_id: str = FRAME_ID) -> None:
        self._write(topic, self._info, camera_info_message(camera, stamp_ns, frame_id), stamp_ns)

    def point_cloud(self, topic: str, stamp_ns: int, points: np.ndarray, intensity: np.ndarray | None,
                    frame_id: str = FRAME_ID) -> None:
        """An unorganised cloud of float32 x, y, z (m, camera frame) and intensity (NaN if unknown)."""
        n = len(points)
        rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
        rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
        rec["intensity"] = np.nan if intensity is None else intensity
        fields = [{"name": name, "offset": 4 * i, "datatype": 7, "count": 1}
                  for i, name in enumerate(("x", "y", "z", "intensity"))]
        self._write(topic, self._cloud, {"header": _header(stamp_ns, frame_id), "height": 1, "width": n,
                                         "fields": fields, "is_bigendian": False, "point_step": 16,
                                         "row_step": 16 * n, "data": rec.tobytes(), "is_dense": True}, stamp_ns)

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        self._w.add_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})

    def finish(self) -> None:
        self._w.finish()


@dataclass
class ExtraImage:
    """An image beside the session's own on every frame (the twin's render, a residual)."""

    topic: str                      #: for a distance image, the kind is appended: ``/tofhil/twin/depth/radial``
    role: str
    image: np.ndarray               #: float32 [H, W]; NaN where invalid
    distance: bool = False          #: radial metres: written as the export's depth kind
    cloud_topic: str | None = None  #: also as a point cloud (a distance image)
    intensity: np.ndarray | None = None
    unit: str = ""


@dataclass
class McapExport:
    out: Path
    n_frames: int
    topics: dict[str, dict[str, Any]]
    counts: dict[str, int]
    notes: list[str] = field(default_factory=list)


#: OS errors of writing the bag (disk full, file-size limit, read-only, permission, I/O).
_WRITE_ERRNOS = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO}


def _stamps_ns(timestamps: Sequence[float]) -> tuple[list[int], str]:
    t = np.asarray(timestamps, dtype=np.float64)
    if t.size and np.all(np.isfinite(t)) and np.all(t >= 0):
        return [int(round(v * 1e9)) for v in t], "frames/timestamp_s"
    return ([int(round(i * SYNTHETIC_PERIOD_S * 1e9)) for i in range(t.size)],
            f"synthetic: the session's timestamps are not all finite and >= 0; frame i at i * {SYNTHETIC_PERIOD_S} s")


def write_session_mcap(session_path: str | Path, out: str | Path, *, force: bool = False, depth_kind: str = "radial",
                       extra: Callable[[int, Any], Sequence[ExtraImage]] | None = None,
                       metadata: dict[str, Any] | None = None,
                       on_frame: Callable[[int, int], None] | None = None) -> McapExport:
    """Write a session as a ROS 2 MCAP bag ``out``: per frame the depth (32FC1 metres on
    ``/tofhil/depth/radial``, or z on ``/tofhil/depth/z`` with ``depth_kind="z"``; NaN where
    invalid), the amplitude (32FC1), the confidence when the session has it, a CameraInfo and
    a point cloud (``/tofhil/points``), plus what ``extra(i, depth_frame)`` adds. A session
    with raw taps only is demodulated (``tofhil.depth.depth_from_raw``).

    The file is written under a temporary name and renamed when complete; nothing existing
    is replaced without ``force``.
    """
    from tofhil import __version__
    from tofhil.depth import depth_from_raw
    from tofhil.outputs import atomic_path, check_new_path
    from tofhil.session import open_session

    check_depth_kind(depth_kind)
    src, out = Path(session_path), Path(out)
    if out.exists() and out.resolve() == src.resolve():
        raise InputFileError("the output must differ from the input", file=out, field="--out")
    check_new_path(out, force)
    with open_session(src, need_frames=True) as s:
        cam = s.camera
        n = s.n_frames
        if n == 0:
            raise InputFileError("has no complete frames", file=src, field="n_frames", expected="at least one frame")
        if not s.has_depth and not s.has_raw:
            raise InputFileError("has no depth and no raw taps", file=src, field="depth/radial_m")
        f = s._file  # every frame's timestamp at once (as the replay driver reads them)
        stamps, stamp_source = _stamps_ns(f["frames/timestamp_s"][:n])
        ray_z = cam.ray_z.astype(np.float32)

        def as_kind(radial: np.ndarray) -> np.ndarray:
            return radial if depth_kind == "radial" else (radial * ray_z).astype(np.float32)

        depth_t = f"/tofhil/depth/{depth_kind}"
        topics: dict[str, dict[str, Any]] = {
            depth_t: {"role": "depth", "kind": depth_kind, "unit": "m", "encoding": "32FC1",
                      "invalid": "NaN"},
            "/tofhil/amplitude": {"role": "amplitude", "unit": "device amplitude (session depth/amplitude)",
                                  "encoding": "32FC1"},
            "/tofhil/camera_info": {"role": "camera_info",
                                    "distortion_model": ROS_DISTORTION_MODEL[cam.distortion_model]},
            "/tofhil/points": {"role": "points", "fields": "x y z intensity (float32; m, amplitude)"},
        }
        try:
            with atomic_path(out) as tmp:
                with open(tmp, "wb") as fh:
                    w = Ros2BagWriter(fh)
                    for i in range(n):
                        d = s.depth_frame(i) if s.has_depth else depth_from_raw(s.raw_frame(i))
                        t = stamps[i]
                        valid = cam.valid_mask(d.radial_m, d.valid)
                        radial = np.where(valid, d.radial_m, np.nan).astype(np.float32)
                        amp = (np.full(cam.shape, np.nan, np.float32) if d.amplitude is None
                               else np.asarray(d.amplitude, dtype=np.float32))
                        w.camera_info("/tofhil/camera_info", t, cam)
                        w.image(depth_t, t, as_kind(radial), "32FC1")
                        w.image("/tofhil/amplitude", t, amp, "32FC1")
                        if d.confidence is not None:
                            topics.setdefault("/tofhil/confidence", {"role": "confidence", "encoding": "32FC1",
                                                                     "unit": "the device's own"})
                            w.image("/tofhil/confidence", t, np.asarray(d.confidence, dtype=np.float32), "32FC1")
                        w.point_cloud("/tofhil/points", t, cam.points(radial, "radial", valid), amp[valid])
                        for e in (extra(i, d) if extra is not None else ()):
                            topic = f"{e.topic}/{depth_kind}" if e.distance else e.topic
                            topics.setdefault(topic, {"role": e.role, "encoding": "32FC1", "unit": e.unit}
                                              | ({"kind": depth_kind, "invalid": "NaN"} if e.distance else {}))
                            img = np.asarray(e.image, dtype=np.float32)
                            w.image(topic, t, as_kind(img) if e.distance else img, "32FC1")
                            if e.cloud_topic is not None:
                                ok = np.isfinite(img) & (img > 0)
                                topics.setdefault(e.cloud_topic, {"role": f"{e.role}_points",
                                                                  "fields": "x y z intensity (float32)"})
                                inten = None if e.intensity is None else np.asarray(e.intensity, np.float32)[ok]
                                w.point_cloud(e.cloud_topic, t, cam.points(np.where(ok, img, 0.0), "radial", ok), inten)
                        if on_frame is not None:
                            on_frame(i + 1, n)
                    w.metadata(METADATA_NAME, {
                        "format": "tofhil.mcap", "format_version": "1", "software_version": f"tofhil {__version__}",
                        "source_session": str(src.resolve()), "frame_id": FRAME_ID,
                        "frame_convention": "optical: x right, y down, z forward (OpenCV)",
                        "depth_kind": depth_kind, "timestamps": stamp_source, "camera": cam.to_dict(),
                        "session_device": s.device, "topics": topics} | dict(metadata or {}))
                    w.finish()
        except OSError as exc:
            if exc.errno not in _WRITE_ERRNOS:
                raise
            # the bag's own name, not "a file being written": the partial file is already removed
            raise InputFileError(f"cannot be written ({exc.strerror or exc})", file=out, field="--out",
                                 expected="a writable file on a disk with room for the bag") from None
    return McapExport(out, n, topics, dict(w.counts))
