"""DepthAI v3 driver for Luxonis ToF cameras (OAK-D SR PoE / OAK ToF 33D modules).

Device path: a ``dai.node.ToF`` (built on the ToF socket with a ``ToFConfig``: phase
unwrapping level and error threshold, median filter, FPPN / wiggle / temperature /
optical / distortion corrections, phase-shuffle temporal filter, burst mode), its outputs
(``depth``, ``amplitude``, ``intensity``, ``phase``, ``raw`` where the device provides
them) read through ``createOutputQueue`` queues, the camera model from the device's
factory calibration.

Host path (CI, no hardware): the same queues fed by a host node
(:class:`HostToFSource`, a ``dai.node.ThreadedHostNode`` in a
``dai.Pipeline(createImplicitDevice=False)``) that sends ``ImgFrame`` messages shaped like
the ToF node's: RAW16 depth in mm, RAW16 amplitude and intensity, float phase, with
sequence numbers and device timestamps. Decoding, pairing and unit conversion are the
same code for both paths.

Pairing: every output carries the frame's sequence number; a frame is complete when each
requested output has delivered that sequence. Incomplete sequences older than the newest
complete one are dropped and counted (never mixed: depth of frame n is never paired with
the amplitude of frame n+1). Timestamps are the device clock (``getTimestampDevice``),
converted to seconds.

Depth kind (Luxonis ToF docs): with ``enableOpticalCorrection`` the node returns a
z-map (rectified, "distance to depth conversion"); without it, the radial distance along
each pixel's ray. The driver reads the setting and converts to radial. With
``enableDistortionCorrection`` (the default) the images are undistorted, so the camera
model has zero distortion; otherwise the factory coefficients are used.

Specs: ``depthai`` (first device), ``depthai:DEVICE_ID_OR_IP``; ``depthai-sim`` (a host
pipeline rendering a plane, :class:`tofhil.sim.sources.PlaneScene`, given by the application; ``depthai-sim:DIST_M`` sets the
plane's distance; ``depthai-sim:SCENE`` sends frames of the simulator twin for a scene
name or file, :class:`tofhil.sim.sources.TwinScene`).
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable

import numpy as np

from tofhil.camera import CameraModel, load_camera_preset
from tofhil.drivers.base import (CaptureSettings, DeviceDisconnected, DeviceEntry, DeviceError, DeviceInfo,
                                 Driver, Frame, FrameDropped, register_driver)
from tofhil.drivers.sources import frame_source
from tofhil.frame_source import DepthScene
from tofhil.frames import DepthFrame

OUTPUTS = ("depth", "amplitude", "intensity", "phase", "raw")
DEFAULT_OUTPUTS = ("depth", "amplitude", "intensity")
MEDIAN = {"off": "MEDIAN_OFF", "3x3": "KERNEL_3x3", "5x5": "KERNEL_5x5", "7x7": "KERNEL_7x7"}
PROFILES = {"low": "LOW_RANGE", "mid": "MID_RANGE", "high": "HIGH_RANGE"}
PRESET = "oak_tof_33d"
#: The host source's colour frames: their own sequence numbers (this offset) and device times
#: this much after the ToF frame's (the colour sensor is not hardware-synchronised).
COLOR_SEQUENCE_OFFSET = 100_000
HOST_COLOR_DELAY_S = 0.004
#: A colour frame goes with the ToF frame whose device time is nearest, if within this.
COLOR_MATCH_S = 0.015
#: The 33D module's lower modulation frequency: its single-frequency ambiguity range is
#: c / (2 * 80 MHz) = 1.87 m (phase unwrapping level 0 in the Luxonis docs).
BASE_FREQ_HZ = 80e6


def _dai() -> Any:
    # depthai logs warnings to stdout at import (e.g. "USB protocol not available - If running in
    # a container..." on every listing without USB): only its errors are news to a user. An
    # explicit DEPTHAI_LEVEL still wins.
    os.environ.setdefault("DEPTHAI_LEVEL", "error")
    try:
        import depthai as dai
    except ImportError as exc:  # pragma: no cover - depthai is a dependency
        raise DeviceError(f"depthai is not installed ({exc})", field="depthai",
                          expected="pip install depthai>=3") from None
    return dai


# --------------------------------------------------------------------------- settings
@dataclass
class ToFSettings:
    """The ToF node's configuration (``CaptureSettings.extra`` keys of the same names)."""

    phase_unwrapping_level: int = 4
    phase_unwrap_error_threshold: int = 100
    median: str = "off"
    enable_phase_unwrapping: bool = True
    enable_optical_correction: bool = False   # False: radial distance; True: z-map
    enable_distortion_correction: bool = True
    enable_fppn_correction: bool = True
    enable_wiggle_correction: bool = True
    enable_temperature_correction: bool = False
    enable_phase_shuffle_temporal_filter: bool = True
    enable_burst_mode: bool = False
    profile: str | None = None                # low | mid | high (a Luxonis preset, applied first)
    fps: float | None = None
    outputs: tuple[str, ...] = DEFAULT_OUTPUTS
    #: Record the device's colour camera beside ToF (``Frame.images["rgb"]``, the session's rgb/ group).
    color: bool = False
    color_size: tuple[int, int] = (640, 480)

    @classmethod
    def from_extra(cls, extra: dict[str, Any]) -> "ToFSettings":
        known = {f for f in cls.__dataclass_fields__}
        unknown = sorted(set(extra) - known)
        if unknown:
            raise DeviceError(f"unknown DepthAI option(s) {', '.join(unknown)}", field="extra",
                              expected="one of " + ", ".join(sorted(known)))
        s = cls(**extra)
        s.outputs = tuple(s.outputs.split(",") if isinstance(s.outputs, str) else s.outputs)
        bad = [o for o in s.outputs if o not in OUTPUTS]
        if bad or "depth" not in s.outputs:
            raise DeviceError(f"outputs {list(s.outputs)}", field="outputs",
                              expected=f"'depth' plus any of {', '.join(OUTPUTS)}")
        if s.median not in MEDIAN:
            raise DeviceError(f"median {s.median!r}", field="median", expected=" | ".join(MEDIAN))
        if s.profile is not None and s.profile not in PROFILES:
            raise DeviceError(f"profile {s.profile!r}", field="profile", expected=" | ".join(PROFILES))
        try:
            s.color_size = tuple(int(v) for v in (s.color_size.split("x") if isinstance(s.color_size, str)
                                                  else s.color_size))
        except (TypeError, ValueError):
            s.color_size = ()
        if len(s.color_size) != 2 or min(s.color_size) < 16:
            raise DeviceError(f"color_size {extra.get('color_size')!r}", field="color_size",
                              expected="WIDTHxHEIGHT of the colour output, e.g. 640x480")
        if not 0 <= int(s.phase_unwrapping_level) <= 6:
            raise DeviceError(f"phase unwrapping level {s.phase_unwrapping_level}", field="phase_unwrapping_level",
                              expected="0..6 (0 = off, 1.87 m range at 80 MHz)")
        return s

    def to_tof_config(self) -> Any:
        """A ``dai.ToFConfig`` with these settings."""
        dai = _dai()
        cfg = dai.ToFConfig()
        if self.profile is not None:
            cfg.setProfilePreset(getattr(dai.ToFConfig.Profile, PROFILES[self.profile]))
        cfg.phaseUnwrappingLevel = int(self.phase_unwrapping_level)
        cfg.phaseUnwrapErrorThreshold = int(self.phase_unwrap_error_threshold)
        cfg.enablePhaseUnwrapping = bool(self.enable_phase_unwrapping)
        cfg.enableOpticalCorrection = bool(self.enable_optical_correction)
        cfg.enableDistortionCorrection = bool(self.enable_distortion_correction)
        cfg.enableFPPNCorrection = bool(self.enable_fppn_correction)
        cfg.enableWiggleCorrection = bool(self.enable_wiggle_correction)
        cfg.enableTemperatureCorrection = bool(self.enable_temperature_correction)
        cfg.enablePhaseShuffleTemporalFilter = bool(self.enable_phase_shuffle_temporal_filter)
        cfg.enableBurstMode = bool(self.enable_burst_mode)
        cfg.median = getattr(dai.MedianFilter, MEDIAN[self.median])
        return cfg

    @property
    def depth_kind(self) -> str:
        return "z" if self.enable_optical_correction else "radial"


# --------------------------------------------------------------------------- decoding
def decode_imgframe(msg: Any, name: str) -> np.ndarray:
    """An ``ImgFrame`` -> ``[H, W]`` array (uint8/uint16, or float32 for float images).

    Reads the raw bytes with the frame's stride, so padded rows decode correctly. A ``raw``
    output in a packed format is returned as its bytes (1-D uint8), undecoded.
    """
    dai = _dai()
    t = msg.getType()
    dtypes = {dai.ImgFrame.Type.RAW16: "<u2", dai.ImgFrame.Type.RAW8: "u1", dai.ImgFrame.Type.GRAY8: "u1",
              dai.ImgFrame.Type.GRAYF16: "<f2", dai.ImgFrame.Type.RAW32: "<f4"}
    if t not in dtypes and name == "raw":
        # Raw sensor frames come in device-specific packings (RAW10/PACK...): keep the bytes.
        return np.asarray(msg.getData(), dtype=np.uint8).copy()
    if t not in dtypes:
        raise FrameDropped(f"{name} frame has type {t.name}", field=name,
                           expected="RAW16, RAW8, GRAY8, GRAYF16 or RAW32 (float)")
    dt = np.dtype(dtypes[t])
    w, h = msg.getWidth(), msg.getHeight()
    data = np.asarray(msg.getData(), dtype=np.uint8)
    stride = msg.getStride() or w * dt.itemsize
    if stride < w * dt.itemsize or data.size < stride * (h - 1) + w * dt.itemsize:
        raise FrameDropped(f"{name} frame {msg.getSequenceNum()} has {data.size} bytes for {w}x{h} "
                           f"stride {stride}", field=name, expected=f"{w}x{h} {t.name} pixels")
    if data.size < stride * h:  # last row unpadded
        data = np.concatenate([data, np.zeros(stride * h - data.size, np.uint8)])
    rows = data[:stride * h].reshape(h, stride)[:, :w * dt.itemsize]
    img = np.ascontiguousarray(rows).view(dt).reshape(h, w)
    return img.astype(np.float32) if dt.kind == "f" else img


def device_time_s(msg: Any) -> float:
    """The frame's device-clock timestamp in seconds."""
    return msg.getTimestampDevice().total_seconds()


class SequencePairer:
    """Group messages of several outputs by sequence number.

    ``add(name, seq, item)`` returns the complete ``{name: item}`` set of the oldest
    sequence that has every output, or None. Incomplete sequences older than a complete
    one can never complete (queues deliver in order), so they are dropped and reported
    through ``on_drop(seq, missing)``.
    """

    def __init__(self, names: tuple[str, ...], on_drop: Callable[[int, list[str]], None],
                 max_pending: int = 16) -> None:
        self.names = names
        self.pending: dict[int, dict[str, Any]] = {}
        self.on_drop = on_drop
        self.max_pending = max_pending
        self.ready: list[tuple[int, dict[str, Any]]] = []

    def add(self, name: str, seq: int, item: Any) -> None:
        bucket = self.pending.setdefault(seq, {})
        bucket[name] = item
        if len(bucket) == len(self.names):
            del self.pending[seq]
            for old in sorted(s for s in self.pending if s < seq):
                missing = [n for n in self.names if n not in self.pending[old]]
                del self.pending[old]
                self.on_drop(old, missing)
            self.ready.append((seq, bucket))
        while len(self.pending) > self.max_pending:  # a stream went silent: bound memory
            old = min(self.pending)
            missing = [n for n in self.names if n not in self.pending.pop(old)]
            self.on_drop(old, missing)

    def pop(self) -> tuple[int, dict[str, Any]] | None:
        return self.ready.pop(0) if self.ready else None


# --------------------------------------------------------------------------- host source
_HOST_SOURCE_CLASS: Any = None


def factory_lens(calib: Any, socket: Any) -> tuple[str, tuple[float, ...], dict[str, float]]:
    """(model, dist, terms left out) of a socket's factory lens (``dai.CalibrationHandler``):
    ``Fisheye`` -> ``fisheye`` (k1..k4); ``Perspective`` -> OpenCV's 14 coefficients as the
    shortest model that holds them (``plumb_bob``, ``rational`` with or without thin prism).
    The sensor tilt (tau_x, tau_y) has no place in these models: left out when not zero,
    and said so."""
    dai = _dai()
    coeffs = [float(c) for c in calib.getDistortionCoefficients(socket)]
    kind = getattr(calib, "getDistortionModel", None)
    if kind is not None and kind(socket) == dai.CameraModel.Fisheye:
        return "fisheye", tuple((coeffs + [0.0] * 4)[:4]), {}
    c = (coeffs + [0.0] * 14)[:14]
    dropped = {name: v for name, v in zip(("tau_x", "tau_y"), c[12:14]) if v != 0.0}
    if any(c[8:12]):
        return "rational", tuple(c[:12]), dropped
    if any(c[5:8]):
        return "rational", tuple(c[:8]), dropped
    return "plumb_bob", tuple(c[:5]), dropped


def host_source_class() -> Any:
    """The :class:`HostToFSource` class (defined lazily: it subclasses a depthai type)."""
    global _HOST_SOURCE_CLASS
    if _HOST_SOURCE_CLASS is not None:
        return _HOST_SOURCE_CLASS
    dai = _dai()
    import datetime

    class HostToFSource(dai.node.ThreadedHostNode):
        """Sends ToF-shaped ImgFrames (one per output per frame) from the host."""

        def __init__(self) -> None:
            super().__init__()
            self.outs = {name: self.createOutput() for name in OUTPUTS + ("rgb",)}
            self.color_image: np.ndarray | None = None
            self.frames: list[dict[str, np.ndarray]] = []
            self.scene: Any = None             # the DepthScene, from setup()
            self.sent = 0
            self.done = threading.Event()

        def setup(self, scene: Any, camera: CameraModel, settings: ToFSettings) -> None:
            self.frames = []
            for img in scene.render_frames(camera):
                depth_m = img["z_m"] if settings.enable_optical_correction else img["radial_m"]
                # The device's wire formats: RAW16 depth in mm (rounded), RAW16 amplitude/intensity.
                self.frames.append({
                    "depth": np.clip(np.round(depth_m * 1000.0), 0, 65535).astype(np.uint16),
                    "amplitude": np.clip(np.round(img["amplitude"]), 0, 65535).astype(np.uint16),
                    "intensity": np.clip(np.round(img["intensity"]), 0, 65535).astype(np.uint16),
                    "phase": img["phase"].astype(np.float32)})
            self.scene = scene
            self.wanted = settings.outputs
            self.color_image = None
            if settings.color:
                if not hasattr(scene, "color"):
                    raise DeviceError("the host plane has no colour camera", field="color",
                                      expected="depthai-sim:SCENE with an rgb_camera block, or color: false")
                self.color_image = scene.color()[0]

        def _color_message(self, seq: int, t_s: float) -> Any:
            # the colour sensor counts its own frames and is not hardware-synchronised: its own
            # sequence numbers (offset) and a device time a few milliseconds after the ToF frame's
            img = self.color_image
            f = dai.ImgFrame()
            h, w = img.shape[:2]
            f.setData(np.frombuffer(np.ascontiguousarray(img).tobytes(), dtype=np.uint8))
            f.setType(dai.ImgFrame.Type.RGB888i)
            f.setWidth(w)
            f.setHeight(h)
            f.setStride(w * 3)
            f.setSequenceNum(seq + COLOR_SEQUENCE_OFFSET)
            t = datetime.timedelta(seconds=t_s + HOST_COLOR_DELAY_S)
            f.setTimestampDevice(t)
            f.setTimestamp(t)
            return f

        def _message(self, name: str, seq: int, t_s: float) -> Any:
            f = dai.ImgFrame()
            img = self.frames[seq % len(self.frames)][name]
            h, w = img.shape
            if img.dtype == np.float32:
                f.setData(np.frombuffer(img.tobytes(), dtype=np.uint8))
                f.setType(dai.ImgFrame.Type.RAW32)
                f.setStride(w * 4)
            else:
                f.setFrame(img)
                f.setType(dai.ImgFrame.Type.RAW16)
                f.setStride(w * 2)
            f.setWidth(w)
            f.setHeight(h)
            f.setSequenceNum(seq)
            f.setTimestampDevice(datetime.timedelta(seconds=t_s))
            f.setTimestamp(datetime.timedelta(seconds=t_s))
            return f

        def run(self) -> None:
            seq = 0
            period = 1.0 / self.scene.fps
            t_next = time.monotonic()
            while self.isRunning() and (self.scene.n_frames is None or seq < self.scene.n_frames):
                t_s = 10.0 + seq * period  # device clock: starts at 10 s, ticks at the frame rate
                for name in self.wanted:
                    if name == "raw":
                        continue  # raw tap streams are device-specific; not produced by the host
                    if name == "amplitude" and seq in self.scene.drop_amplitude_of:
                        continue
                    self.outs[name].send(self._message(name, seq, t_s))
                if self.color_image is not None:
                    self.outs["rgb"].send(self._color_message(seq, t_s))
                seq += 1
                self.sent = seq
                t_next += period  # a fixed frame clock, like the sensor's
                time.sleep(max(0.0, t_next - time.monotonic()))
            self.done.set()

    _HOST_SOURCE_CLASS = HostToFSource
    return HostToFSource


# --------------------------------------------------------------------------- driver
class DepthAIToF(Driver):
    """A Luxonis ToF camera (``depthai[:ID]``) or the host-only pipeline (``depthai-sim``)."""

    scheme = "depthai"

    def __init__(self, spec: str = "depthai", *, host_scene: DepthScene | None = None,
                 camera: CameraModel | None = None) -> None:
        super().__init__(spec)
        scheme, _, rest = spec.partition(":")
        self.host = scheme.lower() == "depthai-sim" or host_scene is not None
        if self.host and host_scene is None:
            host_scene = frame_source("depthai", rest or None)
        self.device_id = "" if self.host else rest
        self.host_scene = host_scene
        self._camera = camera
        self.tof = ToFSettings()
        self.pipeline: Any = None
        self.device: Any = None
        self.queues: dict[str, Any] = {}
        self.config_queue: Any = None
        self.source: Any = None
        self.unmatched = 0
        self._info = DeviceInfo(driver="depthai", model="")
        self._pairer: SequencePairer | None = None
        self._dropped: list[str] = []
        #: The colour camera (``color: true``): its model and the ToF -> colour transform (m).
        self.rgb_camera: CameraModel | None = None
        self.tof_to_rgb: np.ndarray | None = None
        self._colors: list[tuple[float, Any]] = []       # (device time s, message), oldest first
        self.color_queue: Any = None
        self._held: tuple[int, dict[str, Any]] | None = None

    # ---- lifecycle ----------------------------------------------------------
    def _open_device(self) -> None:
        dai = _dai()
        if self.host:
            self._camera = self._camera or self.host_scene.camera_model()
            self._info = DeviceInfo(driver="depthai", model=f"host pipeline ({type(self.host_scene).__name__})",
                                    vendor="tofhil",
                                    firmware=f"depthai {dai.__version__}",
                                    extra={"host_scene": asdict(self.host_scene)})
            return
        found = dai.Device.getAllAvailableDevices()
        if not found:
            raise DeviceError("no DepthAI device found (USB or PoE)", field="--device",
                              expected="a Luxonis ToF camera connected and reachable")
        try:
            self.device = dai.Device(dai.DeviceInfo(self.device_id)) if self.device_id else dai.Device()
        except RuntimeError as exc:
            raise DeviceError(f"cannot open DepthAI device {self.device_id or '(first)'}: {exc}",
                              field="--device", expected="an available device id or IP") from None
        socket = self._tof_socket()
        calib = self.device.readCalibration()
        self._socket = socket
        self._calib = calib
        self._info = DeviceInfo(driver="depthai", model=self.device.getDeviceName(),
                                serial=self.device.getDeviceId(), vendor="Luxonis",
                                firmware=f"depthai {dai.__version__}",
                                extra={"platform": self.device.getPlatformAsString(), "tof_socket": socket.name})

    def _tof_socket(self) -> Any:
        dai = _dai()
        for feat in self.device.getConnectedCameraFeatures():
            if dai.CameraSensorType.TOF in feat.supportedTypes:
                self._sensor_size = (feat.width, feat.height)
                return feat.socket
        raise DeviceError("the device has no ToF sensor", field="--device",
                          expected="an OAK-D SR PoE or OAK ToF module")

    def _device_camera(self) -> CameraModel:
        """Intrinsics (and distortion unless the node undistorts) from the factory calibration."""
        w, h = self._sensor_size
        k = np.asarray(self._calib.getCameraIntrinsics(self._socket, w, h), dtype=float)
        model, dist = "plumb_bob", (0.0,) * 5
        if not self.tof.enable_distortion_correction:
            model, dist, dropped = factory_lens(self._calib, self._socket)
            if dropped:
                self._info.extra["lens_terms_dropped"] = dropped
        return CameraModel(width=w, height=h, fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], dist=dist,
                           distortion_model=model, name=f"{PRESET} (factory calibration)",
                           extra=dict(load_camera_preset(PRESET).extra))

    def _build(self) -> None:
        """Create the pipeline, its outputs' queues and start it."""
        dai = _dai()
        names = tuple(self.tof.outputs)
        if self.host:
            self.pipeline = dai.Pipeline(createImplicitDevice=False)
            src = self.pipeline.create(host_source_class())
            src.setup(self.host_scene, self._camera, self.tof)
            outputs = {n: src.outs[n] for n in names}
            self.source = src
            color_out = None
            if self.tof.color:
                _, self.rgb_camera, self.tof_to_rgb = self.host_scene.color()
                color_out = src.outs["rgb"]
        else:
            self._camera = self._device_camera()
            self.pipeline = dai.Pipeline(self.device)
            kwargs: dict[str, Any] = {"boardSocket": self._socket}
            if self.tof.fps is not None:
                kwargs["fps"] = float(self.tof.fps)
            tof = self.pipeline.create(dai.node.ToF).build(**kwargs)
            tof.setInitialConfig(self.tof.to_tof_config())
            outputs = {}
            for n in names:
                port = getattr(tof, n, None)
                if port is None:
                    raise DeviceError(f"this depthai has no ToF output {n!r}", field="outputs",
                                      expected="depth, amplitude, intensity, phase or raw")
                outputs[n] = port
            self.config_queue = tof.inputConfig.createInputQueue()
            color_out = self._build_color(dai) if self.tof.color else None
        # Host: blocking queues (nothing lost, the producer waits); device: a slow host drops
        # the oldest frames instead of stalling the camera, and the pairer counts them.
        self.queues = {n: o.createOutputQueue(maxSize=8, blocking=self.host) for n, o in outputs.items()}
        self.color_queue = None if color_out is None else color_out.createOutputQueue(maxSize=8, blocking=self.host)
        self._colors, self._held = [], None
        self._pairer = SequencePairer(names, self._on_unmatched)
        self.pipeline.start()

    def _build_color(self, dai: Any) -> Any:
        """The device's colour camera: a ``dai.node.Camera`` on its COLOR socket with an RGB888i
        output of ``color_size``, its factory intrinsics and distortion for that size, and the
        ToF -> colour extrinsics (``getCameraExtrinsics(tof, colour, unit=METER)``: points in the
        ToF frame to the colour frame)."""
        socket = None
        for feat in self.device.getConnectedCameraFeatures():
            if feat.socket != self._socket and dai.CameraSensorType.COLOR in feat.supportedTypes:
                socket = feat.socket
                break
        if socket is None:
            raise DeviceError("the device has no colour camera", field="color",
                              expected="color: false on a ToF-only device (OAK ToF 33D); the OAK-D SR PoE has one")
        w, h = self.tof.color_size
        cam = self.pipeline.create(dai.node.Camera).build(socket)
        kw: dict[str, Any] = {} if self.tof.fps is None else {"fps": float(self.tof.fps)}
        out = cam.requestOutput((w, h), dai.ImgFrame.Type.RGB888i, **kw)
        k = np.asarray(self._calib.getCameraIntrinsics(socket, w, h), dtype=float)
        model, dist, dropped = factory_lens(self._calib, socket)
        if dropped:
            self._info.extra["color_lens_terms_dropped"] = dropped
        self.rgb_camera = CameraModel(width=w, height=h, fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2],
                                      dist=dist, distortion_model=model,
                                      name=f"{socket.name} colour (factory calibration)")
        self.tof_to_rgb = np.asarray(self._calib.getCameraExtrinsics(self._socket, socket,
                                                                     unit=dai.LengthUnit.METER), dtype=float)
        self._info.extra["color_socket"] = socket.name
        return out

    def _teardown(self) -> None:
        if self.pipeline is not None:
            try:
                self.pipeline.stop()
                self.pipeline.wait()
            except RuntimeError:
                pass
        self.pipeline = None
        self.queues = {}
        self.color_queue = None
        self.source = None

    def _close_device(self) -> None:
        self._teardown()
        if self.device is not None:
            try:
                self.device.close()
            except RuntimeError:
                pass
            self.device = None

    def _apply_settings(self, settings: CaptureSettings) -> None:
        if settings.mode != "distance":
            raise DeviceError(f"mode {settings.mode!r} is not available", field="mode",
                              expected="distance (DepthAI ToF delivers depth; raw taps are device-internal)")
        for name, value in (("integration_time_s", settings.integration_time_s), ("roi", settings.roi),
                            ("mod_freq_hz", settings.mod_freq_hz), ("channel", settings.channel)):
            if value is not None:
                raise DeviceError(f"{name} cannot be set on a DepthAI ToF camera", field=name,
                                  expected="leave it unset; use phase_unwrapping_level / profile in extra")
        new = ToFSettings.from_extra(dict(settings.extra))
        restart = self.pipeline is not None and (new.outputs != self.tof.outputs or new.fps != self.tof.fps
                                                 or new.color != self.tof.color
                                                 or new.color_size != self.tof.color_size or self.host)
        self.tof = new
        if self.pipeline is not None and not restart and self.config_queue is not None:
            self.config_queue.send(new.to_tof_config())  # runtime change, no restart
            if not self.host:
                self._camera = self._device_camera()
        elif restart:
            self._teardown()

    @property
    def camera(self) -> CameraModel:
        if self._camera is None:
            if not self.host and self.device is not None:
                self._camera = self._device_camera()
            else:
                self._camera = load_camera_preset(PRESET)
        return self._camera

    def info(self) -> DeviceInfo:
        self._info.extra["tof_config"] = {k: (list(v) if isinstance(v, tuple) else v)
                                          for k, v in asdict(self.tof).items()}
        self._info.extra["depth_kind_on_wire"] = self.tof.depth_kind
        return self._info

    # ---- frames -------------------------------------------------------------
    def _on_unmatched(self, seq: int, missing: list[str]) -> None:
        self.unmatched += 1
        self._dropped.append(f"sequence {seq} lacks {', '.join(missing)}")

    def read_frame(self, timeout_s: float = 2.0) -> Frame:
        self._require_open()
        if self.pipeline is None:
            self._build()
        assert self._pairer is not None
        deadline = time.monotonic() + timeout_s
        while True:
            if self._dropped:
                raise FrameDropped(self._dropped.pop(0), field="depthai")
            got = self._held or self._pairer.pop()
            self._held = None
            if got is not None:
                if self._color_ready(got):
                    return self._to_frame(*got)
                self._held = got      # its colour frame may still be on the way
            progressed = False
            if self.color_queue is not None:
                msg = self.color_queue.tryGet()
                while msg is not None:
                    self._colors = self._colors[-15:] + [(device_time_s(msg), msg)]
                    progressed = True
                    msg = self.color_queue.tryGet()
            for name, q in self.queues.items():
                msg = q.tryGet()
                while msg is not None:
                    self._pairer.add(name, msg.getSequenceNum(), msg)
                    progressed = True
                    msg = q.tryGet()
            if progressed:
                continue
            if not self.pipeline.isRunning():
                raise DeviceDisconnected("the DepthAI pipeline stopped", field="depthai")
            if self.host and self.source is not None and self.source.done.is_set() and not any(
                    q.has() for q in self.queues.values()):
                raise DeviceError("the host source has sent all its frames", field="depthai-sim",
                                  expected="fewer frames than the scene's n_frames")
            if time.monotonic() > deadline:
                if self._held is not None:   # the colour stream stalled: the ToF frame goes alone
                    got, self._held = self._held, None
                    return self._to_frame(*got)
                raise FrameDropped(f"no complete frame within {timeout_s} s", field="depthai")
            time.sleep(0.001)

    def _color_ready(self, got: tuple[int, dict[str, Any]]) -> bool:
        """A ToF frame may go when colour is off or the colour stream has passed its time."""
        if self.color_queue is None:
            return True
        t = device_time_s(got[1]["depth"])
        return any(tc >= t for tc, _ in self._colors)   # colour arrives in time order: the nearest is known

    def _color_for(self, t: float) -> np.ndarray | None:
        """The colour image (uint8 [H, W, 3], RGB) nearest in device time to ``t``, within COLOR_MATCH_S."""
        if not self._colors:
            return None
        tc, msg = min(self._colors, key=lambda c: abs(c[0] - t))
        if abs(tc - t) > COLOR_MATCH_S:
            return None
        h, w = msg.getHeight(), msg.getWidth()
        data = np.asarray(msg.getData(), dtype=np.uint8)
        if data.size < h * w * 3:
            return None
        return data[:h * w * 3].reshape(h, w, 3).copy()

    def _to_frame(self, seq: int, msgs: dict[str, Any]) -> Frame:
        cam = self.camera
        depth_raw = decode_imgframe(msgs["depth"], "depth")
        if depth_raw.shape != cam.shape:
            raise FrameDropped(f"depth frame {seq} is {depth_raw.shape[1]}x{depth_raw.shape[0]}", field="depth",
                               expected=f"{cam.width}x{cam.height} (the camera model)")
        valid = depth_raw > 0
        depth_m = depth_raw.astype(np.float64) * 1e-3  # RAW16 depth is in millimetres
        radial = cam.z_to_radial(depth_m) if self.tof.depth_kind == "z" else depth_m
        images = {n: decode_imgframe(m, n) for n, m in msgs.items() if n not in ("depth",)}
        t = device_time_s(msgs["depth"])
        if self.color_queue is not None:
            rgb = self._color_for(t)
            if rgb is not None:
                images["rgb"] = rgb
        amp = images.get("amplitude")
        inten = images.get("intensity")
        depth = DepthFrame(distance_m=np.where(valid, radial, 0.0).astype(np.float32), kind="radial", camera=cam,
                           amplitude=None if amp is None else amp.astype(np.float32),
                           intensity=None if inten is None else inten.astype(np.float32), valid=valid,
                           timestamp_s=t, sequence=seq,
                           meta={"depth_kind_on_wire": self.tof.depth_kind})
        return Frame(depth=depth, images=images, sequence=seq, timestamp_s=t)


# --------------------------------------------------------------------------- registry
def _list_depthai() -> list[DeviceEntry]:
    try:
        dai = _dai()
        found = dai.Device.getAllAvailableDevices()
    except (DeviceError, RuntimeError):
        return []
    return [DeviceEntry(f"depthai:{d.getDeviceId()}", f"Luxonis DepthAI device {d.name} ({d.state.name})")
            for d in found]


def _list_sim() -> list[DeviceEntry]:
    return [DeviceEntry("depthai-sim", "DepthAI host-only pipeline rendering a plane at 1 m "
                        "(depthai-sim:DIST_M)", "emulated")]


register_driver("depthai", lambda spec: DepthAIToF(spec), lister=_list_depthai,
                description="Luxonis ToF camera through DepthAI v3 (depthai[:DEVICE_ID_OR_IP])")
register_driver("depthai-sim", lambda spec: DepthAIToF(spec), lister=_list_sim,
                description="DepthAI host-only pipeline (no hardware): a rendered plane through real queues")
