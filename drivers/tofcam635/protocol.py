"""ESPROS epc635 serial protocol (TOFcam635, Onion Tau): framing, CRC, commands, image header.

Reference (read, not copied): espros/epc-tofcam-toolkit 0.13.0 (``epc/tofCam635/tofCam635.py``,
``epc/tofCam_lib/crc.py``, ``communication/communicationConstants/*.py``) and the header
layout of espros/cam635_driver (``communication_constants.h``, commit c41db12a). See
docs/drivers.md for the full citation.

Wire format (all integers little-endian):

* command, host -> camera, always 14 bytes:
  ``0xF5, command id, 8 parameter bytes (zero padded), CRC32 over the first 10 bytes``
* reply, camera -> host: ``0xFA, type, uint16 payload length, payload, CRC32 over all
  preceding bytes of the packet``.
* image payloads start with the 80-byte :class:`ImageHeader`. DCS images (up to 76 880
  bytes, more than a uint16 length allows) come in one or two packets (TOFcam635 manual,
  GET_DCS): every payload starts with a 5-byte prefix ``(packet index uint8, total DCS
  pixel bytes uint32)`` followed by the next piece of ``header + pixels``, at most 50 000
  payload bytes per packet.

CRC32: the STM32 hardware CRC unit (polynomial 0x04C11DB7, initial value 0xFFFFFFFF, no
reflection, no final xor) fed with one 32-bit word per byte (each byte zero-extended), as
the vendor's ``calcCrc32_32``. That equals CRC-32/MPEG-2 over the byte stream in which
every byte b becomes ``00 00 00 b``; :func:`crc32` computes it with zlib's table-driven
CRC by bit-reversal (MPEG-2 is the reflected zlib CRC on bit-reversed input and output),
so a whole frame is checked in well under a millisecond.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, fields
from enum import IntEnum

import numpy as np

from tofhil.errors import DeviceError

START_COMMAND = 0xF5
START_DATA = 0xFA
COMMAND_SIZE = 14
COMMAND_PARAM_BYTES = 8
PACKET_OVERHEAD = 8  # start, type, uint16 length, CRC32
HEADER_SIZE = 80
DCS_PREFIX_SIZE = 5
#: Largest payload of one DCS packet (TOFcam635 manual, GET_DCS example).
DCS_MAX_PACKET_PAYLOAD = 50_000
#: Largest payload a single packet can carry (uint16 length field).
MAX_PAYLOAD = 0xFFFF

SENSOR_WIDTH = 160
SENSOR_HEIGHT = 60
#: DCS samples are 12-bit ADC values around mid-scale; the client subtracts this.
DCS_OFFSET = 2048
DCS_MAX = 4095

#: Distance/amplitude codes (values >= LIMIT_VALID are not distances).
LIMIT_VALID = 16000
CODE_LOW_AMPLITUDE = 16001
CODE_ADC_OVERFLOW = 16002
CODE_SATURATION = 16003
MASK_VALUE = 0x3FFF  # bits 14-15 carry a confidence code
#: Amplitudes above this are error codes (vendor client: DEFAULT_MAX_AMPLITUDE).
MAX_AMPLITUDE = 2896

#: ROI coordinates are multiples of this (epc-tofcam-toolkit rounds to it; its GUI steps by it).
ROI_STEP = 4
#: The whole sensor as a ROI: half-open ``(x0, y0, x1, y1)``, x1 and y1 exclusive.
FULL_ROI = (0, 0, SENSOR_WIDTH, SENSOR_HEIGHT)

#: Modulation frequency codes of COMMAND_SET_MODULATION_FREQUENCY.
MOD_FREQ_CODES = {0: 10.0e6, 1: 20.0e6}


class Cmd(IntEnum):
    """Command ids (second byte of a command)."""

    SET_INT_TIME_DIST = 0x00
    SET_INT_TIME_GRAYSCALE = 0x01
    SET_ROI = 0x02
    SET_BINNING = 0x03
    SET_OPERATION_MODE = 0x04
    SET_MOD_FREQUENCY = 0x05
    SET_DLL_STEP = 0x06
    SET_TEMPORAL_FILTER = 0x07
    SET_MEDIAN_FILTER = 0x08
    SET_AMPLITUDE_LIMIT = 0x09
    SET_AVERAGE_FILTER = 0x0A
    SET_GAUSSIAN_FILTER = 0x0B
    SET_FRAME_RATE = 0x0C
    SET_HDR = 0x0D
    SET_MOD_CHANNEL = 0x0E
    SET_FILTER_SINGLE_SPOT = 0x0F
    SET_EDGE_FILTER = 0x10
    SET_INTERFERENCE_DETECTION = 0x11
    GET_DISTANCE = 0x20
    GET_AMPLITUDE = 0x21
    GET_DISTANCE_AMPLITUDE = 0x22
    GET_DCS_DISTANCE_AMPLITUDE = 0x23
    GET_GRAYSCALE = 0x24
    GET_DCS = 0x25
    SET_AUTO_ACQUISITION = 0x26
    GET_INTEGRATION_TIME_3D = 0x27
    STOP_STREAM = 0x28
    GET_DISTANCE_GRAYSCALE = 0x29
    GET_CALIBRATION = 0x43
    IDENTIFY = 0x47
    GET_CHIP_INFORMATION = 0x48
    GET_FIRMWARE_RELEASE = 0x49
    GET_TEMPERATURE = 0x4A
    WRITE_REGISTER = 0x4C
    READ_REGISTER = 0x4D
    GET_PRODUCTION_INFO = 0x50
    GET_CALIBRATION_INFO = 0x57
    SET_ILLUMINATION_POWER = 0x6C
    SYSTEM_RESET = 0x6D
    SET_ILLU_SEGMENT = 0x6E


class DataType(IntEnum):
    """Reply types (second byte of a reply packet)."""

    ACK = 0x00
    NACK = 0x01
    IDENTIFICATION = 0x02
    DISTANCE = 0x03
    AMPLITUDE = 0x04
    DISTANCE_AMPLITUDE = 0x05
    GRAYSCALE = 0x06
    DCS = 0x07
    DCS_DISTANCE_AMPLITUDE = 0x08
    INTEGRATION_TIME = 0x09
    DISTANCE_GRAYSCALE = 0x0A
    CALIBRATION_INFO = 0xF6
    LENS_CALIBRATION_DATA = 0xF7
    TRACE = 0xF8
    PRODUCTION_INFO = 0xF9
    CALIBRATION_DATA = 0xFA
    REGISTER = 0xFB
    TEMPERATURE = 0xFC
    CHIP_INFORMATION = 0xFD
    FIRMWARE_RELEASE = 0xFE
    ERROR = 0xFF


#: Which image reply each acquisition command produces, and bytes per pixel.
IMAGE_REPLY = {
    Cmd.GET_DISTANCE: (DataType.DISTANCE, 2),
    Cmd.GET_DISTANCE_AMPLITUDE: (DataType.DISTANCE_AMPLITUDE, 4),
    Cmd.GET_GRAYSCALE: (DataType.GRAYSCALE, 1),
    Cmd.GET_DCS: (DataType.DCS, 8),
}


def roi_problem(roi: tuple[int, ...]) -> str | None:
    """Why the camera refuses ``roi`` (half-open ``x0, y0, x1, y1``), or None if it accepts it.

    The rules of the vendor client (epc-tofcam-toolkit 0.13 ``set_roi`` and its ROI widget):
    every coordinate a multiple of :data:`ROI_STEP`, ``x1``/``y1`` exclusive, at least one
    step wide and high, inside the 160 x 60 sensor. ``(4, 4, 156, 12)`` is 152 x 8 pixels.
    """
    if len(roi) != 4:
        return f"{len(roi)} values"
    x0, y0, x1, y1 = roi
    if any(v % ROI_STEP for v in roi):
        return f"not multiples of {ROI_STEP}"
    if not (0 <= x0 < x1 <= SENSOR_WIDTH and 0 <= y0 < y1 <= SENSOR_HEIGHT):
        return "empty or outside the sensor"
    return None


ROI_EXPECTED = (f"X0,Y0,X1,Y1 half-open (X1, Y1 exclusive), multiples of {ROI_STEP}, "
                f"0 <= X0 < X1 <= {SENSOR_WIDTH}, 0 <= Y0 < Y1 <= {SENSOR_HEIGHT}")


# --------------------------------------------------------------------------- errors
class ProtocolError(DeviceError):
    """Bytes from the camera that do not form a valid packet or image."""


class CrcError(ProtocolError):
    """A packet whose CRC32 does not match its contents."""


class TruncatedPacket(ProtocolError):
    """A packet that ended (timeout, disconnect) before its announced length."""


class NackError(ProtocolError):
    """The camera refused a command (NACK or ERROR reply)."""


# --------------------------------------------------------------------------- CRC
_BITREV8 = np.array([int(f"{i:08b}"[::-1], 2) for i in range(256)], dtype=np.uint8)


def _bitrev32(x: int) -> int:
    return int(f"{x & 0xFFFFFFFF:032b}"[::-1], 2)


def crc32(data: bytes | bytearray | memoryview | np.ndarray) -> int:
    """epc635 CRC32 of ``data`` (see the module docstring for the definition)."""
    b = np.frombuffer(bytes(data), dtype=np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8).ravel()
    words = np.zeros(4 * b.size, dtype=np.uint8)
    words[3::4] = _BITREV8[b]  # big-endian word 00 00 00 b, bit-reversed for the reflected engine
    # zlib: reflected, init 0xFFFFFFFF, xorout 0xFFFFFFFF. Undo the xorout, reflect back.
    return _bitrev32(zlib.crc32(words.tobytes()) ^ 0xFFFFFFFF)


def crc32_reference(data: bytes) -> int:
    """Bit-by-bit definition (slow; for tests): STM32 CRC unit, one word per byte."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(32):
            crc = ((crc << 1) ^ 0x04C11DB7) & 0xFFFFFFFF if crc & 0x80000000 else (crc << 1) & 0xFFFFFFFF
    return crc


# --------------------------------------------------------------------------- commands
def encode_command(cmd: int, params: bytes | list[int] = b"") -> bytes:
    """A 14-byte command frame: 0xF5, id, 8 parameter bytes, CRC32."""
    p = bytes(params)
    if len(p) > COMMAND_PARAM_BYTES:
        raise ValueError(f"command 0x{cmd:02x} has {len(p)} parameter bytes, at most 8 fit")
    body = bytes([START_COMMAND, cmd & 0xFF]) + p.ljust(COMMAND_PARAM_BYTES, b"\0")
    return body + struct.pack("<I", crc32(body))


def decode_command(frame: bytes) -> tuple[int, bytes]:
    """Camera side: a 14-byte frame -> (command id, 8 parameter bytes); checks start and CRC."""
    if len(frame) != COMMAND_SIZE:
        raise TruncatedPacket(f"command frame has {len(frame)} bytes", expected=f"{COMMAND_SIZE}")
    if frame[0] != START_COMMAND:
        raise ProtocolError(f"command starts with 0x{frame[0]:02x}", expected="0xF5")
    (crc,) = struct.unpack_from("<I", frame, 10)
    if crc != crc32(frame[:10]):
        raise CrcError("command CRC32 mismatch")
    return frame[1], bytes(frame[2:10])


def encode_packet(dtype: int, payload: bytes = b"") -> bytes:
    """A reply packet: 0xFA, type, uint16 length, payload, CRC32."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes does not fit a packet (max {MAX_PAYLOAD})")
    body = struct.pack("<BBH", START_DATA, dtype & 0xFF, len(payload)) + bytes(payload)
    return body + struct.pack("<I", crc32(body))


@dataclass(frozen=True)
class Packet:
    """One reply packet with a valid CRC."""

    dtype: int
    payload: bytes


class PacketParser:
    """Incremental reply parser that resynchronises on the next start byte.

    ``feed`` bytes as they arrive and call :meth:`next_packet`. Garbage before a start
    byte is skipped (counted in ``skipped_bytes``); a packet with a bad CRC is dropped
    (``crc_errors``) and parsing resumes at the byte after its start byte.

    A stray 0xFA in garbage announces a random length and would make the parser wait for
    bytes that never come. :meth:`expect` narrows what a start byte may announce (the reply
    types and the largest payload the host is waiting for), which rejects almost every
    false start at once; :meth:`salvage` (after a timeout) looks past a false start for a
    complete packet with a valid CRC further on.
    """

    def __init__(self, max_payload: int = MAX_PAYLOAD) -> None:
        self._buf = bytearray()
        self.max_payload = max_payload
        self.types: frozenset[int] | None = None
        self.skipped_bytes = 0
        self.crc_errors = 0

    def expect(self, types: set[int] | frozenset[int] | None, max_payload: int = MAX_PAYLOAD) -> None:
        """Accept only packets of ``types`` (None: any) with at most ``max_payload`` bytes."""
        self.types = None if types is None else frozenset(int(t) for t in types)
        self.max_payload = max_payload

    def feed(self, data: bytes) -> None:
        self._buf += data

    @property
    def pending(self) -> int:
        """Bytes received but not yet consumed."""
        return len(self._buf)

    def needed(self) -> int:
        """Bytes still missing to complete the packet at the head of the buffer (>= 1);
        4 (a packet head) when the buffer does not start with a plausible packet."""
        buf = self._buf
        if len(buf) < 4 or buf[0] != START_DATA:
            return max(1, 4 - len(buf)) if not buf or buf[0] == START_DATA else 4
        total = self._plausible(buf, 0)
        return 4 if total is None else max(1, total - len(buf))

    def _plausible(self, buf: bytearray | memoryview, at: int) -> int | None:
        """Total size of the packet a start byte at ``at`` announces, None if implausible."""
        dtype = buf[at + 1]
        (length,) = struct.unpack_from("<H", buf, at + 2)
        if length > self.max_payload or (self.types is not None and dtype not in self.types):
            return None
        return length + PACKET_OVERHEAD

    def _valid_at(self, buf: bytearray, at: int, total: int) -> bool:
        (crc,) = struct.unpack_from("<I", buf, at + total - 4)
        return crc == crc32(memoryview(buf)[at: at + total - 4])

    def next_packet(self) -> Packet | None:
        """The next valid packet, or None when more bytes are needed."""
        buf = self._buf
        while True:
            start = buf.find(START_DATA)
            if start < 0:
                self.skipped_bytes += len(buf)
                buf.clear()
                return None
            if start:
                self.skipped_bytes += start
                del buf[:start]
            if len(buf) < 4:
                return None
            total = self._plausible(buf, 0)
            if total is None:
                self._drop_start()
                continue
            if len(buf) < total:
                return None
            if not self._valid_at(buf, 0, total):
                self.crc_errors += 1
                self._drop_start()
                continue
            pkt = Packet(buf[1], bytes(buf[4: total - 4]))
            del buf[:total]
            return pkt

    def salvage(self) -> Packet | None:
        """After a timeout: if the head is a false start, find a valid packet behind it."""
        buf = self._buf
        at = buf.find(START_DATA, 1)
        while at >= 0 and at + 4 <= len(buf):
            total = self._plausible(buf, at)
            if total is not None and at + total <= len(buf) and self._valid_at(buf, at, total):
                self.skipped_bytes += at
                del buf[:at]
                return self.next_packet()
            at = buf.find(START_DATA, at + 1)
        return None

    def _drop_start(self) -> None:
        self.skipped_bytes += 1
        del self._buf[:1]

    def discard(self) -> int:
        """Drop everything buffered (after a timeout); returns how many bytes were dropped."""
        n = len(self._buf)
        self.skipped_bytes += n
        self._buf.clear()
        return n


# --------------------------------------------------------------------------- header
#: (field, struct format, byte offset) of the 80-byte image header.
_HEADER_LAYOUT: tuple[tuple[str, str, int], ...] = (
    ("version", "B", 0),
    ("frame_counter", "H", 1),
    ("timestamp", "H", 3),
    ("firmware_version", "I", 5),
    ("hardware_version", "B", 9),
    ("chip_id", "H", 10),
    ("width", "H", 12),
    ("height", "H", 14),
    ("origin_x", "H", 16),
    ("origin_y", "H", 18),
    ("current_int_time_3d_wf", "H", 20),
    ("current_int_time_3d_nf", "H", 22),
    ("current_int_time_grayscale", "H", 24),
    ("int_time_grayscale", "H", 26),
    ("int_time_0", "H", 28), ("int_time_1", "H", 30), ("int_time_2", "H", 32), ("int_time_3", "H", 34),
    ("int_time_4", "H", 36), ("int_time_5", "H", 38), ("int_time_6", "H", 40), ("int_time_7", "H", 42),
    ("amplitude_limit_0", "H", 44), ("amplitude_limit_1", "H", 46), ("amplitude_limit_2", "H", 48),
    ("amplitude_limit_3", "H", 50), ("amplitude_limit_4", "H", 52),
    ("offset", "h", 54),
    ("binning", "B", 56),
    ("temporal_filter_factor", "H", 57),
    ("temporal_filter_threshold", "H", 59),
    ("single_value_filter_factor", "H", 61),
    ("single_value_filter_threshold", "H", 63),
    ("mod_frequency_code", "B", 65),
    ("mod_channel", "B", 66),
    ("flags", "H", 67),
    ("temperature_centi_c", "h", 69),
    ("illumination_beam", "B", 71),  # manual: FOV (0 NFOV spot only, 1 WFOV, 2 NFOV image)
    ("beam_b_distance", "H", 72),  # NFOV spot distance
    ("beam_b_amplitude", "H", 74),  # NFOV spot amplitude
    ("spot_x", "B", 76),
    ("spot_y", "B", 77),
)
# The fields are contiguous (little-endian, no alignment); 4 spare bytes end the header.
_HEADER_STRUCT = struct.Struct("<" + "".join(fmt for _, fmt, _ in _HEADER_LAYOUT) + "2x")
assert all(struct.calcsize("<" + "".join(f for _, f, _ in _HEADER_LAYOUT[:i])) == off
           for i, (_, _, off) in enumerate(_HEADER_LAYOUT))
assert _HEADER_STRUCT.size == HEADER_SIZE


@dataclass
class ImageHeader:
    """The 80-byte header in front of every image payload (offsets per cam635_driver)."""

    version: int = 0
    frame_counter: int = 0
    timestamp: int = 0  # device clock, milliseconds, wraps at 2**16
    firmware_version: int = 0
    hardware_version: int = 0
    chip_id: int = 0
    width: int = SENSOR_WIDTH
    height: int = SENSOR_HEIGHT
    origin_x: int = 0
    origin_y: int = 0
    current_int_time_3d_wf: int = 0
    current_int_time_3d_nf: int = 0
    current_int_time_grayscale: int = 0
    int_time_grayscale: int = 0
    int_time_0: int = 0
    int_time_1: int = 0
    int_time_2: int = 0
    int_time_3: int = 0
    int_time_4: int = 0
    int_time_5: int = 0
    int_time_6: int = 0
    int_time_7: int = 0
    amplitude_limit_0: int = 0
    amplitude_limit_1: int = 0
    amplitude_limit_2: int = 0
    amplitude_limit_3: int = 0
    amplitude_limit_4: int = 0
    offset: int = 0
    binning: int = 0
    temporal_filter_factor: int = 0
    temporal_filter_threshold: int = 0
    single_value_filter_factor: int = 0
    single_value_filter_threshold: int = 0
    mod_frequency_code: int = 1
    mod_channel: int = 0
    flags: int = 0
    temperature_centi_c: int = 0
    illumination_beam: int = 1
    beam_b_distance: int = 0xFFFF
    beam_b_amplitude: int = 0xFFFF
    spot_x: int = 0xFF
    spot_y: int = 0xFF

    def pack(self) -> bytes:
        return _HEADER_STRUCT.pack(*(getattr(self, name) for name, _, _ in _HEADER_LAYOUT))

    @classmethod
    def unpack(cls, data: bytes) -> "ImageHeader":
        if len(data) < HEADER_SIZE:
            raise TruncatedPacket(f"image header has {len(data)} bytes", expected=f"{HEADER_SIZE}")
        values = _HEADER_STRUCT.unpack_from(data, 0)
        return cls(**{name: v for (name, _, _), v in zip(_HEADER_LAYOUT, values)})

    @property
    def temperature_c(self) -> float:
        return self.temperature_centi_c / 100.0

    @property
    def mod_freq_hz(self) -> float:
        return MOD_FREQ_CODES.get(self.mod_frequency_code, float("nan"))

    @property
    def n_pixels(self) -> int:
        return self.width * self.height

    def to_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


# --------------------------------------------------------------------------- images
def encode_image_packets(dtype: int, header: ImageHeader, pixels: bytes) -> bytes:
    """Camera side: the packet(s) carrying one image (DCS split in two, others in one)."""
    head = header.pack()
    if dtype == DataType.DCS:
        stream = head + pixels
        step = DCS_MAX_PACKET_PAYLOAD - DCS_PREFIX_SIZE
        return b"".join(encode_packet(dtype, struct.pack("<BI", i, len(pixels)) + stream[off: off + step])
                        for i, off in enumerate(range(0, len(stream), step)))
    return encode_packet(dtype, head + pixels)


@dataclass
class Image:
    """A decoded image reply: its header and the raw pixel bytes after the header."""

    dtype: int
    header: ImageHeader
    pixels: bytes


class ImageAssembler:
    """Host side: packets -> one :class:`Image`; DCS images span one or more packets."""

    def __init__(self, dtype: int) -> None:
        self.dtype = dtype
        self._parts: list[bytes] = []
        self._total: int | None = None
        self._got = 0
        self._next_index = 0

    def add(self, pkt: Packet) -> Image | None:
        """Add one packet; returns the image when complete. Raises ProtocolError if inconsistent."""
        if pkt.dtype in (DataType.NACK, DataType.ERROR):
            raise NackError(f"camera answered {DataType(pkt.dtype).name} "
                            f"(payload {pkt.payload[:8].hex()}) to an image request")
        if pkt.dtype != self.dtype:
            raise ProtocolError(f"unexpected reply type 0x{pkt.dtype:02x}", expected=f"0x{self.dtype:02x}")
        if self.dtype != DataType.DCS:
            return self._finish(pkt.payload)
        if len(pkt.payload) < DCS_PREFIX_SIZE:
            raise TruncatedPacket(f"DCS packet payload has {len(pkt.payload)} bytes",
                                  expected=f">= {DCS_PREFIX_SIZE}")
        index, total = struct.unpack_from("<BI", pkt.payload, 0)
        if index != self._next_index:
            raise ProtocolError(f"DCS packet {index} arrived out of order", expected=f"packet {self._next_index}")
        if self._total is None:
            if not 0 < total <= 4 * 2 * SENSOR_WIDTH * SENSOR_HEIGHT:
                raise ProtocolError(f"DCS size field says {total} bytes",
                                    expected=f"1..{4 * 2 * SENSOR_WIDTH * SENSOR_HEIGHT}")
            self._total = total
        elif total != self._total:
            raise ProtocolError(f"DCS packets disagree on the image size ({total} vs {self._total})")
        chunk = pkt.payload[DCS_PREFIX_SIZE:]
        self._parts.append(chunk)
        self._got += len(chunk)
        self._next_index += 1
        want = HEADER_SIZE + self._total
        if self._got > want:
            raise ProtocolError(f"DCS packets carry {self._got} bytes", expected=f"{want}")
        if self._got == want:
            return self._finish(b"".join(self._parts))
        return None

    def _finish(self, data: bytes) -> Image:
        header = ImageHeader.unpack(data)
        _, bpp = next(v for v in IMAGE_REPLY.values() if v[0] == self.dtype)
        if not (0 < header.width <= SENSOR_WIDTH and 0 < header.height <= SENSOR_HEIGHT):
            raise ProtocolError(f"image header says {header.width}x{header.height}",
                                expected=f"at most {SENSOR_WIDTH}x{SENSOR_HEIGHT}")
        want = header.n_pixels * bpp
        pixels = data[HEADER_SIZE:]
        if len(pixels) != want:
            raise TruncatedPacket(f"{DataType(self.dtype).name} image has {len(pixels)} pixel bytes",
                                  expected=f"{want} for {header.width}x{header.height}")
        return Image(self.dtype, header, pixels)


def decode_dcs(img: Image) -> np.ndarray:
    """DCS image -> int16 ``[4, H, W]`` device values (12-bit, mid-scale 2048)."""
    h = img.header
    return np.frombuffer(img.pixels, dtype="<i2").reshape(4, h.height, h.width)


def decode_distance_amplitude(img: Image) -> tuple[np.ndarray, np.ndarray]:
    """Distance + amplitude image -> two uint16 ``[H, W]`` arrays (interleaved on the wire)."""
    h = img.header
    v = (np.frombuffer(img.pixels, dtype="<u2") & MASK_VALUE).reshape(h.height, h.width, 2)
    return v[..., 0], v[..., 1]


def decode_grayscale(img: Image) -> np.ndarray:
    """Grayscale image -> uint8 ``[H, W]``."""
    h = img.header
    return np.frombuffer(img.pixels, dtype=np.uint8).reshape(h.height, h.width)


# --------------------------------------------------------------------------- small replies
#: Total reply sizes (packet overhead included) of the small answers, as the vendor client expects.
ANSWER_SIZE = {DataType.ACK: 8, DataType.CHIP_INFORMATION: 12, DataType.CALIBRATION_INFO: 22,
               DataType.REGISTER: 9, DataType.FIRMWARE_RELEASE: 12, DataType.TEMPERATURE: 10,
               DataType.IDENTIFICATION: 12, DataType.INTEGRATION_TIME: 10, DataType.PRODUCTION_INFO: 10}


def _need(payload: bytes, n: int, what: str) -> None:
    if len(payload) < n:
        raise TruncatedPacket(f"{what} reply has {len(payload)} payload bytes", expected=f">= {n}")


def decode_chip_information(payload: bytes) -> tuple[int, int]:
    """-> (chip id, wafer id)."""
    _need(payload, 4, "chip information")
    chip, wafer = struct.unpack_from("<HH", payload, 0)
    return chip, wafer


def decode_firmware_release(payload: bytes) -> tuple[int, int]:
    """-> (major, minor); the vendor prints it as ``major.minor`` with minor in hundredths."""
    _need(payload, 4, "firmware release")
    (v,) = struct.unpack_from("<I", payload, 0)
    return v >> 16, v & 0xFFFF


def decode_temperature(payload: bytes) -> float:
    """-> chip temperature in degrees Celsius (sent in centi-degrees)."""
    _need(payload, 2, "temperature")
    (t,) = struct.unpack_from("<h", payload, 0)
    return t / 100.0


@dataclass(frozen=True)
class Identification:
    hw_version: int
    device_type: int
    chip_type: int
    op_mode: int

    @classmethod
    def unpack(cls, payload: bytes) -> "Identification":
        _need(payload, 4, "identification")
        (v,) = struct.unpack_from("<I", payload, 0)
        return cls(v & 0xFF, (v >> 8) & 0xFF, (v >> 16) & 0xFF, (v >> 24) & 0xFF)

    def pack(self) -> bytes:
        return struct.pack("<I", self.hw_version | self.device_type << 8 | self.chip_type << 16
                           | self.op_mode << 24)


#: chip type of the epc635 in the identification word (cam635_driver: CHIP_TYPE_EPC635).
CHIP_TYPE_EPC635 = 0x04


def u16(value: int) -> bytes:
    return struct.pack("<H", value & 0xFFFF)
