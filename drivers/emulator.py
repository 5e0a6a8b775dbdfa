"""A faithful TOFcam635 emulator: the epc635 protocol on top of an image source.

:class:`Epc635Emulator` is the camera's firmware as a byte-in/byte-out state machine: it
parses 14-byte commands, keeps the settings (ROI, integration time, modulation frequency
and channel, amplitude limit...), and answers with ACKs, identification, chip info,
firmware release, temperature and images (DCS, distance, distance + amplitude,
grayscale) framed exactly as the real camera does (:mod:`tofhil.drivers.epc635_protocol`).
Two transports carry it: an in-process pyusb backend
(:mod:`tofhil.drivers.emulator_backend`), and a pseudo-terminal
(:mod:`tofhil.drivers.pty_server`).

Images come from an :class:`ImageSource` that returns noise-free canonical taps, rendered
once per modulation frequency (cached) and scaled with the integration time; the emulator
adds per-frame noise, converts to the
device's DCS (12-bit, mid-scale 2048, differential so the offset cancels) and, like the
firmware, computes distance and amplitude from them. Sources:

* :class:`AnalyticWall` -- a flat wall at a known distance with a closed-form amplitude,
  for fast tests that must not depend on the renderer;
* :class:`SimulatedSource` -- the simulator twin (``tofhil.sim.pipeline.simulate``) run
  with a hidden-truth effects set the twin's scene does not contain
  (:data:`HIDDEN_TRUTH_EFFECTS`).

:class:`FaultPlan` injects CRC errors, truncated replies, garbage between packets, silent
timeouts, USB stalls and disconnects (with reconnection) on image replies.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel, load_camera_preset
from tofhil.demod import distance_to_phase, phasor, taps_from_signal, wrapped_phase
from tofhil.drivers import epc635_protocol as P
from tofhil.drivers.base import DeviceEntry, DeviceInfo, register_driver
from tofhil.drivers.tofcam635 import TOFCAM635, DeviceProfile, TofCam635, canonical_phases, canonical_to_dcs
from tofhil.errors import DeviceError, InputFileError

#: Integration time all source amplitudes are quoted at (the vendor initialize() value).
REFERENCE_INTEGRATION_TIME_S = 125e-6


# --------------------------------------------------------------------------- sources
class ImageSource(ABC):
    """Noise-free canonical taps (DN) of the full 160 x 60 sensor.

    Sources render at :data:`REFERENCE_INTEGRATION_TIME_S`, once per modulation frequency
    (cached); signal, offset and ambient all grow linearly with the exposure, so other
    integration times are a scale factor, not a new render.
    """

    camera: CameraModel
    description: str = ""

    def __init__(self) -> None:
        self._cache: dict[float, np.ndarray] = {}
        self._lock = threading.Lock()

    def taps(self, freq_hz: float, integration_time_s: float, theta_rad: np.ndarray) -> np.ndarray:
        """``[K, H, W]`` float32 taps ``B + A cos(phi - theta_k)`` for this exposure."""
        key = float(freq_hz)
        with self._lock:
            ref = self._cache.get(key)
            if ref is None:
                a, phi, b = self.signal(freq_hz)
                ref = taps_from_signal(a, phi, b, theta_rad).astype(np.float32)
                ref.setflags(write=False)
                self._cache[key] = ref
        return ref * np.float32(integration_time_s / REFERENCE_INTEGRATION_TIME_S)

    @abstractmethod
    def signal(self, freq_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Amplitude (DN), phase (rad) and offset (DN) images ``[H, W]`` at the reference exposure."""

    def noise_model(self) -> "NoiseModel":
        return NoiseModel()

    def scene_text(self) -> str:
        return ""


@dataclass
class WallSpec:
    """A flat Lambertian wall facing the camera (normal along -z) at depth ``distance_m``."""

    distance_m: float = 1.0
    #: Amplitude (DN) on the optical axis for a wall at 1 m, at the reference integration time.
    amplitude_at_1m_dn: float = 600.0
    ambient_dn: float = 150.0


class AnalyticWall(ImageSource):
    """Closed form: radial distance ``d = z / ray_z``; amplitude ``A = A1 * ray_z / d^2``
    (inverse square of the emitter/return path times Lambertian cos of incidence); phase
    ``4 pi f d / c``; offset = ambient + A."""

    def __init__(self, wall: WallSpec | None = None, camera: CameraModel | None = None) -> None:
        super().__init__()
        self.wall = wall or WallSpec()
        self.camera = camera or load_camera_preset("epc635")
        self.description = f"analytic wall at {self.wall.distance_m:g} m"

    def radial_m(self) -> np.ndarray:
        return self.wall.distance_m / self.camera.ray_z

    def amplitude_dn(self, integration_time_s: float = REFERENCE_INTEGRATION_TIME_S) -> np.ndarray:
        d = self.radial_m()
        return (self.wall.amplitude_at_1m_dn * (integration_time_s / REFERENCE_INTEGRATION_TIME_S)
                * self.camera.ray_z / d**2)

    def signal(self, freq_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = self.amplitude_dn()
        phi = distance_to_phase(self.radial_m(), freq_hz)
        return a, phi, self.wall.ambient_dn + a

    def scene_text(self) -> str:
        w = self.wall
        return (f"# tofhil emulator analytic source\nwall:\n  distance_m: {w.distance_m}\n"
                f"  amplitude_at_1m_dn: {w.amplitude_at_1m_dn}\n  ambient_dn: {w.ambient_dn}\n")


#: The emulated camera's hidden truth: imperfections the twin's scene does not model
#: (tofhil.sim.effects names; documented in docs/drivers.md). Merged over the scene's own
#: ``effects:`` block.
HIDDEN_TRUTH_EFFECTS: dict[str, dict[str, Any]] = {
    "stray_light": {"weight": 0.03, "sigma_px": 12.0, "veil": 0.005},
    "wiggling": {"h3_amplitude": 0.03, "h3_phase_rad": 0.4},
    "fixed_pattern": {"row_delay_s": 2e-12, "col_delay_s": -1e-12, "random_delay_s": 5e-12, "seed": 635},
}

#: What makes the scene's camera a TOFcam635 (ASSUMED where the data sheet is silent): the
#: epc635 preset, its four 90-degree DCS, an LED illumination brighter than a lab LED ring,
#: a DN scale that puts a white wall at 1 m near 10 % of the 12-bit DCS range at 125 us, and
#: a 16-bit single-ended ADC so that only the device's 12-bit differential DCS clip.
TOFCAM635_OVERRIDES: dict[str, Any] = {
    "camera": {"preset": "epc635"},
    "emitter": {"power_w": 2.0},
    "sensor": {"taps": 4, "theta_deg": [0, 90, 180, 270], "integration_time_s": REFERENCE_INTEGRATION_TIME_S,
               "conversion_gain_dn_per_e": 0.15, "adc_bits": 16, "full_well_e": 1_000_000},
}


class SimulatedSource(ImageSource):
    """Frames rendered by the simulator twin from a scene file, through the hidden-truth model.

    The scene is loaded with :data:`TOFCAM635_OVERRIDES` (the emulated device is a
    TOFcam635 whatever camera the scene names) and rendered once per modulation frequency
    with noise off and the hidden-truth effects on; the emulator adds per-frame noise with
    the scene sensor's read noise and conversion gain. Rendered taps are re-expressed at the
    device's tap phases through the complex signal (``phasor``).
    """

    def __init__(self, scene_path: str | Path, effects: dict[str, dict[str, Any]] | None = None,
                 seed: int = 635) -> None:
        super().__init__()
        try:
            from tofhil.sim.pipeline import resolve_effects  # noqa: F401
            from tofhil.sim.scene import load_scene
        except ImportError as exc:
            raise DeviceError(f"the simulator twin is not available ({exc})", field="--scene",
                              expected="tofhil.sim.pipeline") from None
        self.scene_path = str(scene_path)
        self.scene = load_scene(scene_path, overrides=TOFCAM635_OVERRIDES)
        self.hidden = HIDDEN_TRUTH_EFFECTS if effects is None else effects
        self.seed = seed
        self.camera = self.scene.camera
        if self.camera.shape != (P.SENSOR_HEIGHT, P.SENSOR_WIDTH):
            raise InputFileError(f"camera is {self.camera.width}x{self.camera.height}", file=scene_path,
                                 field="camera", expected=f"{P.SENSOR_WIDTH}x{P.SENSOR_HEIGHT} (preset epc635)")
        self.description = f"simulated scene {self.scene_path}"
        self.meta: dict[str, Any] = {}

    def effects(self) -> dict[str, dict[str, Any]]:
        from tofhil.sim.pipeline import resolve_effects

        known = resolve_effects(self.scene, None)  # what the twin's scene itself models
        return resolve_effects(self.scene, {**known, **self.hidden})

    def signal(self, freq_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import dataclasses

        from tofhil.sim.pipeline import simulate

        scene = dataclasses.replace(self.scene, sensor=dataclasses.replace(self.scene.sensor,
                                                                           freq_hz=(float(freq_hz),)))
        raw = simulate(scene, 1, self.seed, noise=False, effects=self.effects())[0]
        self.meta = dict(raw.meta)
        taps = np.asarray(raw.taps[0], dtype=np.float64) - float(raw.meta.get("black_level_dn", 0.0))
        s = phasor(taps, raw.theta_rad)
        scale = REFERENCE_INTEGRATION_TIME_S / raw.integration_time_s if raw.integration_time_s > 0 else 1.0
        return np.abs(s) * scale, wrapped_phase(s), taps.mean(axis=0) * scale

    def noise_model(self) -> "NoiseModel":
        sensor = self.scene.sensor  # the resolved SensorConfig
        gain = sensor.conversion_gain_dn_per_e
        return NoiseModel(read_noise_dn=sensor.read_noise_e * gain, electrons_per_dn=1.0 / gain)

    def scene_text(self) -> str:
        return getattr(self.scene, "text", "") or ""


def default_source() -> ImageSource:
    """The bundled ``bench_demo`` scene when the twin and the scene exist, else an analytic wall."""
    try:
        from tofhil.sim.scene import bundled_scenes

        if "bench_demo" in bundled_scenes():
            return SimulatedSource("bench_demo")
    except (ImportError, DeviceError):
        pass
    return AnalyticWall()


def source_from_spec(scene: str | None) -> ImageSource:
    """``None`` -> :func:`default_source`; ``wall:1.5`` -> analytic wall at 1.5 m; else a scene file/name."""
    if scene is None or scene == "":
        return default_source()
    if scene.startswith("wall"):
        _, _, dist = scene.partition(":")
        try:
            return AnalyticWall(WallSpec(distance_m=float(dist) if dist else 1.0))
        except ValueError:
            raise DeviceError(f"bad wall distance {dist!r}", field="--scene", expected="wall:METRES") from None
    return SimulatedSource(scene)


# --------------------------------------------------------------------------- noise and faults
@dataclass
class NoiseModel:
    """Per-frame noise of one tap in DN: read noise plus shot noise ``var = c / gain``."""

    read_noise_dn: float = 1.5
    electrons_per_dn: float = 8.0

    def apply(self, taps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        var = self.read_noise_dn**2 + np.maximum(taps, 0.0) / self.electrons_per_dn
        return taps + rng.standard_normal(taps.shape, dtype=np.float32) * np.sqrt(var, dtype=np.float32)


FAULT_KINDS = ("crc", "truncate", "garbage", "timeout", "stall", "disconnect")


@dataclass
class FaultPlan:
    """Which image replies go wrong: ``at`` maps the image-request index (0-based) to a
    fault; ``rates`` gives per-request probabilities. ``disconnect_s`` is how long a
    disconnected device stays away."""

    at: dict[int, str] = field(default_factory=dict)
    rates: dict[str, float] = field(default_factory=dict)
    seed: int = 0
    disconnect_s: float = 0.2

    def __post_init__(self) -> None:
        for kind in list(self.at.values()) + list(self.rates):
            if kind not in FAULT_KINDS:
                raise DeviceError(f"unknown fault {kind!r}", field="faults", expected=" | ".join(FAULT_KINDS))
        self._rng = np.random.default_rng(self.seed)

    def fault_for(self, index: int) -> str | None:
        if index in self.at:
            return self.at[index]
        for kind, p in self.rates.items():
            if self._rng.random() < p:
                return kind
        return None

    @classmethod
    def parse(cls, text: str) -> "FaultPlan":
        """``"crc@3,truncate@5,disconnect@8"``, ``"crc=0.05,timeout=0.01"``; ``disconnect_s=2``
        sets how long a disconnect lasts."""
        at: dict[int, str] = {}
        rates: dict[str, float] = {}
        away = 0.2
        for item in filter(None, (t.strip() for t in text.split(","))):
            try:
                if item.startswith("disconnect_s="):
                    away = float(item.partition("=")[2])
                elif "@" in item:
                    kind, idx = item.split("@")
                    at[int(idx)] = kind
                else:
                    kind, p = item.split("=")
                    rates[kind] = float(p)
            except ValueError:
                raise DeviceError(f"bad fault item {item!r}", field="--faults",
                                  expected="KIND@FRAME or KIND=PROBABILITY, comma separated") from None
        return cls(at=at, rates=rates, disconnect_s=away)


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

    def __init__(self, source: ImageSource | None = None, *, profile: DeviceProfile = TOFCAM635,
                 noise: NoiseModel | None = None, faults: FaultPlan | None = None, seed: int = 0,
                 frame_interval_s: float = 0.0) -> None:
        self.source = source or AnalyticWall()
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
        self.roi = (0, 0, P.SENSOR_WIDTH - 1, P.SENSOR_HEIGHT - 1)
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
            x0, y0, x1, y1 = struct.unpack_from("<4H", p, 0)
            x1, y1 = min(x1, P.SENSOR_WIDTH - 1), min(y1, P.SENSOR_HEIGHT - 1)  # vendor sends 160/60
            if x0 > x1 or y0 > y1:
                return P.encode_packet(D.NACK)
            self.roi = (x0, y0, x1, y1)
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
            chip_id=self.CHIP_ID, width=x1 - x0 + 1, height=y1 - y0 + 1, origin_x=x0, origin_y=y0,
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
        c = self.noise.apply(clean[:, y0:y1 + 1, x0:x1 + 1], self.rng) if self.noise else clean[:, y0:y1 + 1, x0:x1 + 1]
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
        b = clean[:, y0:y1 + 1, x0:x1 + 1].mean(axis=0)
        b = self.noise.apply(b[None], self.rng)[0] if self.noise else b
        return np.clip(np.rint(b / 16.0), 0, 255).astype(np.uint8)

    def _firmware_distance(self, dcs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the camera computes from its DCS: distance (mm or code) and amplitude (DN)."""
        taps = dcs.astype(np.float32) - self.profile.dcs_offset
        s = phasor(taps, canonical_phases(self.profile))
        amp = np.abs(s)
        dist_mm = wrapped_phase(s) * (C_M_PER_S / (4 * np.pi * self.freq_hz)) * 1e3
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
        from tofhil.drivers.emulator_backend import EmulatorBackend

        _, scene = spec.partition(":")[::2]
        self.emulator = emulator or Epc635Emulator(source_from_spec(scene or None))
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
