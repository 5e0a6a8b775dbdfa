"""Byte pipes to the TOFcam635: the bulk endpoints of its USB CDC data interface (pyusb,
detaching the kernel's cdc_acm), or a serial port (the CDC tty, or the emulator's pty); the
USB lookup (VID/PID) and the mapping of USB errors (permissions -> the shipped udev rule)."""

from __future__ import annotations

import errno
from abc import ABC, abstractmethod
from importlib import resources
from typing import Any

from tofhil.drivers.base import DeviceDisconnected, FrameDropped
from tofhil.errors import DeviceError

USB_VID = 0x0483
USB_PID = 0x5740  # STM32 virtual COM port, as enumerated by the TOFcam635
CDC_DATA_CLASS = 0x0A
CDC_COMM_CLASS = 0x02


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
