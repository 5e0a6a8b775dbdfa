"""pyusb driver for the ESPROS TOFcam635 (epc635 sensor; the Onion Tau camera speaks the same).

The camera is a USB CDC device (STMicroelectronics VID 0x0483, STM32 virtual COM port PID
0x5740). The driver talks to the bulk endpoints of its CDC *data* interface through pyusb
(detaching the kernel's cdc_acm driver when it is attached), or -- same protocol, same
code -- to a serial port (``serial:/dev/ttyACM0``, or the pseudo-terminal of
``tofhil emulate --pty``). Protocol details: :mod:`tofhil.drivers.tofcam635.protocol`.

Device specs: ``usb`` (first TOFcam635), ``usb:BUS:ADDR`` (that one), ``serial:PORT``.

Transports: :mod:`.transport`; device profile and tap conversion: :mod:`.profile`.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any, Callable

import numpy as np

from tofhil.camera import CameraModel, load_camera_preset
from tofhil.drivers.base import (CaptureSettings, DeviceDisconnected, DeviceEntry, DeviceInfo, Driver, Frame,
                                 FrameDropped, parse_spec, register_driver)
from tofhil.drivers.tofcam635 import protocol as P
from tofhil.drivers.tofcam635.profile import TOFCAM635, dcs_to_canonical
from tofhil.drivers.tofcam635.transport import (USB_PID, USB_VID, SerialTransport, Transport, UsbTransport,
                                                default_usb_backend, find_usb_devices)
from tofhil.errors import DeviceError
from tofhil.frames import DepthFrame, RawFrame


# --------------------------------------------------------------------------- driver
class TofCam635(Driver):
    """TOFcam635 over USB (pyusb) or a serial port. See the module docstring for specs."""

    scheme = "usb"
    profile = TOFCAM635

    def __init__(self, spec: str = "usb", *, backend: Any = None,
                 transport_factory: Callable[[], Transport] | None = None) -> None:
        super().__init__(spec)
        self._location = spec  # what _make_transport resolves (subclasses may relabel self.spec)
        self._backend = backend
        self._transport_factory = transport_factory
        self.transport: Transport | None = None
        self._parser = P.PacketParser()
        self._info: DeviceInfo | None = None
        self._roi = P.FULL_ROI
        self._sensor_camera = load_camera_preset(self.profile.camera_preset)
        self._camera = self._sensor_camera
        self._seq_unwrap = _Unwrapper(1 << 16)
        self._ts_unwrap = _Unwrapper(1 << 16)
        self._silent = 0
        #: consecutive replies with no byte at all before the device counts as gone
        self.max_silent = 3
        self.reply_timeout_s = 1.0

    # ---- opening ------------------------------------------------------------
    def _make_transport(self) -> Transport:
        if self._transport_factory is not None:
            return self._transport_factory()
        scheme, rest = parse_spec(self._location)
        if scheme == "serial":
            if not rest:
                raise DeviceError("serial device needs a port", field="--device", expected="serial:/dev/ttyACM0")
            return SerialTransport(rest)
        backend = self._backend if self._backend is not None else default_usb_backend()
        bus = address = None
        if rest:
            try:
                bus_s, addr_s = rest.split(":")
                bus, address = int(bus_s), int(addr_s)
            except ValueError:
                raise DeviceError(f"bad USB location {rest!r}", field="--device", expected="usb or usb:BUS:ADDR") from None
        devs = find_usb_devices(backend, bus, address)
        if not devs:
            where = f" at bus {bus} address {address}" if bus is not None else ""
            raise DeviceDisconnected(f"no TOFcam635 (USB {USB_VID:04x}:{USB_PID:04x}) found{where}",
                                     field="--device", expected="a connected camera (see `tofhil devices`)")
        return UsbTransport(devs[0])

    def _open_device(self) -> None:
        self.transport = self._make_transport()
        self._parser = P.PacketParser()
        try:
            # A camera left in auto-repeat/streaming mode keeps sending images: stop it first.
            self._send(P.Cmd.STOP_STREAM, [])
            self._drain()
            self._info = self._identify()
            # Known state, as the vendor's initialize(): beam A, no HDR, filters off.
            self._command(P.Cmd.SET_OPERATION_MODE, [0])
            self._command(P.Cmd.SET_HDR, [0])
            for cmd, params in ((P.Cmd.SET_MEDIAN_FILTER, [0]), (P.Cmd.SET_AVERAGE_FILTER, [0]),
                                (P.Cmd.SET_EDGE_FILTER, [0, 0]), (P.Cmd.SET_TEMPORAL_FILTER, [0, 0, 0, 0]),
                                (P.Cmd.SET_INTERFERENCE_DETECTION, [0, 0, 0xF4, 0x01])):
                self._command(cmd, params)
        except Exception:
            self._close_device()
            raise

    def _close_device(self) -> None:
        if self.transport is not None:
            self.transport.close()
            self.transport = None

    def _identify(self) -> DeviceInfo:
        ident = P.Identification.unpack(self._request(P.Cmd.IDENTIFY, [], P.DataType.IDENTIFICATION))
        if ident.chip_type != P.CHIP_TYPE_EPC635:
            raise DeviceError(f"device reports chip type {ident.chip_type}", field="--device",
                              expected=f"{P.CHIP_TYPE_EPC635} (epc635)")
        major, minor = P.decode_firmware_release(self._request(P.Cmd.GET_FIRMWARE_RELEASE, [],
                                                               P.DataType.FIRMWARE_RELEASE))
        chip_id, wafer_id = P.decode_chip_information(self._request(P.Cmd.GET_CHIP_INFORMATION, [],
                                                                    P.DataType.CHIP_INFORMATION))
        return DeviceInfo(driver="tofcam635", model=self.profile.model, serial=f"{wafer_id}.{chip_id}",
                          firmware=f"{major}.{minor:02d}", vendor="ESPROS Photonics",
                          extra={"chip_id": chip_id, "wafer_id": wafer_id, "hw_version": ident.hw_version,
                                 "device_type": ident.device_type, "chip_type": ident.chip_type,
                                 "transport": self.transport.description if self.transport else ""})

    def info(self) -> DeviceInfo:
        self._require_open()
        assert self._info is not None
        return self._info

    def chip_temperature_c(self) -> float:
        """Chip temperature read on request (degrees Celsius)."""
        self._require_open()
        return P.decode_temperature(self._request(P.Cmd.GET_TEMPERATURE, [], P.DataType.TEMPERATURE))

    @property
    def camera(self) -> CameraModel:
        return self._camera

    # ---- settings -----------------------------------------------------------
    def _apply_settings(self, s: CaptureSettings) -> None:
        if s.mode not in ("dcs", "distance", "grayscale"):
            raise DeviceError(f"mode {s.mode!r} not supported", field="mode", expected="dcs | distance | grayscale")
        if s.roi is not None:
            roi = tuple(int(v) for v in s.roi)
            problem = P.roi_problem(roi)
            if problem is not None:  # refused here, as the camera would (it answers NACK)
                raise DeviceError(f"ROI {tuple(s.roi)}: {problem}", field="roi", expected=P.ROI_EXPECTED)
        else:
            roi = P.FULL_ROI
        self._command(P.Cmd.SET_ROI, b"".join(P.u16(v) for v in roi))
        self._roi = roi
        # The header reports the real size; until a frame arrives assume the ROI's.
        self._camera = crop_camera(self._sensor_camera, roi)
        if s.mod_freq_hz is not None:
            codes = {f: c for c, f in P.MOD_FREQ_CODES.items()}
            code = codes.get(float(s.mod_freq_hz))
            if code is None:
                raise DeviceError(f"modulation frequency {s.mod_freq_hz:g} Hz not supported", field="mod_freq_hz",
                                  expected=" or ".join(f"{f:g}" for f in self.profile.mod_freqs_hz))
            self._command(P.Cmd.SET_MOD_FREQUENCY, [code])
        if s.channel is not None or s.mod_freq_hz is not None:
            ch = int(s.channel or 0)
            if not 0 <= ch <= 15:
                raise DeviceError(f"modulation channel {ch}", field="channel", expected="0..15")
            self._command(P.Cmd.SET_MOD_CHANNEL, [0, ch])  # auto channel off, then the channel
        if s.integration_time_s is not None:
            us = int(round(s.integration_time_s * 1e6))
            if not 1 <= us <= 0xFFFF:
                raise DeviceError(f"integration time {s.integration_time_s * 1e6:g} us", field="integration_time_s",
                                  expected="1..65535 us")
            self._command(P.Cmd.SET_INT_TIME_DIST, [0, us & 0xFF, us >> 8])
            self._command(P.Cmd.SET_INT_TIME_GRAYSCALE, [us & 0xFF, us >> 8])
        if s.min_amplitude is not None:
            amp = int(round(s.min_amplitude))
            if not 0 <= amp <= 2047:  # the range cam635_driver's dynamic_reconfigure allows
                raise DeviceError(f"minimum amplitude {s.min_amplitude}", field="min_amplitude", expected="0..2047 DN")
            for index in range(5):  # one limit per HDR integration-time slot, as the vendor client
                self._command(P.Cmd.SET_AMPLITUDE_LIMIT, [index, amp & 0xFF, amp >> 8])

    # ---- low-level exchange -------------------------------------------------
    def _send(self, cmd: int, params: bytes | list[int]) -> None:
        assert self.transport is not None
        self.transport.write(P.encode_command(cmd, params))

    def _read_packet(self, deadline: float) -> P.Packet:
        assert self.transport is not None
        got_any = False
        while True:
            pkt = self._parser.next_packet()
            if pkt is not None:
                self._silent = 0
                return pkt
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                pkt = self._parser.salvage()  # a false start byte may hide a complete reply
                if pkt is not None:
                    self._silent = 0
                    return pkt
                partial = self._parser.pending
                missing = self._parser.needed() if partial else 0
                self._parser.discard()
                if got_any or partial:
                    self._silent = 0
                    raise P.TruncatedPacket(f"{self.transport.description}: truncated reply, {partial} bytes "
                                            f"received, {missing} more announced, none within "
                                            f"{self.reply_timeout_s:g} s", expected="a complete packet")
                self._silent += 1
                if self._silent >= self.max_silent:
                    self._silent = 0
                    raise DeviceDisconnected(f"{self.transport.description}: no reply to "
                                             f"{self.max_silent} requests in a row")
                raise FrameDropped(f"{self.transport.description}: no reply within {self.reply_timeout_s:g} s")
            data = self.transport.read_some(min(remaining, 0.25), self._parser.needed())
            if data:
                got_any = True
                self._parser.feed(data)

    def _drain(self, quiet_s: float = 0.02, max_s: float = 0.5) -> None:
        """Discard late bytes (of a dropped reply) so the next request starts clean."""
        assert self.transport is not None
        self.transport.reset_input()
        end = time.monotonic() + max_s
        while time.monotonic() < end:
            if not self.transport.read_some(quiet_s):
                break
        self._parser.discard()

    def _exchange(self, cmd: int, params: bytes | list[int], want: int, retries: int = 2) -> P.Packet:
        """Send a command and return its reply of type ``want``; retried on a garbled reply."""
        last: Exception | None = None
        self._parser.expect({want, P.DataType.NACK, P.DataType.ERROR}, 64)
        for _ in range(retries + 1):
            self._send(cmd, params)
            try:
                pkt = self._read_packet(time.monotonic() + self.reply_timeout_s)
            except (P.ProtocolError, FrameDropped) as exc:
                last = exc
                self._drain()
                continue
            if pkt.dtype == want:
                return pkt
            if pkt.dtype in (P.DataType.NACK, P.DataType.ERROR):
                last = P.NackError(f"camera refused command 0x{cmd:02x} ({P.DataType(pkt.dtype).name})")
            else:
                last = P.ProtocolError(f"reply type 0x{pkt.dtype:02x} to command 0x{cmd:02x}",
                                       expected=f"0x{want:02x}")
            self._drain()
        raise DeviceError(f"command 0x{cmd:02x} failed: {last}", field=self.spec)

    def _command(self, cmd: int, params: bytes | list[int]) -> None:
        self._exchange(cmd, params, P.DataType.ACK)

    def _request(self, cmd: int, params: bytes | list[int], dtype: int) -> bytes:
        return self._exchange(cmd, params, dtype).payload

    def acquire(self, cmd: int) -> P.Image:
        """One image of the given acquisition command (single-shot); FrameDropped if corrupt."""
        self._require_open()
        dtype, _ = P.IMAGE_REPLY[P.Cmd(cmd)]
        asm = P.ImageAssembler(dtype)
        largest = P.DCS_MAX_PACKET_PAYLOAD if dtype == P.DataType.DCS else \
            P.HEADER_SIZE + 4 * P.SENSOR_WIDTH * P.SENSOR_HEIGHT
        self._parser.expect({dtype, P.DataType.NACK, P.DataType.ERROR}, largest)
        self._send(cmd, [0])  # 0 = single measurement
        deadline = time.monotonic() + self.reply_timeout_s
        try:
            while True:
                img = asm.add(self._read_packet(deadline))
                if img is not None:
                    return img
        except P.ProtocolError as exc:
            self._drain()
            raise FrameDropped(str(exc)) from None
        except FrameDropped:
            self._drain()
            raise

    # ---- frames -------------------------------------------------------------
    def read_frame(self, timeout_s: float = 2.0) -> Frame:
        self._require_open()
        self.reply_timeout_s = timeout_s
        mode = self.settings.mode
        cmd = {"dcs": P.Cmd.GET_DCS, "distance": P.Cmd.GET_DISTANCE_AMPLITUDE, "grayscale": P.Cmd.GET_GRAYSCALE}[mode]
        img = self.acquire(cmd)
        h = img.header
        camera = self._camera_for(h)
        seq = self._seq_unwrap(h.frame_counter)
        ts = self._ts_unwrap(h.timestamp) * 1e-3
        meta = {"header": h.to_dict(), "host_time_s": time.time(),
                # the 12-bit DCS clip at 0 and 4095: canonical taps (mid-scale removed) at
                # these values are saturated (tofhil.demod.TapLimits)
                "saturation_dn": float(P.DCS_MAX - self.profile.dcs_offset),
                "saturation_low_dn": float(-self.profile.dcs_offset)}
        freq = h.mod_freq_hz
        int_time_s = h.int_time_0 * 1e-6 if h.int_time_0 else (self.settings.integration_time_s or math.nan)
        if mode == "dcs":
            taps, theta = dcs_to_canonical(P.decode_dcs(img), self.profile)
            raw = RawFrame(taps=taps[None], freq_hz=[freq], theta_rad=theta,   # int16 DN, as the device gives them
                           integration_time_s=int_time_s, camera=camera, timestamp_s=ts, sequence=seq,
                           temperature_c=h.temperature_c, meta=meta)
            return Frame(raw=raw, sequence=seq, timestamp_s=ts)
        if mode == "distance":
            dist, amp = P.decode_distance_amplitude(img)
            # the frequency and exposure the device measured at, kept with the depth (a session
            # of depth alone has no raw/freq_hz to say it)
            depth = distance_codes_to_frame(dist, amp, camera, ts, seq, h.temperature_c,
                                            meta | {"freq_hz": [freq], "integration_time_s": int_time_s})
            return Frame(depth=depth, sequence=seq, timestamp_s=ts)
        gray = P.decode_grayscale(img)
        return Frame(images={"grayscale": gray.copy()}, sequence=seq, timestamp_s=ts)

    def _camera_for(self, h: P.ImageHeader) -> CameraModel:
        roi = (h.origin_x, h.origin_y, h.origin_x + h.width, h.origin_y + h.height)
        if self._camera.shape != (h.height, h.width) or roi != self._roi:
            if roi[2] > P.SENSOR_WIDTH or roi[3] > P.SENSOR_HEIGHT:
                raise FrameDropped(f"header ROI {roi} exceeds the sensor")
            self._roi = roi
            self._camera = crop_camera(self._sensor_camera, roi)
        return self._camera


class _Unwrapper:
    """Unwrap a wrapping device counter into a monotonic integer.

    A drop from the top quarter of the range into the bottom quarter is a wrap; any other
    step backwards is a device restart (after a reconnect), and the count continues from the
    last value instead of jumping by a whole period.
    """

    def __init__(self, modulus: int) -> None:
        self.modulus = modulus
        self._last: int | None = None
        self._base = 0

    def __call__(self, value: int) -> int:
        last = self._last
        if last is not None and value < last:
            if last >= 3 * self.modulus // 4 and value < self.modulus // 4:
                self._base += self.modulus
            else:
                self._base += last - value + 1  # restarted: continue right after the last value
        self._last = value
        return self._base + value


def crop_camera(camera: CameraModel, roi: tuple[int, int, int, int]) -> CameraModel:
    """The camera model of a half-open ROI ``(x0, y0, x1, y1)`` of the sensor (x1, y1 exclusive)."""
    x0, y0, x1, y1 = roi
    if (x0, y0, x1, y1) == (0, 0, camera.width, camera.height):
        return camera
    return replace(camera, width=x1 - x0, height=y1 - y0, cx=camera.cx - x0, cy=camera.cy - y0)



def distance_codes_to_frame(dist: np.ndarray, amp: np.ndarray, camera: CameraModel, ts: float, seq: int,
                            temperature_c: float, meta: dict[str, Any]) -> DepthFrame:
    """Distance codes (mm, >= 16000 = low amplitude / overflow / saturation) -> radial DepthFrame."""
    valid = dist < P.LIMIT_VALID
    radial = np.where(valid, dist.astype(np.float32) * np.float32(1e-3), np.float32(np.nan))
    amplitude = np.where(amp <= P.MAX_AMPLITUDE, amp.astype(np.float32), np.float32(np.nan))
    codes = {"low_amplitude": int(np.count_nonzero(dist == P.CODE_LOW_AMPLITUDE)),
             "adc_overflow": int(np.count_nonzero(dist == P.CODE_ADC_OVERFLOW)),
             "saturation": int(np.count_nonzero(dist == P.CODE_SATURATION))}
    return DepthFrame(distance_m=radial, kind="radial", camera=camera, amplitude=amplitude, valid=valid,
                      timestamp_s=ts, sequence=seq, temperature_c=temperature_c, meta=meta | {"invalid_codes": codes})


# --------------------------------------------------------------------------- registry
def _list_connected() -> list[DeviceEntry]:
    entries: list[DeviceEntry] = []
    try:
        backend = default_usb_backend()
        for d in find_usb_devices(backend):
            entries.append(DeviceEntry(f"usb:{d.bus}:{d.address}", f"TOFcam635 (USB {USB_VID:04x}:{USB_PID:04x}, "
                                       f"bus {d.bus} address {d.address})", "connected"))
    except DeviceError as exc:
        entries.append(DeviceEntry("usb", f"USB unavailable: {exc}", "connected"))
    try:
        from serial.tools import list_ports

        for p in list_ports.comports():
            if p.vid == USB_VID and p.pid == USB_PID:
                entries.append(DeviceEntry(f"serial:{p.device}", f"TOFcam635 tty ({p.description})", "connected"))
    except Exception:  # port enumeration is best effort (no sysfs in some containers)
        pass
    return entries


register_driver("usb", lambda spec: TofCam635(spec), lister=_list_connected,
                description="ESPROS TOFcam635 over USB (pyusb): usb or usb:BUS:ADDR")
register_driver("serial", lambda spec: TofCam635(spec),
                description="TOFcam635 protocol on a serial port: serial:/dev/ttyACM0 or a pty")
