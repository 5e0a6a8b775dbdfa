"""A faithful TOFcam635 emulator: the epc635 protocol on top of an image source.

:class:`Epc635Emulator` is the camera's firmware as a byte-in/byte-out state machine: it
parses 14-byte commands, keeps the settings (ROI, integration time, modulation frequency
and channel, amplitude limit...), and answers with ACKs, identification, chip info,
firmware release, temperature and images (DCS, distance, distance + amplitude,
grayscale) framed exactly as the real camera does (:mod:`tofhil.drivers.tofcam635.protocol`).
Two transports carry it: an in-process pyusb backend
(:mod:`tofhil.drivers.tofcam635.usb_backend`), and a pseudo-terminal
(:mod:`tofhil.drivers.tofcam635.pty`).

Images come from the :class:`tofhil.frame_source.ImageSource` its caller gives it (the
simulator twin's are in :mod:`tofhil.sim.sources`; opened from a spec, the one the
application connected, :mod:`tofhil.drivers.sources`): noise-free canonical taps, rendered
once per modulation frequency (cached) and scaled with the integration time; the emulator
adds the source's per-frame noise, converts to the device's DCS (12-bit, mid-scale 2048,
differential so the offset cancels) and, like the firmware, computes distance and amplitude
from them. Faults: :mod:`tofhil.drivers.tofcam635.faults`.

:class:`FaultPlan` injects CRC errors, truncated replies, garbage between packets, silent
timeouts, USB stalls and disconnects (with reconnection) on image replies.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from tofhil.demod import phase_to_distance, phasor, wrapped_phase
from tofhil.drivers.base import DeviceEntry, DeviceInfo, register_driver
from tofhil.drivers.tofcam635 import protocol as P
from tofhil.drivers.tofcam635.driver import TofCam635
from tofhil.drivers.tofcam635.faults import FaultPlan
from tofhil.drivers.tofcam635.profile import TOFCAM635, DeviceProfile, canonical_phases, canonical_to_dcs
from tofhil.drivers.sources import frame_source
from tofhil.frame_source import ImageSource, TapNoise


# --------------------------------------------------------------------------- the camera
@dataclass
class EmulatorStats:
    commands: int = 0
    images: int = 0
    bad_commands: int = 0
    faults: dict[str, int] = field(default_factory=dict)


class Epc635Emulator:
    """The TOFcam635 firmware: :meth:`receive` command bytes, :meth:`transmit` reply bytes.

    Thread-safe: the pty server and a pyusb backend may call it from another thread.
    """

    CHIP_ID = 20
    WAFER_ID = 1038
    FIRMWARE = (3, 49)
    HW_VERSION = 2

    def __init__(self, source: ImageSource, *, profile: DeviceProfile = TOFCAM635,
                 noise: TapNoise | None = None, faults: FaultPlan | None = None, seed: int = 0,
                 frame_interval_s: float = 0.0) -> None:
        self.source = source
        self.profile = profile
        self.noise = self.source.noise_model() if noise is None else noise
        self.faults = faults or FaultPlan()
        self.rng = np.random.default_rng(seed)
        self.frame_interval_s = frame_interval_s
        self.stats = EmulatorStats()
        self._lock = threading.RLock()
        self._in = bytearray()
        self._out = bytearray()
        self._t0 = time.monotonic()
        self._last_frame = 0.0
        self.absent_until = 0.0
        self.stalled = False
        self.generation = 0  # bumps on each reconnect (USB address changes)
        self.reset()

    # ---- state --------------------------------------------------------------
    def reset(self) -> None:
        self.roi = P.FULL_ROI
        self.int_time_us = [125, 0, 0, 0, 0, 0, 0, 0]
        self.int_time_gray_us = 50
        self.mod_code = 1
        self.channel = 0
        self.amp_limits = [100, 100, 100, 100, 100]
        self.op_mode = 0
        self.hdr = 0
        self.frame_counter = 0

    @property
    def freq_hz(self) -> float:
        return P.MOD_FREQ_CODES[self.mod_code]

    @property
    def present(self) -> bool:
        return time.monotonic() >= self.absent_until

    def temperature_c(self) -> float:
        """Warm-up curve (hidden truth): 31 C rising by 9 C with a 90 s time constant."""
        t = time.monotonic() - self._t0
        return 31.0 + 9.0 * (1.0 - math.exp(-t / 90.0))

    # ---- byte interface -----------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Bytes from the host; complete commands are executed at once."""
        with self._lock:
            if not self.present:
                return
            self._in += data
            while True:
                start = self._in.find(P.START_COMMAND)
                if start < 0:
                    self._in.clear()
                    return
                del self._in[:start]
                if len(self._in) < P.COMMAND_SIZE:
                    return
                frame = bytes(self._in[:P.COMMAND_SIZE])
                try:
                    cmd, params = P.decode_command(frame)
                except P.ProtocolError:
                    self.stats.bad_commands += 1
                    del self._in[:1]  # resynchronise on the next start byte
                    self._out += P.encode_packet(P.DataType.NACK)
                    continue
                del self._in[:P.COMMAND_SIZE]
                self._out += self.execute(cmd, params)

    def transmit(self, max_bytes: int | None = None) -> bytes:
        """Reply bytes ready for the host (up to ``max_bytes``)."""
        with self._lock:
            n = len(self._out) if max_bytes is None else min(max_bytes, len(self._out))
            data = bytes(self._out[:n])
            del self._out[:n]
            return data

    @property
    def pending(self) -> int:
        return len(self._out)

    def disconnect(self, seconds: float) -> None:
        with self._lock:
            self.absent_until = time.monotonic() + seconds
            self._in.clear()
            self._out.clear()
            self.generation += 1
            self.reset()  # a power-cycled camera starts from its defaults

    # ---- commands -----------------------------------------------------------
    def execute(self, cmd: int, p: bytes) -> bytes:
        """One command -> reply bytes (possibly faulted for image requests)."""
        self.stats.commands += 1
        C, D = P.Cmd, P.DataType
        ack = P.encode_packet(D.ACK)
        u16 = lambda i: struct.unpack_from("<H", p, i)[0]  # noqa: E731
        if cmd in (C.GET_DCS, C.GET_DISTANCE, C.GET_DISTANCE_AMPLITUDE, C.GET_GRAYSCALE):
            return self._image_reply(P.Cmd(cmd))
        if cmd == C.SET_INT_TIME_DIST:
            if p[0] < len(self.int_time_us):
                self.int_time_us[p[0]] = max(1, u16(1))
            return ack
        if cmd == C.SET_INT_TIME_GRAYSCALE:
            self.int_time_gray_us = max(1, u16(0))
            return ack
        if cmd == C.SET_ROI:
            roi = struct.unpack_from("<4H", p, 0)
            if P.roi_problem(roi) is not None:
                return P.encode_packet(D.NACK)  # the camera keeps its previous ROI
            self.roi = roi
            return ack
        if cmd == C.SET_MOD_FREQUENCY:
            if p[0] not in P.MOD_FREQ_CODES:
                return P.encode_packet(D.NACK)
            self.mod_code = p[0]
            return ack
        if cmd == C.SET_MOD_CHANNEL:
            self.channel = p[1] & 0x0F
            return ack
        if cmd == C.SET_AMPLITUDE_LIMIT:
            if p[0] < len(self.amp_limits):
                self.amp_limits[p[0]] = u16(1)
            return ack
        if cmd == C.SET_OPERATION_MODE:
            self.op_mode = p[0]
            return ack
        if cmd == C.SET_HDR:
            self.hdr = p[0]
            return ack
        if cmd in (C.SET_BINNING, C.SET_DLL_STEP, C.SET_TEMPORAL_FILTER, C.SET_MEDIAN_FILTER,
                   C.SET_AVERAGE_FILTER, C.SET_GAUSSIAN_FILTER, C.SET_FRAME_RATE, C.SET_FILTER_SINGLE_SPOT,
                   C.SET_EDGE_FILTER, C.SET_INTERFERENCE_DETECTION, C.SET_ILLUMINATION_POWER,
                   C.SET_ILLU_SEGMENT, C.STOP_STREAM, C.WRITE_REGISTER, C.SET_AUTO_ACQUISITION):
            return ack  # accepted; the emulated images do not model these filters
        if cmd == C.SYSTEM_RESET:
            self.reset()
            return ack
        if cmd == C.IDENTIFY:
            ident = P.Identification(self.HW_VERSION, 0, P.CHIP_TYPE_EPC635, self.op_mode)
            return P.encode_packet(D.IDENTIFICATION, ident.pack())
        if cmd == C.GET_CHIP_INFORMATION:
            return P.encode_packet(D.CHIP_INFORMATION, struct.pack("<HH", self.CHIP_ID, self.WAFER_ID))
        if cmd == C.GET_FIRMWARE_RELEASE:
            major, minor = self.FIRMWARE
            return P.encode_packet(D.FIRMWARE_RELEASE, struct.pack("<I", major << 16 | minor))
        if cmd == C.GET_TEMPERATURE:
            return P.encode_packet(D.TEMPERATURE, struct.pack("<h", round(self.temperature_c() * 100)))
        if cmd == C.READ_REGISTER:
            return P.encode_packet(D.REGISTER, bytes([0]))
        if cmd == C.GET_INTEGRATION_TIME_3D:
            return P.encode_packet(D.INTEGRATION_TIME, P.u16(self.int_time_us[0]))
        if cmd == C.GET_CALIBRATION_INFO:
            return P.encode_packet(D.CALIBRATION_INFO, bytes(14))
        if cmd == C.GET_PRODUCTION_INFO:
            return P.encode_packet(D.PRODUCTION_INFO, bytes([25, 1]))
        return P.encode_packet(D.NACK)

    # ---- images -------------------------------------------------------------
    def _header(self) -> P.ImageHeader:
        x0, y0, x1, y1 = self.roi
        it = self.int_time_us
        ms = int((time.monotonic() - self._t0) * 1000) & 0xFFFF
        return P.ImageHeader(
            version=1, frame_counter=self.frame_counter & 0xFFFF, timestamp=ms,
            firmware_version=self.FIRMWARE[0] << 16 | self.FIRMWARE[1], hardware_version=self.HW_VERSION,
            chip_id=self.CHIP_ID, width=x1 - x0, height=y1 - y0, origin_x=x0, origin_y=y0,
            current_int_time_3d_wf=it[0], current_int_time_grayscale=self.int_time_gray_us,
            int_time_grayscale=self.int_time_gray_us, int_time_0=it[0], int_time_1=it[1], int_time_2=it[2],
            amplitude_limit_0=self.amp_limits[0], amplitude_limit_1=self.amp_limits[1],
            amplitude_limit_2=self.amp_limits[2], amplitude_limit_3=self.amp_limits[3],
            amplitude_limit_4=self.amp_limits[4], mod_frequency_code=self.mod_code, mod_channel=self.channel,
            temperature_centi_c=round(self.temperature_c() * 100), illumination_beam=1)

    def device_dcs(self, integration_time_s: float | None = None) -> np.ndarray:
        """One noisy acquisition of the ROI as the device's int16 DCS ``[4, h, w]`` (0..4095)."""
        t_int = self.int_time_us[0] * 1e-6 if integration_time_s is None else integration_time_s
        theta = canonical_phases(self.profile)
        clean = self.source.taps(self.freq_hz, t_int, theta)
        x0, y0, x1, y1 = self.roi
        c = self.noise.apply(clean[:, y0:y1, x0:x1], self.rng) if self.noise else clean[:, y0:y1, x0:x1]
        # epc635 pixels read the difference of their two storage gates: DCS_k ~ (c_k - c_{k+2}) / 2
        # = A cos(phi - theta_k); offset and ambient cancel, noise of both gates remains.
        diff = 0.5 * (c - np.roll(c, 2, axis=0))
        dcs = np.rint(canonical_to_dcs(diff, self.profile))
        return np.clip(dcs, 0, P.DCS_MAX).astype(np.int16)

    def _image_reply(self, cmd: P.Cmd) -> bytes:
        index = self.stats.images
        self.stats.images += 1
        fault = self.faults.fault_for(index)
        if self.frame_interval_s > 0:
            wait = self._last_frame + self.frame_interval_s - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            self._last_frame = time.monotonic()
        self.frame_counter += 1
        header = self._header()
        dcs = self.device_dcs()
        dtype, _ = P.IMAGE_REPLY[cmd]
        if cmd == P.Cmd.GET_DCS:
            pixels = dcs.astype("<i2").tobytes()
        elif cmd == P.Cmd.GET_GRAYSCALE:
            pixels = self._grayscale().tobytes()
        else:
            dist, amp = self._firmware_distance(dcs)
            if cmd == P.Cmd.GET_DISTANCE:
                pixels = dist.astype("<u2").tobytes()
            else:
                pixels = np.stack([dist, amp], axis=-1).astype("<u2").tobytes()
        reply = P.encode_image_packets(dtype, header, pixels)
        return self._inject(fault, reply)

    def _grayscale(self) -> np.ndarray:
        """8-bit intensity: the tap offset at the grayscale integration time, 16 DN per count."""
        theta = canonical_phases(self.profile)
        clean = self.source.taps(self.freq_hz, self.int_time_gray_us * 1e-6, theta)
        x0, y0, x1, y1 = self.roi
        b = clean[:, y0:y1, x0:x1].mean(axis=0)
        b = self.noise.apply(b[None], self.rng)[0] if self.noise else b
        return np.clip(np.rint(b / 16.0), 0, 255).astype(np.uint8)

    def _firmware_distance(self, dcs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the camera computes from its DCS: distance (mm or code) and amplitude (DN)."""
        taps = dcs.astype(np.float32) - self.profile.dcs_offset
        s = phasor(taps, canonical_phases(self.profile))
        amp = np.abs(s)
        dist_mm = phase_to_distance(wrapped_phase(s), self.freq_hz) * 1e3
        dist = np.minimum(np.rint(dist_mm), P.LIMIT_VALID - 1).astype(np.uint16)
        dist[amp < self.amp_limits[0]] = P.CODE_LOW_AMPLITUDE
        overflow = ((dcs <= 0) | (dcs >= P.DCS_MAX)).any(axis=0)
        dist[overflow] = P.CODE_ADC_OVERFLOW
        amp_codes = np.minimum(np.rint(amp), P.MAX_AMPLITUDE).astype(np.uint16)
        amp_codes[overflow] = P.CODE_ADC_OVERFLOW
        return dist, amp_codes

    def _inject(self, fault: str | None, reply: bytes) -> bytes:
        if fault is None:
            return reply
        self.stats.faults[fault] = self.stats.faults.get(fault, 0) + 1
        if fault == "crc":
            b = bytearray(reply)
            b[len(b) // 2] ^= 0x5A  # a payload byte flips in transit; the CRC no longer matches
            return bytes(b)
        if fault == "truncate":
            return reply[: len(reply) // 2]
        if fault == "garbage":
            junk = self.rng.integers(0, 256, 37, dtype=np.uint8).tobytes()
            return junk + bytes([P.START_DATA, 0x07, 0x10]) + reply  # a fake start byte too
        if fault == "timeout":
            return b""
        if fault == "stall":
            self.stalled = True  # USB: endpoint halts until the host clears it; pty: silence
            return b""
        if fault == "disconnect":
            self.disconnect(self.faults.disconnect_s)
            return b""
        return reply


# --------------------------------------------------------------------------- registry
class EmulatedTofCam635(TofCam635):
    """The real pyusb driver talking to an in-process emulator through its pyusb backend."""

    scheme = "emulator"

    def __init__(self, spec: str = "emulator", *, emulator: Epc635Emulator | None = None) -> None:
        from tofhil.drivers.tofcam635.usb_backend import EmulatorBackend

        _, scene = spec.partition(":")[::2]
        self.emulator = emulator or Epc635Emulator(frame_source("tofcam635", scene or None))
        self.usb_backend = EmulatorBackend([self.emulator])
        super().__init__("usb", backend=self.usb_backend)
        self.spec = spec

    def info(self) -> DeviceInfo:
        info = super().info()
        info.extra = info.extra | {"emulated": True, "source": self.emulator.source.description}
        return info


def _list_emulated() -> list[DeviceEntry]:
    return [DeviceEntry("emulator", "in-process TOFcam635 emulator (bundled bench_demo scene, or an analytic "
                        "wall); emulator:SCENE.yaml or emulator:wall:1.5 for others", "emulated")]


register_driver("emulator", lambda spec: EmulatedTofCam635(spec), lister=_list_emulated,
                description="in-process TOFcam635 emulator through the pyusb driver: emulator[:SCENE]")
