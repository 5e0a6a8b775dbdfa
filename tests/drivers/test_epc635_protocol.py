"""epc635 protocol: CRC and framing against the vendor manual's own byte examples, the
80-byte header at its documented offsets, resynchronisation, and a fuzzed parser."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tofhil.drivers.tofcam635 import protocol as P

# Byte sequences printed in the TOF>cam 635 operation manual (chapter 11), CRC included.
MANUAL_EXAMPLES = [
    "f5 51 01 01 00 00 00 00 00 00 25 5a 1d 10",  # SET_OUTPUT both on
    "f5 4a 00 00 00 00 00 00 00 00 1f f8 6e 87",  # GET_TEMPERATURE
    "fa fc 02 00 47 13 54 1e 4c 14",  # temperature reply, 49.35 C
    "f5 49 00 00 00 00 00 00 00 00 8a 3c 6e 7e",  # GET_TOFCOS_VERSION
    "fa fe 04 00 0e 00 01 00 e6 c5 85 a0",  # version 1.14
    "f5 24 00 00 00 00 00 00 00 00 74 4b 28 68",  # GET_GS, acquisition mode 0
    "f5 25 00 00 00 00 00 00 00 00 6a fc 68 c3",  # GET_DCS, acquisition mode 0
]


@pytest.mark.parametrize("example", MANUAL_EXAMPLES)
def test_crc_matches_the_manuals_examples(example: str) -> None:
    b = bytes.fromhex(example)
    assert struct.pack("<I", P.crc32(b[:-4])) == b[-4:]


@given(st.binary(max_size=64))
def test_fast_crc_equals_the_bitwise_stm32_definition(data: bytes) -> None:
    assert P.crc32(data) == P.crc32_reference(data)


def test_commands_and_replies_are_framed_as_in_the_manual() -> None:
    assert P.encode_command(P.Cmd.GET_TEMPERATURE) == bytes.fromhex(MANUAL_EXAMPLES[1])
    assert P.encode_command(0x51, [1, 1]) == bytes.fromhex(MANUAL_EXAMPLES[0])
    assert P.encode_command(P.Cmd.GET_DCS, [0]) == bytes.fromhex(MANUAL_EXAMPLES[6])
    assert P.encode_packet(P.DataType.TEMPERATURE, bytes([0x47, 0x13])) == bytes.fromhex(MANUAL_EXAMPLES[2])
    cmd, params = P.decode_command(bytes.fromhex(MANUAL_EXAMPLES[0]))
    assert cmd == 0x51 and params == bytes([1, 1, 0, 0, 0, 0, 0, 0])
    with pytest.raises(ValueError):
        P.encode_command(0x02, bytes(9))


def test_small_replies_decode_to_the_manuals_values() -> None:
    parser = P.PacketParser()
    parser.feed(bytes.fromhex(MANUAL_EXAMPLES[2]) + bytes.fromhex(MANUAL_EXAMPLES[4]))
    t = parser.next_packet()
    v = parser.next_packet()
    assert t is not None and v is not None
    assert P.decode_temperature(t.payload) == pytest.approx(49.35)
    assert P.decode_firmware_release(v.payload) == (1, 14)
    assert P.decode_chip_information(struct.pack("<HH", 20, 1038)) == (20, 1038)
    ident = P.Identification.unpack(struct.pack("<I", 0x02040001))
    assert (ident.hw_version, ident.device_type, ident.chip_type, ident.op_mode) == (1, 0, 4, 2)


def test_header_fields_sit_at_the_documented_offsets() -> None:
    raw = bytearray(80)
    struct.pack_into("<H", raw, 1, 1234)  # frame counter
    struct.pack_into("<I", raw, 5, 3 << 16 | 49)  # firmware
    struct.pack_into("<HHHH", raw, 12, 80, 40, 8, 4)  # width, height, origin x, y
    struct.pack_into("<H", raw, 28, 500)  # integration time 0
    raw[65], raw[66] = 0, 7  # 10 MHz code, channel 7
    struct.pack_into("<h", raw, 69, -1234)  # centi-degrees
    h = P.ImageHeader.unpack(bytes(raw))
    assert (h.frame_counter, h.width, h.height, h.origin_x, h.origin_y) == (1234, 80, 40, 8, 4)
    assert h.firmware_version >> 16 == 3 and h.int_time_0 == 500
    assert h.mod_freq_hz == 10e6 and h.mod_channel == 7
    assert h.temperature_c == pytest.approx(-12.34)
    assert h.pack() == bytes(raw)
    with pytest.raises(P.TruncatedPacket):
        P.ImageHeader.unpack(bytes(79))


def _image(width: int = 160, height: int = 60, seed: int = 0) -> tuple[P.ImageHeader, np.ndarray]:
    rng = np.random.default_rng(seed)
    dcs = rng.integers(0, 4096, (4, height, width)).astype(np.int16)
    return P.ImageHeader(width=width, height=height, frame_counter=7), dcs


def test_full_dcs_image_spans_two_packets_like_the_manual() -> None:
    header, dcs = _image()
    wire = P.encode_image_packets(P.DataType.DCS, header, dcs.astype("<i2").tobytes())
    parser = P.PacketParser()
    parser.feed(wire)
    first, second = parser.next_packet(), parser.next_packet()
    assert first is not None and second is not None and parser.next_packet() is None
    # manual, GET_DCS: first packet 50 000 payload bytes, index 0, total 76 800 pixel bytes
    assert len(first.payload) == 50_000
    assert first.payload[:5] == bytes([0x00, 0x00, 0x2C, 0x01, 0x00])
    assert second.payload[:5] == bytes([0x01, 0x00, 0x2C, 0x01, 0x00])
    asm = P.ImageAssembler(P.DataType.DCS)
    assert asm.add(first) is None
    img = asm.add(second)
    assert img is not None
    np.testing.assert_array_equal(P.decode_dcs(img), dcs)


def test_small_roi_dcs_fits_one_packet() -> None:
    header, dcs = _image(16, 8)
    parser = P.PacketParser()
    parser.feed(P.encode_image_packets(P.DataType.DCS, header, dcs.astype("<i2").tobytes()))
    img = P.ImageAssembler(P.DataType.DCS).add(parser.next_packet())  # type: ignore[arg-type]
    assert img is not None and img.header.width == 16
    np.testing.assert_array_equal(P.decode_dcs(img), dcs)


def test_distance_amplitude_are_interleaved_and_confidence_masked() -> None:
    d = np.array([[1000, 16001], [42, 7000]], dtype=np.uint16)
    a = np.array([[500, 3], [9, 2896]], dtype=np.uint16)
    wire = np.stack([d | 0x4000, a | 0xC000], axis=-1).astype("<u2").tobytes()  # confidence bits set
    img = P.Image(P.DataType.DISTANCE_AMPLITUDE, P.ImageHeader(width=2, height=2), wire)
    dd, aa = P.decode_distance_amplitude(img)
    np.testing.assert_array_equal(dd, d)
    np.testing.assert_array_equal(aa, a)


def test_parser_resynchronises_after_garbage_and_a_corrupt_packet() -> None:
    good = P.encode_packet(P.DataType.TEMPERATURE, b"\x10\x20")
    bad = bytearray(P.encode_packet(P.DataType.TEMPERATURE, b"\x30\x40"))
    bad[4] ^= 0x01
    wire = b"\x00\x13\xfa\x01" + bytes(bad) + good + b"\xfa"
    # Told what to expect, a false start (type 0x01, length 0xFCFA) is rejected at once.
    parser = P.PacketParser()
    parser.expect({P.DataType.TEMPERATURE}, 2)
    parser.feed(wire)
    assert parser.next_packet() == P.Packet(P.DataType.TEMPERATURE, b"\x10\x20")
    assert parser.crc_errors >= 1 and parser.skipped_bytes >= 4
    assert parser.next_packet() is None  # the trailing start byte waits for more
    # Not told, it waits for the false start's 64 762 bytes; salvage finds the good packet.
    blind = P.PacketParser()
    blind.feed(wire)
    assert blind.next_packet() is None
    assert blind.salvage() == P.Packet(P.DataType.TEMPERATURE, b"\x10\x20")


def test_parser_says_how_many_bytes_the_current_packet_still_needs() -> None:
    pkt = P.encode_packet(P.DataType.GRAYSCALE, bytes(100))
    parser = P.PacketParser()
    assert parser.needed() == 4
    parser.feed(pkt[:2])
    assert parser.needed() == 2
    parser.feed(pkt[2:50])
    assert parser.needed() == len(pkt) - 50
    parser.feed(pkt[50:])
    assert parser.next_packet() == P.Packet(P.DataType.GRAYSCALE, bytes(100))


def test_assembler_rejects_inconsistent_images() -> None:
    header, dcs = _image(8, 4)
    pixels = dcs.astype("<i2").tobytes()
    short = P.Packet(P.DataType.DCS, struct.pack("<BI", 0, len(pixels)) + header.pack() + pixels[:-2]
                     + P.encode_packet(0, b"")[:0])
    asm = P.ImageAssembler(P.DataType.DCS)
    assert asm.add(short) is None  # waiting for the missing 2 bytes
    with pytest.raises(P.ProtocolError):
        asm.add(P.Packet(P.DataType.DCS, struct.pack("<BI", 0, len(pixels)) + b"\0\0"))  # index repeats
    with pytest.raises(P.ProtocolError):
        P.ImageAssembler(P.DataType.DCS).add(P.Packet(P.DataType.DCS, struct.pack("<BI", 0, 10**9)))
    with pytest.raises(P.NackError):
        P.ImageAssembler(P.DataType.DISTANCE).add(P.Packet(P.DataType.NACK, b""))
    lying = P.ImageHeader(width=161, height=60).pack()
    with pytest.raises(P.ProtocolError):
        P.ImageAssembler(P.DataType.GRAYSCALE).add(P.Packet(P.DataType.GRAYSCALE, lying + bytes(161 * 60)))
    with pytest.raises(P.TruncatedPacket):
        P.ImageAssembler(P.DataType.GRAYSCALE).add(P.Packet(P.DataType.GRAYSCALE, P.ImageHeader(
            width=4, height=2).pack() + bytes(7)))


# --------------------------------------------------------------------------- fuzzing
def _parse_all(wire: bytes, dtype: int) -> list[P.Image]:
    """What a host does with a byte stream: packets -> images; parser errors drop the image.
    The parser is not told what to expect (worst case); at the end of the stream (the host's
    timeout) it salvages what a false start may hide."""
    parser = P.PacketParser()
    parser.feed(wire)
    images: list[P.Image] = []
    asm = P.ImageAssembler(dtype)
    while (pkt := parser.next_packet() or parser.salvage()) is not None:
        try:
            img = asm.add(pkt)
        except P.ProtocolError:
            asm = P.ImageAssembler(dtype)
            continue
        if img is not None:
            images.append(img)
            asm = P.ImageAssembler(dtype)
    return images


_HEADER, _DCS = _image(12, 6, seed=3)
_WIRE = P.encode_image_packets(P.DataType.DCS, _HEADER, _DCS.astype("<i2").tobytes())
_FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_FUZZ
@given(st.binary(max_size=400))
def test_random_bytes_never_raise_outside_the_protocol(data: bytes) -> None:
    for dtype in (P.DataType.DCS, P.DataType.DISTANCE, P.DataType.GRAYSCALE):
        for img in _parse_all(data, dtype):
            assert img.header.n_pixels * 1 <= len(img.pixels)  # only self-consistent images come out


@_FUZZ
@given(st.integers(0, len(_WIRE) * 8 - 1))
def test_a_bit_flip_drops_the_frame_never_delivers_wrong_data(bit: int) -> None:
    wire = bytearray(_WIRE)
    wire[bit // 8] ^= 1 << (bit % 8)
    images = _parse_all(bytes(wire), P.DataType.DCS)
    assert images == []  # CRC32 catches every single-bit error


@_FUZZ
@given(st.integers(0, len(_WIRE) - 1), st.binary(max_size=30))
def test_truncation_then_a_good_frame_resynchronises(cut: int, junk: bytes) -> None:
    images = _parse_all(_WIRE[:cut] + junk + _WIRE, P.DataType.DCS)
    assert len(images) >= 1
    np.testing.assert_array_equal(P.decode_dcs(images[-1]), _DCS)
