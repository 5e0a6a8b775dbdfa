"""What the emulated TOFcam635 sees: image sources (noise-free canonical taps of the full
160 x 60 sensor) and the per-frame noise added to them.

* :class:`AnalyticWall` -- a flat wall at a known distance with a closed-form amplitude,
  for fast tests that must not depend on the renderer;
* :class:`SimulatedSource` -- the simulator twin (``tofhil.sim.pipeline.simulate``) run
  with a hidden-truth effects set the twin's scene does not contain
  (:data:`HIDDEN_TRUTH_EFFECTS`).
"""

from __future__ import annotations

import math
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tofhil.camera import CameraModel, load_camera_preset
from tofhil.demod import distance_to_phase, phasor, taps_from_signal, wrapped_phase
from tofhil.drivers.tofcam635 import protocol as P
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
    #: The emitter's beam (the twin's default: ``cos^1``), at the camera centre.
    profile_cos_n: float = 1.0


class AnalyticWall(ImageSource):
    """Closed form: the twin's radiometry of a plane (:func:`tofhil.sim.radiometry.plane_view`):
    radial distance ``d = z / ray_z``; amplitude ``A1 * p(theta) cos(incidence) cos^4(alpha) / d^2``
    relative to the axis at 1 m; phase ``4 pi f d / c``; offset = ambient + A."""

    def __init__(self, wall: WallSpec | None = None, camera: CameraModel | None = None) -> None:
        super().__init__()
        self.wall = wall or WallSpec()
        self.camera = camera or load_camera_preset("epc635")
        self.description = f"analytic wall at {self.wall.distance_m:g} m"

    def _relative(self) -> np.ndarray:
        from tofhil.sim.radiometry import Plane, plane_relative_amplitude
        from tofhil.sim.scene import BeamProfile

        return plane_relative_amplitude(self.camera, Plane(self.wall.distance_m),
                                        BeamProfile("cos_n", n=self.wall.profile_cos_n))

    def radial_m(self) -> np.ndarray:
        return self.wall.distance_m / self.camera.ray_z

    def amplitude_dn(self, integration_time_s: float = REFERENCE_INTEGRATION_TIME_S) -> np.ndarray:
        return (self.wall.amplitude_at_1m_dn * (integration_time_s / REFERENCE_INTEGRATION_TIME_S)
                * self._relative())

    def signal(self, freq_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = self.amplitude_dn()
        phi = distance_to_phase(self.radial_m(), freq_hz)
        return a, phi, self.wall.ambient_dn + a

    def scene_text(self) -> str:
        w = self.wall
        return (f"# tofhil emulator analytic source\nwall:\n  distance_m: {w.distance_m}\n"
                f"  amplitude_at_1m_dn: {w.amplitude_at_1m_dn}\n  ambient_dn: {w.ambient_dn}\n"
                f"  profile: {{type: cos_n, n: {w.profile_cos_n}}}\n")


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


# --------------------------------------------------------------------------- noise
@dataclass
class NoiseModel:
    """Per-frame noise of one tap, in DN: the simulator's sensor noise (``tofhil.sim.sensor``:
    shot noise of the collected electrons, then read noise), with the electrons counted at
    ``electrons_per_dn`` (``inf``: no shot noise) and the read noise given in DN."""

    read_noise_dn: float = 1.5
    electrons_per_dn: float = 8.0

    def apply(self, taps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        from tofhil.sim.sensor import read_noise, shot_noise

        out = np.asarray(taps, dtype=np.float32)
        if math.isfinite(self.electrons_per_dn):
            e_per_dn = np.float32(self.electrons_per_dn)
            out = shot_noise(out * e_per_dn, rng) / e_per_dn
        return read_noise(out, np.float32(self.read_noise_dn), rng).astype(np.float32, copy=False)
