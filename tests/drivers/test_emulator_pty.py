"""``tofhil emulate --pty`` as a real subprocess: a serial client speaking the protocol byte by
byte, the driver capturing a session over the serial port, and the vendor's own Python client
(epc-tofcam-toolkit, when installed) initialising the camera and reading every image type."""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
import serial

from tofhil import C_M_PER_S
from tofhil.camera import load_camera_preset
from tofhil.depth import depth_from_raw
from tofhil.drivers.tofcam635 import protocol as P
from tofhil.drivers.base import CaptureSettings
from tofhil.drivers.capture import capture
from tofhil.drivers.tofcam635.driver import TofCam635
from tofhil.session import open_session

from tests.drivers.pty_emulator import emulator_pty

WALL_M = 1.2


def _emulator(*extra: str) -> Iterator[str]:
    with emulator_pty("--scene", f"wall:{WALL_M}", *extra) as port:
        yield port


@pytest.fixture(scope="module")
def pty_port() -> Iterator[str]:
    yield from _emulator()


def _read_packet(port: serial.Serial) -> tuple[int, bytes]:
    head = port.read(4)
    assert len(head) == 4 and head[0] == 0xFA, head
    (length,) = struct.unpack_from("<H", head, 2)
    rest = port.read(length + 4)
    assert len(rest) == length + 4
    assert struct.unpack("<I", rest[-4:])[0] == P.crc32(head + rest[:-4])
    return head[1], rest[:-4]


def test_a_serial_client_speaks_the_protocol(pty_port: str) -> None:
    cam = load_camera_preset("epc635")
    with serial.Serial(pty_port, 10_000_000, timeout=2.0) as port:
        port.write(P.encode_command(P.Cmd.GET_FIRMWARE_RELEASE))
        dtype, payload = _read_packet(port)
        assert dtype == P.DataType.FIRMWARE_RELEASE and len(payload) == 4
        port.write(P.encode_command(P.Cmd.SET_MOD_FREQUENCY, [0]))  # 10 MHz
        assert _read_packet(port) == (P.DataType.ACK, b"")
        port.write(P.encode_command(P.Cmd.SET_INT_TIME_DIST, [0, 0x2C, 0x01]))  # 300 us (1000 us would clip)
        assert _read_packet(port) == (P.DataType.ACK, b"")
        port.write(P.encode_command(P.Cmd.GET_DCS, [0]))
        first_t, first = _read_packet(port)
        second_t, second = _read_packet(port)
        assert first_t == second_t == P.DataType.DCS
        index0, total = struct.unpack_from("<BI", first)
        assert (index0, second[0], total) == (0, 1, 4 * 2 * 160 * 60)
        stream = first[5:] + second[5:]
        header = P.ImageHeader.unpack(stream)
        assert (header.width, header.height, header.mod_freq_hz, header.int_time_0) == (160, 60, 10e6, 300)
        dcs = np.frombuffer(stream[80:], "<i2").reshape(4, 60, 160).astype(float) - 2048
        phase = np.arctan2(dcs[3] - dcs[1], dcs[2] - dcs[0]) + np.pi  # the vendor's formula
        dist = phase * C_M_PER_S / (4 * np.pi * 10e6)
        err = dist - WALL_M / cam.ray_z
        assert abs(float(np.median(err))) < 5e-3 and float(np.percentile(np.abs(err), 90)) < 0.05  # ~1-2 cm noise, more in the dim (cos^8) corners
        port.write(b"\xf5\x20" + bytes(12))  # bad CRC: the camera answers NACK
        assert _read_packet(port)[0] == P.DataType.NACK


def test_a_roi_over_the_pty_gives_images_of_its_size(pty_port: str) -> None:
    """The vendor test's ROI (4, 4, 156, 12), half-open: 152 x 8 distance + amplitude pairs."""
    with serial.Serial(pty_port, 10_000_000, timeout=2.0) as port:
        for roi, shape in (((4, 4, 156, 12), (8, 152)), ((0, 0, 160, 60), (60, 160))):
            port.write(P.encode_command(P.Cmd.SET_ROI, b"".join(P.u16(v) for v in roi)))
            assert _read_packet(port) == (P.DataType.ACK, b"")
            port.write(P.encode_command(P.Cmd.GET_DISTANCE_AMPLITUDE, [0]))
            dtype, payload = _read_packet(port)
            header = P.ImageHeader.unpack(payload)
            assert dtype == P.DataType.DISTANCE_AMPLITUDE
            assert (header.origin_x, header.origin_y, header.height, header.width) == (roi[0], roi[1], *shape)
            assert len(payload) - P.HEADER_SIZE == 2 * 2 * shape[0] * shape[1]
        port.write(P.encode_command(P.Cmd.SET_ROI, b"".join(P.u16(v) for v in (4, 4, 157, 12))))
        assert _read_packet(port)[0] == P.DataType.NACK


# Reply sizes the vendor client reads with a single fixed-length read (its __answer_table).
VENDOR_ANSWER_SIZES = [(P.Cmd.GET_CHIP_INFORMATION, 12), (P.Cmd.GET_CALIBRATION_INFO, 22), (P.Cmd.READ_REGISTER, 9),
                       (P.Cmd.GET_FIRMWARE_RELEASE, 12), (P.Cmd.GET_TEMPERATURE, 10), (P.Cmd.IDENTIFY, 12),
                       (P.Cmd.SET_HDR, 8)]


def test_small_replies_have_the_sizes_the_vendor_client_reads(pty_port: str) -> None:
    with serial.Serial(pty_port, 10_000_000, timeout=1.0) as port:
        for cmd, size in VENDOR_ANSWER_SIZES:
            port.write(P.encode_command(cmd))
            reply = port.read(size)
            assert len(reply) == size and reply[0] == 0xFA
            assert struct.unpack("<I", reply[-4:])[0] == P.crc32(reply[:-4])
            port.timeout = 0.05
            assert port.read(1) == b""  # nothing more follows
            port.timeout = 1.0


def test_driver_captures_a_session_over_the_serial_port(pty_port: str, tmp_path: Path) -> None:
    out = tmp_path / "serial.h5"
    with TofCam635(f"serial:{pty_port}") as dev:
        summary = capture(dev, out, 3, CaptureSettings(mode="dcs", integration_time_s=600e-6))
        assert "serial port" in dev.info().extra["transport"]
    assert summary.frames_written == 3 and summary.dropped == 0
    with open_session(out) as s:
        assert s.n_frames == 3
        for raw in s.raw_frames():
            err = depth_from_raw(raw).radial_m - WALL_M / s.camera.ray_z
            assert abs(float(np.median(err))) < 5e-3


def test_serial_capture_survives_a_silent_device_and_faults(tmp_path: Path) -> None:
    """On a pty a disconnect is silence: three silent requests -> reconnect (reopen the port)."""
    for port in _emulator("--faults", "crc@1,disconnect@3,truncate@5,disconnect_s=1.2"):
        dev = TofCam635(f"serial:{port}")
        dev.backoff_s = 0.05
        with dev:
            summary = capture(dev, tmp_path / "flaky.h5", 6, CaptureSettings(mode="dcs"), timeout_s=0.3)
        assert summary.frames_written == 6 and summary.reconnects == 1
        # crc, the disconnect's lost reply and one more silent request, truncate
        assert summary.dropped == 4
        with open_session(tmp_path / "flaky.h5") as s:
            assert s.n_frames == 6


def test_the_vendor_client_reads_every_image_type(pty_port: str) -> None:
    tofcam = pytest.importorskip("epc.tofCam635", reason="epc-tofcam-toolkit not installed (pip install "
                                 "--no-deps epc-tofcam-toolkit; see docs/drivers.md)")
    from epc.tofCam_lib.algorithms import calc_distance_and_amplitude

    cam = tofcam.TOFcam635(pty_port)
    try:
        cam.initialize()  # ROI, mode, HDR, 20 MHz, 125 us, filters, amplitude limit 100
        assert cam.device.get_chip_infos() == (20, 1038)
        assert float(cam.device.get_fw_version()) == pytest.approx(3.49)
        assert 20 < cam.device.get_chip_temperature() < 60
        truth_mm = 1e3 * WALL_M / load_camera_preset("epc635").ray_z
        distance = np.asarray(cam.get_distance_image(), dtype=float)
        assert distance.shape == (60, 160)
        assert abs(float(np.median(distance - truth_mm))) < 5
        distance2, amplitude = cam.get_distance_and_amplitude_image()
        assert abs(float(np.median(np.asarray(distance2, float) - truth_mm))) < 5
        assert 100 < float(np.median(amplitude)) < 2896
        gray = cam.get_grayscale_image()
        assert gray.shape == (60, 160) and gray.dtype == np.uint8 and gray.max() > 0
        dcs = cam.get_raw_dcs_images()
        assert dcs.shape == (4, 60, 160)
        dist_v, amp_v = calc_distance_and_amplitude(dcs.astype(float), 20e6)
        assert abs(float(np.median(dist_v - truth_mm))) < 5
        assert math.isclose(float(np.median(amp_v)), float(np.median(amplitude)), rel_tol=0.05)
    finally:
        cam.interface.com.close()
