"""The driver interface every camera back-end implements, and the device registry.

A driver opens a device, configures it (:class:`CaptureSettings`), reads frames one at a
time (:meth:`Driver.read_frame`) and closes it; :meth:`Driver.stream` wraps
``read_frame`` with the robustness rules every driver shares:

* a corrupted or truncated frame raises :class:`FrameDropped`; the stream counts it in
  :attr:`Driver.stats` and goes on with the next frame (it is never yielded as data);
* a lost device raises :class:`DeviceDisconnected`; the stream retries with exponential
  backoff (:meth:`Driver.reconnect`, which re-applies the last settings) and either goes
  on or, when the retries are exhausted, raises so the caller can end the session cleanly
  with every completed frame saved.

Frames carry the core types: :class:`tofhil.frames.RawFrame` (canonical taps, converted at
the driver edge from the device's tap convention) and/or :class:`tofhil.frames.DepthFrame`
(radial distance in metres), with the device's timestamp and sequence number.

Devices are named by a spec string ``SCHEME[:REST]`` (``emulator``, ``usb``, ``usb:1:5``,
``serial:/dev/ttyACM0``, ``depthai``...). A driver module registers its schemes with
:func:`register_driver` when imported; :func:`open_device` and :func:`list_devices` import
the modules in :data:`DRIVER_MODULES` lazily (a module that does not exist yet is skipped),
so a new back-end only has to call ``register_driver`` at import time. Driver modules must
import heavy SDKs (depthai, usb backends) inside functions, not at module top.
"""

from __future__ import annotations

import importlib
import math
import time
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Iterator

import numpy as np

from tofhil.camera import CameraModel
from tofhil.errors import DeviceError
from tofhil.frames import DepthFrame, RawFrame

__all__ = [
    "CaptureSettings", "DeviceEntry", "DeviceInfo", "DeviceDisconnected", "Driver", "DriverStats", "EndOfRecording",
    "Frame", "FrameDropped", "DRIVER_MODULES", "register_driver", "open_device", "list_devices",
    "registered_schemes", "parse_spec", "create_driver",
]

#: Acquisition modes a driver may support (``CaptureSettings.mode``).
MODES = ("dcs", "distance", "grayscale")


# --------------------------------------------------------------------------- errors
class FrameDropped(DeviceError):
    """One frame was corrupt, truncated or incomplete; the device is still usable."""


class DeviceDisconnected(DeviceError):
    """The device went away (unplugged, stalled beyond recovery, port closed)."""


class EndOfRecording(DeviceError):
    """A recorded source (replay) has no more frames: a capture ends cleanly with what it got."""


# --------------------------------------------------------------------------- data
@dataclass
class CaptureSettings:
    """What to acquire and how. ``None`` leaves the device's current/default value.

    ``mode``: ``"dcs"`` (raw correlation taps -> RawFrame), ``"distance"`` (distance and
    amplitude -> DepthFrame) or ``"grayscale"`` (intensity only -> ``Frame.images``).
    ``roi`` is ``(x0, y0, x1, y1)`` in sensor pixels, half-open (x1, y1 exclusive, as numpy slices
    and the TOFcam635 firmware: ``(4, 4, 156, 12)`` is 152 x 8 pixels).
    ``extra`` holds device-specific options (documented by each driver).
    """

    mode: str = "dcs"
    integration_time_s: float | None = None
    mod_freq_hz: float | None = None
    channel: int | None = None
    min_amplitude: float | None = None
    roi: tuple[int, int, int, int] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise DeviceError(f"unknown acquisition mode {self.mode!r}", field="mode",
                              expected=" | ".join(MODES))
        if self.integration_time_s is not None and not (self.integration_time_s > 0):
            raise DeviceError(f"integration time {self.integration_time_s!r} s",
                              field="integration_time_s", expected="a positive number of seconds")
        if self.mod_freq_hz is not None and not (self.mod_freq_hz > 0):
            raise DeviceError(f"modulation frequency {self.mod_freq_hz!r} Hz",
                              field="mod_freq_hz", expected="a positive frequency in Hz")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class DeviceInfo:
    """Identity of an opened device, stored in the session's ``device`` attribute."""

    driver: str
    model: str
    serial: str = ""
    firmware: str = ""
    vendor: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = {"driver": self.driver, "model": self.model, "serial": self.serial,
             "firmware": self.firmware, "vendor": self.vendor}
        d.update(self.extra)
        return d


@dataclass
class Frame:
    """One acquisition: raw taps and/or depth, plus any extra images (e.g. ``grayscale``)."""

    raw: RawFrame | None = None
    depth: DepthFrame | None = None
    images: dict[str, np.ndarray] = field(default_factory=dict)
    sequence: int = 0
    timestamp_s: float = math.nan


@dataclass
class DriverStats:
    """Counters a capture reports in its summary."""

    frames: int = 0
    dropped: int = 0
    reconnects: int = 0
    #: The reason of each dropped frame / reconnect, most recent last (bounded).
    events: list[str] = field(default_factory=list)

    def note(self, text: str) -> None:
        self.events.append(text)
        del self.events[:-100]


@dataclass(frozen=True)
class DeviceEntry:
    """One line of ``tofhil devices``: a spec that :func:`open_device` accepts."""

    spec: str
    description: str
    kind: str = "connected"  # "connected" | "emulated"


# --------------------------------------------------------------------------- driver
class Driver(ABC):
    """Base class of every camera driver. Use as a context manager::

        with open_device("emulator") as dev:
            dev.configure(CaptureSettings(mode="dcs", integration_time_s=500e-6))
            for frame in dev.stream(10):
                ...
    """

    #: Registry scheme of this driver (``"usb"``, ``"emulator"``...), for messages.
    scheme: str = ""

    def __init__(self, spec: str = "") -> None:
        self.spec = spec
        self.stats = DriverStats()
        self.settings = CaptureSettings()
        self._open = False
        #: Reconnect policy used by :meth:`stream`.
        self.max_reconnects = 5
        self.backoff_s = 0.05
        self.backoff_max_s = 2.0

    # ---- to implement -------------------------------------------------------
    @abstractmethod
    def _open_device(self) -> None:
        """Find and open the device; raise :class:`DeviceError` with a reason if impossible."""

    @abstractmethod
    def _close_device(self) -> None:
        """Release the device; must not raise if it is already gone."""

    @abstractmethod
    def _apply_settings(self, settings: CaptureSettings) -> None:
        """Send ``settings`` to the device (called by :meth:`configure` and after reconnects)."""

    @abstractmethod
    def read_frame(self, timeout_s: float = 2.0) -> Frame:
        """Acquire one frame in the configured mode.

        Raises :class:`FrameDropped` for a bad frame and :class:`DeviceDisconnected` when
        the device is lost.
        """

    @abstractmethod
    def info(self) -> DeviceInfo:
        """Identity of the opened device (model, serial, firmware, chip ids...)."""

    @property
    @abstractmethod
    def camera(self) -> CameraModel:
        """Camera model of the frames this driver produces (with the current ROI)."""

    # ---- lifecycle ----------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> "Driver":
        if not self._open:
            self._open_device()
            self._open = True
        return self

    def close(self) -> None:
        if self._open:
            self._open = False
            self._close_device()

    def configure(self, settings: CaptureSettings | None = None, **changes: Any) -> CaptureSettings:
        """Apply ``settings`` (or keyword changes to the current ones); returns what is in force."""
        if settings is None:
            merged = self.settings.to_dict() | changes
            settings = CaptureSettings(**merged)
        elif changes:
            raise TypeError("pass either a CaptureSettings or keyword changes, not both")
        self._require_open()
        self._apply_settings(settings)
        self.settings = settings
        return settings

    def reconnect(self) -> None:
        """Close and reopen the device and re-apply the last settings."""
        try:
            self._close_device()
        except Exception:  # the device is gone; closing a dead handle may fail any way
            pass
        self._open = False
        self._open_device()
        self._open = True
        self._apply_settings(self.settings)

    def _require_open(self) -> None:
        if not self._open:
            raise DeviceError("device is not open", field=self.spec or self.scheme)

    def __enter__(self) -> "Driver":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- streaming ----------------------------------------------------------
    def stream(self, n_frames: int | None = None, *, timeout_s: float = 2.0,
               max_dropped: int | None = None) -> Iterator[Frame]:
        """Yield ``n_frames`` good frames (forever when None), dropping bad ones.

        Dropped frames and reconnects are counted in :attr:`stats`. When the device stays
        away after ``max_reconnects`` attempts (backoff doubling from ``backoff_s``), the
        last :class:`DeviceDisconnected` propagates; frames already yielded are the
        caller's to keep. ``max_dropped`` bounds consecutive drops (None: 50 + n_frames).
        """
        self._require_open()
        got = 0
        consecutive_drops = 0
        limit = max_dropped if max_dropped is not None else 50 + (n_frames or 0)
        while n_frames is None or got < n_frames:
            try:
                frame = self.read_frame(timeout_s)
            except FrameDropped as exc:
                self.stats.dropped += 1
                self.stats.note(f"dropped: {exc}")
                consecutive_drops += 1
                if consecutive_drops > limit:
                    raise DeviceError(f"{consecutive_drops} frames in a row were corrupt; last: {exc}",
                                      field=self.spec or self.scheme) from None
                continue
            except DeviceDisconnected as exc:
                self.stats.note(f"disconnected: {exc}")
                self._reconnect_with_backoff(exc)
                continue
            consecutive_drops = 0
            got += 1
            self.stats.frames += 1
            yield frame

    def _reconnect_with_backoff(self, cause: DeviceDisconnected) -> None:
        delay = self.backoff_s
        last: DeviceError = cause
        for _ in range(self.max_reconnects):
            time.sleep(delay)
            try:
                self.reconnect()
            except DeviceError as exc:  # still away (DeviceDisconnected or not found)
                last = exc
                delay = min(2.0 * delay, self.backoff_max_s)
                continue
            self.stats.reconnects += 1
            self.stats.note("reconnected")
            return
        self._open = False
        raise DeviceDisconnected(f"device lost and not back after {self.max_reconnects} attempts "
                                 f"({last})", field=self.spec or self.scheme) from None


# --------------------------------------------------------------------------- registry
#: Modules imported (in order) before a spec is resolved; each registers its schemes.
#: A module that is not present is skipped, so back-ends can land independently.
DRIVER_MODULES: list[str] = [
    "tofhil.drivers.tofcam635.driver",
    "tofhil.drivers.tofcam635.emulator",
    "tofhil.drivers.depthai.driver",
    "tofhil.drivers.importers.replay",
]

DriverFactory = Callable[[str], Driver]
DeviceLister = Callable[[], list[DeviceEntry]]


@dataclass
class _Registration:
    factory: DriverFactory
    lister: DeviceLister | None
    description: str


_REGISTRY: dict[str, _Registration] = {}
_loaded = False


def register_driver(scheme: str, factory: DriverFactory, *, lister: DeviceLister | None = None,
                    description: str = "") -> None:
    """Make ``SCHEME[:REST]`` specs open with ``factory(spec)`` (which returns an unopened driver).

    ``lister`` (optional) returns the devices of this scheme that are present now, for
    ``tofhil devices``; it must be quick and must not raise when no device is attached.
    """
    scheme = scheme.strip().lower()
    if not scheme or ":" in scheme:
        raise ValueError(f"bad driver scheme {scheme!r}")
    _REGISTRY[scheme] = _Registration(factory, lister, description)


def _load_driver_modules() -> None:
    global _loaded
    if _loaded:
        return
    _loaded = True
    for name in DRIVER_MODULES:
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:  # a real missing dependency inside the module: report it
                raise


def registered_schemes() -> dict[str, str]:
    """Scheme -> description of every registered driver."""
    _load_driver_modules()
    return {k: r.description for k, r in sorted(_REGISTRY.items())}


def parse_spec(spec: str) -> tuple[str, str]:
    """``"serial:/dev/ttyACM0"`` -> ``("serial", "/dev/ttyACM0")``; ``"usb"`` -> ``("usb", "")``."""
    scheme, _, rest = spec.strip().partition(":")
    return scheme.lower(), rest


def create_driver(spec: str) -> Driver:
    """An unopened driver for ``spec``; unknown schemes raise a DeviceError listing the known ones."""
    _load_driver_modules()
    scheme, _ = parse_spec(spec)
    reg = _REGISTRY.get(scheme)
    if reg is None:
        known = ", ".join(f"{k}[:...]" for k in sorted(_REGISTRY)) or "none registered"
        raise DeviceError(f"unknown device {spec!r}", field="--device", expected=known)
    return reg.factory(spec)


def open_device(spec: str) -> Driver:
    """Create and open the driver for ``spec``; use the result as a context manager."""
    return create_driver(spec).open()


def list_devices() -> list[DeviceEntry]:
    """Every device the registered drivers can see now (connected first, then emulated)."""
    _load_driver_modules()
    entries: list[DeviceEntry] = []
    for scheme, reg in sorted(_REGISTRY.items()):
        if reg.lister is None:
            continue
        try:
            entries.extend(reg.lister())
        except DeviceError as exc:
            entries.append(DeviceEntry(scheme, f"unavailable: {exc}", "connected"))
    entries.sort(key=lambda e: (e.kind != "connected", e.spec))
    return entries
