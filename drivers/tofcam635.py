"""pyusb driver for the ESPROS TOFcam635 (epc635 sensor; the Onion Tau camera speaks the same).

The camera is a USB CDC device (STMicroelectronics VID 0x0483, STM32 virtual COM port PID
0x5740). The driver talks to the bulk endpoints of its CDC *data* interface through pyusb
(detaching the kernel's cdc_acm driver when it is attached), or -- same protocol, same
code -- to a serial port (``serial:/dev/ttyACM0``, or the pseudo-terminal of
``tofhil emulate --pty``). Protocol details: :mod:`tofhil.drivers.epc635_protocol`.

Device specs: ``usb`` (first TOFcam635), ``usb:BUS:ADDR`` (that one), ``serial:PORT``.

Tap convention (the device profile): the vendor computes the phase as
``atan2(DCS3 - DCS1, DCS2 - DCS0) + pi`` after removing the 2048 mid-scale offset, i.e.
``phi = atan2(DCS1 - DCS3, DCS0 - DCS2)``. That is exactly the canonical estimator for
``DCS_k = A cos(phi - theta_k)`` with ``theta_k = 0, 90, 180, 270 deg`` and sign +1, so the
profile declares those phases; the driver subtracts the offset and applies the
:class:`tofhil.demod.TapConvention` at the edge.
"""

from __future__ import annotations

import errno
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from importlib import resources
from typing import Any, Callable

import numpy as np

from tofhil.camera import CameraModel, load_camera_preset
from tofhil.demod import TapConvention
from tofhil.drivers import epc635_protocol as P
from tofhil.drivers.base import (CaptureSettings, DeviceDisconnected, DeviceEntry, DeviceInfo, Driver, Frame,
                                 FrameDropped, parse_spec, register_driver)
from tofhil.errors import DeviceError
from tofhil.frames import DepthFrame, RawFrame

USB_VID = 0x0483
USB_PID = 0x5740  # STM32 virtual COM port, as enumerated by the TOFcam635
CDC_DATA_CLASS = 0x0A
CDC_COMM_CLASS = 0x02


@dataclass(frozen=True)
class DeviceProfile:
    """What tofhil needs to know about a device model to convert its data at the edge."""

    model: str
    camera_preset: str
    taps: TapConvention
    dcs_offset: int
    mod_freqs_hz: tuple[float, ...]
    #: Default integration time when the user gives none (vendor initialize(): 125 us).
    default_integration_time_s: float = 125e-6
    max_integration_time_s: float = 65535e-6


TOFCAM635 = DeviceProfile(
    model="TOFcam635",
    camera_preset="epc635",
    taps=TapConvention(theta_rad=(0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi), order=None, sign=1.0),
    dcs_offset=P.DCS_OFFSET,
    mod_freqs_hz=(10.0e6, 20.0e6),
)


def udev_rule_path() -> str:
    """Where the shipped udev rule lives (inside the installed package)."""
    return str(resources.files("tofhil.configs").joinpath("udev", "99-tofcam635.rules"))


def permission_error(what: str) -> DeviceError:
    rule = udev_rule_path()
    return DeviceError(
        f"permission denied opening {what}. Install the udev rule shipped with tofhil and replug the "
        f"camera: sudo cp {rule} /etc/udev/rules.d/ && sudo udevadm control --reload-rules && "
        f"sudo udevadm trigger (see docs/drivers.md, USB permissions)", field="--device",
        expected="read/write access to the USB device")


# --------------------------------------------------------------------------- transports
class Transport(ABC):
    """A byte pipe to the camera."""

    description = ""

    @abstractmethod
    def write(self, data: bytes) -> None: ...

    @abstractmethod
    def read_some(self, timeout_s: float, expected: int | None = None) -> bytes:
        """Whatever bytes arrive within ``timeout_s`` (empty on timeout). ``expected`` is how
        many bytes the host knows are still coming for the current packet (a hint)."""

    @abstractmethod
    def close(self) -> None: ...

    def reset_input(self) -> None:
        """Forget bytes already received but not read (best effort)."""


class UsbTransport(Transport):
    """Bulk endpoints of the CDC data interface, through pyusb."""

    READ_SIZE = 16384  # a multiple of every bulk max packet size: no libusb overflow

    def __init__(self, dev: Any) -> None:
        import usb.core
        import usb.util

        self._usb = usb
        self.dev = dev
        self.description = f"USB {dev.idVendor:04x}:{dev.idProduct:04x} bus {dev.bus} address {dev.address}"
        self._detached: list[int] = []
        try:
            cfg = self._configuration()
            data_intf = comm_intf = None
            for intf in cfg:
                if intf.bInterfaceClass == CDC_DATA_CLASS and data_intf is None:
                    data_intf = intf
                elif intf.bInterfaceClass == CDC_COMM_CLASS and comm_intf is None:
                    comm_intf = intf
            if data_intf is None:
                raise DeviceError(f"{self.description} has no CDC data interface", field="--device",
                                  expected="a TOFcam635 (USB CDC device)")
            for intf in (comm_intf, data_intf):
                if intf is None:
                    continue
                n = intf.bInterfaceNumber
                try:
                    if dev.is_kernel_driver_active(n):
                        dev.detach_kernel_driver(n)  # cdc_acm holds it as /dev/ttyACM*
                        self._detached.append(n)
                except NotImplementedError:  # backends without kernel drivers (Windows, emulator)
                    pass
            self._intf = data_intf.bInterfaceNumber
            usb.util.claim_interface(dev, self._intf)
            ep_out = usb.util.find_descriptor(data_intf, custom_match=lambda e: usb.util.endpoint_direction(
                e.bEndpointAddress) == usb.util.ENDPOINT_OUT)
            ep_in = usb.util.find_descriptor(data_intf, custom_match=lambda e: usb.util.endpoint_direction(
                e.bEndpointAddress) == usb.util.ENDPOINT_IN)
            if ep_out is None or ep_in is None:
                raise DeviceError(f"{self.description}: data interface lacks bulk endpoints", field="--device")
            self.ep_out, self.ep_in = ep_out.bEndpointAddress, ep_in.bEndpointAddress
            self.max_packet = int(ep_in.wMaxPacketSize) or 64
            if comm_intf is not None:
                self._set_line_state(comm_intf.bInterfaceNumber)
        except usb.core.USBError as exc:
            self._release()
            raise usb_error(exc, self.description) from None
        except Exception:
            self._release()
            raise

    def _configuration(self) -> Any:
        try:
            return self.dev.get_active_configuration()
        except self._usb.core.USBError as exc:
            if exc.errno == errno.EACCES:
                raise
            self.dev.set_configuration()
            return self.dev.get_active_configuration()

    def _set_line_state(self, comm: int) -> None:
        # CDC SET_LINE_CODING (10 Mbaud 8N1, what the vendor client opens) and
        # SET_CONTROL_LINE_STATE (DTR|RTS); some STM32 VCP firmwares only send after DTR.
        line = (10_000_000).to_bytes(4, "little") + bytes([0, 0, 8])
        try:
            self.dev.ctrl_transfer(0x21, 0x20, 0, comm, line, timeout=200)
            self.dev.ctrl_transfer(0x21, 0x22, 0x03, comm, None, timeout=200)
        except self._usb.core.USBError as exc:
            if exc.errno in (errno.ENODEV, errno.EACCES):
                raise
            # a device that rejects the class requests still streams: not fatal

    def write(self, data: bytes) -> None:
        try:
            self.dev.write(self.ep_out, data, timeout=1000)
        except self._usb.core.USBTimeoutError:
            raise FrameDropped(f"{self.description}: write timed out") from None
        except self._usb.core.USBError as exc:
            raise usb_error(exc, self.description) from None

    def read_some(self, timeout_s: float, expected: int | None = None) -> bytes:
        ms = max(1, int(timeout_s * 1000))
        # Ask for the rest of the current packet rounded up to whole USB packets: the transfer
        # then ends on the reply's short last packet or exactly when full, never by a timeout
        # (libusb discards what a timed-out transfer had received).
        mps = self.max_packet
        size = self.READ_SIZE if expected is None else min(self.READ_SIZE, -(-max(expected, 1) // mps) * mps)
        try:
            return bytes(self.dev.read(self.ep_in, size, timeout=ms))
        except self._usb.core.USBTimeoutError:
            return b""
        except self._usb.core.USBError as exc:
            if exc.errno == errno.EPIPE:  # endpoint halted (stall): clear it, lose this transfer
                try:
                    self.dev.clear_halt(self.ep_in)
                except self._usb.core.USBError:
                    pass
                raise FrameDropped(f"{self.description}: endpoint stalled (cleared)") from None
            raise usb_error(exc, self.description) from None

    def _release(self) -> None:
        usb = self._usb
        try:
            usb.util.dispose_resources(self.dev)
        except Exception:  # a vanished device cannot be released; nothing to do
            pass
        for n in self._detached:
            try:
                self.dev.attach_kernel_driver(n)  # give /dev/ttyACM* back
            except Exception:
                pass
        self._detached = []

    def close(self) -> None:
        self._release()


def usb_error(exc: Exception, what: str) -> DeviceError:
    """Map a pyusb error to the driver's vocabulary."""
    code = getattr(exc, "errno", None)
    if code == errno.EACCES:
        return permission_error(what)
    if code in (errno.ENODEV, errno.EIO, errno.ENOENT, errno.ESHUTDOWN, errno.EPROTO):
        return DeviceDisconnected(f"{what}: {exc}")
    return DeviceDisconnected(f"{what}: USB error {exc}")


class SerialTransport(Transport):
    """The same protocol over a serial port (the CDC tty, or a pseudo-terminal)."""

    def __init__(self, port: str) -> None:
        import serial

        self._serial_mod = serial
        self.description = f"serial port {port}"
        try:
            self.ser = serial.Serial(port, baudrate=10_000_000, timeout=0.2, write_timeout=2.0)
        except serial.SerialException as exc:
            if isinstance(exc.__context__, PermissionError) or "Permission denied" in str(exc):
                raise permission_error(port) from None
            raise DeviceDisconnected(f"cannot open {port}: {exc}", field="--device",
                                     expected="an existing serial port") from None

    def write(self, data: bytes) -> None:
        try:
            self.ser.write(data)
        except (self._serial_mod.SerialException, OSError) as exc:
            raise DeviceDisconnected(f"{self.description}: {exc}") from None

    def read_some(self, timeout_s: float, expected: int | None = None) -> bytes:
        try:
            self.ser.timeout = max(timeout_s, 0.001)
            first = self.ser.read(1)
            if not first:
                return b""
            n = self.ser.in_waiting
            return first + (self.ser.read(n) if n else b"")
        except (self._serial_mod.SerialException, OSError, TypeError) as exc:
            raise DeviceDisconnected(f"{self.description}: {exc}") from None

    def reset_input(self) -> None:
        try:
            self.ser.reset_input_buffer()
        except (self._serial_mod.SerialException, OSError):
            pass

    def close(self) -> None:
        try:
            self.ser.close()
        except Exception:
            pass


# --------------------------------------------------------------------------- device lookup
def default_usb_backend() -> Any:
    """libusb-1.0 from the libusb-package wheel (works without a system libusb)."""
    import libusb_package

    backend = libusb_package.get_libusb1_backend()
    if backend is None:
        raise DeviceError("no libusb backend could be loaded", field="--device",
                          expected="libusb-1.0 (pip install libusb-package)")
    return backend


def find_usb_devices(backend: Any, bus: int | None = None, address: int | None = None) -> list[Any]:
    import usb.core

    def match(d: Any) -> bool:
        if bus is not None:
            return d.bus == bus and d.address == address
        return d.idProduct == USB_PID

    try:
        return list(usb.core.find(find_all=True, idVendor=USB_VID, backend=backend, custom_match=match))
    except usb.core.USBError as exc:
        raise usb_error(exc, "USB bus") from None


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
        self._roi = (0, 0, P.SENSOR_WIDTH - 1, P.SENSOR_HEIGHT - 1)
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
            x0, y0, x1, y1 = (int(v) for v in s.roi)
            if not (0 <= x0 <= x1 < P.SENSOR_WIDTH and 0 <= y0 <= y1 < P.SENSOR_HEIGHT):
                raise DeviceError(f"ROI {s.roi}", field="roi",
                                  expected=f"x0 <= x1 < {P.SENSOR_WIDTH}, y0 <= y1 < {P.SENSOR_HEIGHT} (inclusive)")
            roi = (x0, y0, x1, y1)
        else:
            roi = (0, 0, P.SENSOR_WIDTH - 1, P.SENSOR_HEIGHT - 1)
        self._command(P.Cmd.SET_ROI, b"".join(P.u16(v) for v in roi))
        self._roi = roi
        # The header reports the real size; until a frame arrives assume the inclusive ROI.
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
                self._parser.discard()
                if got_any or partial:
                    self._silent = 0
                    raise P.TruncatedPacket(f"reply incomplete after timeout ({partial} bytes buffered)")
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
            raw = RawFrame(taps=taps[None].astype(np.float32), freq_hz=[freq], theta_rad=theta,
                           integration_time_s=int_time_s, camera=camera, timestamp_s=ts, sequence=seq,
                           temperature_c=h.temperature_c, meta=meta)
            return Frame(raw=raw, sequence=seq, timestamp_s=ts)
        if mode == "distance":
            dist, amp = P.decode_distance_amplitude(img)
            depth = distance_codes_to_frame(dist, amp, camera, ts, seq, h.temperature_c, meta)
            return Frame(depth=depth, sequence=seq, timestamp_s=ts)
        gray = P.decode_grayscale(img)
        return Frame(images={"grayscale": gray.copy()}, sequence=seq, timestamp_s=ts)

    def _camera_for(self, h: P.ImageHeader) -> CameraModel:
        roi = (h.origin_x, h.origin_y, h.origin_x + h.width - 1, h.origin_y + h.height - 1)
        if self._camera.shape != (h.height, h.width) or roi != self._roi:
            if roi[2] >= P.SENSOR_WIDTH or roi[3] >= P.SENSOR_HEIGHT:
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
    """The camera model of an inclusive ROI ``(x0, y0, x1, y1)`` of the sensor."""
    x0, y0, x1, y1 = roi
    if (x0, y0, x1, y1) == (0, 0, camera.width - 1, camera.height - 1):
        return camera
    return replace(camera, width=x1 - x0 + 1, height=y1 - y0 + 1, cx=camera.cx - x0, cy=camera.cy - y0)


def dcs_to_canonical(dcs: np.ndarray, profile: DeviceProfile = TOFCAM635) -> tuple[np.ndarray, np.ndarray]:
    """Device DCS ``[4, H, W]`` (12-bit around 2048) -> canonical taps (DN, offset removed) and phases."""
    taps = np.asarray(dcs, dtype=np.float32) - np.float32(profile.dcs_offset)
    return profile.taps.to_canonical(taps)


def canonical_phases(profile: DeviceProfile = TOFCAM635) -> np.ndarray:
    """Phases of the canonical taps the driver delivers (what an emulator must render)."""
    _, theta = profile.taps.to_canonical(np.zeros((len(profile.taps.theta_rad), 1, 1)))
    return theta


def canonical_to_dcs(taps: np.ndarray, profile: DeviceProfile = TOFCAM635) -> np.ndarray:
    """Inverse of :func:`dcs_to_canonical` (for the emulator): taps at :func:`canonical_phases`
    -> device stack order, plus the mid-scale offset. Not quantised or clipped."""
    t = np.asarray(taps)
    if profile.taps.order is not None:
        t = np.take(t, np.argsort(np.asarray(profile.taps.order)), axis=-3)
    return t + profile.dcs_offset


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
