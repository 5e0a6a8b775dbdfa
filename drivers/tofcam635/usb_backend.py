"""The emulated TOFcam635 as a pyusb backend, so the real pyusb driver runs unchanged.

``usb.core.find(idVendor=0x0483, backend=EmulatorBackend([emulator]))`` returns a
``usb.core.Device`` with the descriptors of the STM32 virtual COM port the camera
enumerates as: configuration 1 with a CDC communication interface (0, interrupt IN 0x82)
and a CDC data interface (1, bulk OUT 0x01, bulk IN 0x81). Bytes written to 0x01 go to
the emulator's command parser; reads on 0x81 return its replies.

Faithful to what libusb does on Linux where it matters to a driver: the kernel's cdc_acm
driver is "attached" to both interfaces until detached (claiming before that fails with
EBUSY); an unplugged device raises ENODEV on every handle and reappears under a new
address; a halted endpoint raises EPIPE until ``clear_halt``; a read with no data waits
(up to 100 ms of the given timeout, to keep tests quick) and raises ``USBTimeoutError``;
``deny_access=True`` makes ``open_device`` fail with EACCES like a missing udev rule.
"""

from __future__ import annotations

import array
import errno
import time
from dataclasses import dataclass, field
from typing import Any

import usb.backend
import usb.core

from tofhil.drivers.tofcam635.emulator import Epc635Emulator
from tofhil.drivers.tofcam635.transport import USB_PID, USB_VID

EP_OUT = 0x01
EP_IN = 0x81
EP_NOTIFY = 0x82
#: Longest a read with no data waits before timing out (keeps tests fast).
MAX_IDLE_WAIT_S = 0.1


class _Desc:
    """A descriptor: named integer fields, as pyusb reads them with getattr."""

    def __init__(self, **fields_: Any) -> None:
        self.__dict__.update(fields_)
        self.extra_descriptors: list[int] = []


def _device_descriptor(bus: int, address: int) -> _Desc:
    return _Desc(bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0x02, bDeviceSubClass=0x02,
                 bDeviceProtocol=0x00, bMaxPacketSize0=64, idVendor=USB_VID, idProduct=USB_PID,
                 bcdDevice=0x0200, iManufacturer=1, iProduct=2, iSerialNumber=3, bNumConfigurations=1,
                 address=address, bus=bus, port_number=1, port_numbers=(1,), speed=2)


_CONFIG = _Desc(bLength=9, bDescriptorType=2, wTotalLength=67, bNumInterfaces=2, bConfigurationValue=1,
                iConfiguration=0, bmAttributes=0xC0, bMaxPower=50)
_INTERFACES = [
    _Desc(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0, bNumEndpoints=1,
          bInterfaceClass=0x02, bInterfaceSubClass=0x02, bInterfaceProtocol=0x01, iInterface=0),
    _Desc(bLength=9, bDescriptorType=4, bInterfaceNumber=1, bAlternateSetting=0, bNumEndpoints=2,
          bInterfaceClass=0x0A, bInterfaceSubClass=0x00, bInterfaceProtocol=0x00, iInterface=0),
]
_ENDPOINTS = [
    [_Desc(bLength=7, bDescriptorType=5, bEndpointAddress=EP_NOTIFY, bmAttributes=0x03, wMaxPacketSize=8,
           bInterval=16, bRefresh=0, bSynchAddress=0)],
    [_Desc(bLength=7, bDescriptorType=5, bEndpointAddress=EP_OUT, bmAttributes=0x02, wMaxPacketSize=64,
           bInterval=0, bRefresh=0, bSynchAddress=0),
     _Desc(bLength=7, bDescriptorType=5, bEndpointAddress=EP_IN, bmAttributes=0x02, wMaxPacketSize=64,
           bInterval=0, bRefresh=0, bSynchAddress=0)],
]
_STRINGS = {1: "STMicroelectronics", 2: "TOFcam635 (tofhil emulator)"}


@dataclass
class _DeviceId:
    """What ``enumerate_devices`` yields: one emulator at one bus address."""

    emulator: Epc635Emulator
    bus: int
    address: int
    generation: int
    serial: str


@dataclass
class _Handle:
    dev: _DeviceId
    claimed: set[int] = field(default_factory=set)
    kernel_attached: dict[int, bool] = field(default_factory=lambda: {0: True, 1: True})


def _err(message: str, code: int) -> usb.core.USBError:
    return usb.core.USBError(message, None, code)


class EmulatorBackend(usb.backend.IBackend):
    """pyusb backend exposing one or more :class:`Epc635Emulator` as USB devices."""

    def __init__(self, emulators: list[Epc635Emulator], *, bus: int = 1, deny_access: bool = False) -> None:
        super().__init__()
        self.emulators = list(emulators)
        self.bus = bus
        self.deny_access = deny_access
        self.kernel_detaches = 0

    # ---- enumeration ----------------------------------------------------
    def enumerate_devices(self):  # type: ignore[no-untyped-def]
        for i, emu in enumerate(self.emulators):
            if emu.present:
                # a replugged device gets a new address, like a real bus
                yield _DeviceId(emu, self.bus, 10 + i + 16 * emu.generation, emu.generation,
                                f"EMU{emu.WAFER_ID}.{emu.CHIP_ID + i}")

    def get_parent(self, dev: _DeviceId) -> None:
        return None

    def get_device_descriptor(self, dev: _DeviceId) -> _Desc:
        return _device_descriptor(dev.bus, dev.address)

    def get_configuration_descriptor(self, dev: _DeviceId, config: int) -> _Desc:
        if config != 0:
            raise IndexError("configuration index out of range")
        return _CONFIG

    def get_interface_descriptor(self, dev: _DeviceId, intf: int, alt: int, config: int) -> _Desc:
        if config != 0 or alt != 0 or not 0 <= intf < len(_INTERFACES):
            raise IndexError("interface index out of range")
        return _INTERFACES[intf]

    def get_endpoint_descriptor(self, dev: _DeviceId, ep: int, intf: int, alt: int, config: int) -> _Desc:
        if config != 0 or alt != 0 or not 0 <= intf < len(_ENDPOINTS) or not 0 <= ep < len(_ENDPOINTS[intf]):
            raise IndexError("endpoint index out of range")
        return _ENDPOINTS[intf][ep]

    # ---- handles ----------------------------------------------------------
    def _alive(self, h: _Handle) -> Epc635Emulator:
        emu = h.dev.emulator
        if not emu.present or emu.generation != h.dev.generation:
            raise _err("No such device (it may have been disconnected)", errno.ENODEV)
        return emu

    def open_device(self, dev: _DeviceId) -> _Handle:
        if self.deny_access:
            raise _err("Access denied (insufficient permissions)", errno.EACCES)
        h = _Handle(dev)
        self._alive(h)
        return h

    def close_device(self, dev_handle: _Handle) -> None:
        dev_handle.claimed.clear()

    def set_configuration(self, dev_handle: _Handle, config_value: int) -> None:
        self._alive(dev_handle)
        if config_value not in (1, -1, 0):
            raise _err("Invalid parameter", errno.EINVAL)

    def get_configuration(self, dev_handle: _Handle) -> int:
        self._alive(dev_handle)
        return 1

    def set_interface_altsetting(self, dev_handle: _Handle, intf: int, altsetting: int) -> None:
        self._alive(dev_handle)

    def claim_interface(self, dev_handle: _Handle, intf: int) -> None:
        self._alive(dev_handle)
        if dev_handle.kernel_attached.get(intf, False):
            raise _err("Resource busy (cdc_acm holds the interface)", errno.EBUSY)
        dev_handle.claimed.add(intf)

    def release_interface(self, dev_handle: _Handle, intf: int) -> None:
        dev_handle.claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle: _Handle, intf: int) -> bool:
        self._alive(dev_handle)
        return dev_handle.kernel_attached.get(intf, False)

    def detach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        self._alive(dev_handle)
        dev_handle.kernel_attached[intf] = False
        self.kernel_detaches += 1

    def attach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        self._alive(dev_handle)
        dev_handle.kernel_attached[intf] = True

    # ---- transfers ----------------------------------------------------------
    def bulk_write(self, dev_handle: _Handle, ep: int, intf: int, data: array.array, timeout: int) -> int:
        emu = self._alive(dev_handle)
        if ep != EP_OUT or 1 not in dev_handle.claimed:
            raise _err("Invalid endpoint or interface not claimed", errno.EINVAL)
        emu.receive(bytes(data))
        return len(data)

    def bulk_read(self, dev_handle: _Handle, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        emu = self._alive(dev_handle)
        if ep != EP_IN or 1 not in dev_handle.claimed:
            raise _err("Invalid endpoint or interface not claimed", errno.EINVAL)
        if emu.stalled:
            raise _err("Pipe error (endpoint halted)", errno.EPIPE)
        data = emu.transmit(len(buff))
        if not data:
            time.sleep(min(timeout / 1000.0 if timeout else MAX_IDLE_WAIT_S, MAX_IDLE_WAIT_S))
            self._alive(dev_handle)
            data = emu.transmit(len(buff))
            if not data:
                raise usb.core.USBTimeoutError("Operation timed out", None, errno.ETIMEDOUT)
        buff[: len(data)] = array.array("B", data)
        return len(data)

    def intr_read(self, dev_handle: _Handle, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        self._alive(dev_handle)
        raise usb.core.USBTimeoutError("Operation timed out", None, errno.ETIMEDOUT)  # no serial-state events

    def clear_halt(self, dev_handle: _Handle, ep: int) -> None:
        emu = self._alive(dev_handle)
        if ep == EP_IN:
            emu.stalled = False

    def reset_device(self, dev_handle: _Handle) -> None:
        self._alive(dev_handle).reset()

    def ctrl_transfer(self, dev_handle: _Handle, bmRequestType: int, bRequest: int, wValue: int, wIndex: int,
                      data: array.array, timeout: int) -> int:
        self._alive(dev_handle)
        if bmRequestType == 0x80 and bRequest == 0x06 and wValue >> 8 == 0x03:  # GET_DESCRIPTOR(string)
            index = wValue & 0xFF
            if index == 0:
                raw = bytes([4, 3, 0x09, 0x04])  # LANGID en-US
            else:
                text = dev_handle.dev.serial if index == 3 else _STRINGS.get(index, "")
                enc = text.encode("utf-16-le")
                raw = bytes([2 + len(enc), 3]) + enc
            n = min(len(raw), len(data))
            data[:n] = array.array("B", raw[:n])
            return n
        if bmRequestType == 0x21 and bRequest in (0x20, 0x22):  # CDC SET_LINE_CODING / SET_CONTROL_LINE_STATE
            return len(data) if data is not None else 0
        raise _err("Pipe error (request not supported)", errno.EPIPE)
