"""The simulated frame sources the emulated cameras are given (``tofhil.frame_source``).

* :class:`AnalyticWall` -- a flat wall at a known distance with a closed-form amplitude, for
  fast tests that must not depend on the renderer (raw taps, the TOFcam635 emulator);
* :class:`SimulatedSource` -- the simulator twin (``tofhil.sim.pipeline.simulate``) run with
  a hidden-truth effects set the twin's scene does not contain (:data:`HIDDEN_TRUTH_EFFECTS`);
* :class:`PlaneScene` and :class:`TwinScene` -- what the DepthAI host pipeline sends (depth,
  amplitude, intensity, phase): the same closed-form plane, or frames of the twin;
* :class:`NoiseModel` -- the per-frame sensor noise the TOFcam635 emulator adds.

The drivers never import this module: the application (``tofhil.app.emulators``) gives the
emulators these sources, or a caller passes one explicitly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tofhil.camera import CameraModel, load_camera_preset
from tofhil.demod import distance_to_phase, phasor, wrapped_phase
from tofhil.errors import DeviceError, InputFileError, TofhilError
from tofhil.frame_source import REFERENCE_INTEGRATION_TIME_S, ImageSource
from tofhil.sim.radiometry import Plane, plane_relative_amplitude, plane_view
from tofhil.sim.scene import BeamProfile, bundled_scenes, load_scene
from tofhil.sim.sensor import read_noise, shot_noise

#: The TOFcam635's sensor (its camera preset's size): a scene the emulator renders must have it.
TOFCAM635_PRESET = "epc635"
#: The OAK ToF camera of the DepthAI host pipeline: its preset and the base modulation
#: frequency its phase image wraps at (the device's, ``tofhil.drivers.depthai.driver``).
DEPTHAI_PRESET = "oak_tof_33d"
DEPTHAI_BASE_FREQ_HZ = 80e6


def plane_images(camera: CameraModel, plane: Plane, profile: BeamProfile) -> tuple[np.ndarray, np.ndarray]:
    """Radial distance (m) and amplitude relative to the axis at 1 m of a Lambertian plane seen
    by a co-located emitter: the one analytic wall both emulators' sources are built on."""
    try:
        d = plane_view(camera, plane, power_w=1.0, profile=profile).radial_m
    except TofhilError:
        raise DeviceError("the plane does not cover the field of view", field="tilt_deg",
                          expected="a tilt smaller than 90 deg minus half the field of view") from None
    return d, plane_relative_amplitude(camera, plane, profile)


# --------------------------------------------------------------------------- raw taps (TOFcam635)
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
        self.camera = camera or load_camera_preset(TOFCAM635_PRESET)
        self.description = f"analytic wall at {self.wall.distance_m:g} m"

    def _images(self) -> tuple[np.ndarray, np.ndarray]:
        return plane_images(self.camera, Plane(self.wall.distance_m), BeamProfile("cos_n", n=self.wall.profile_cos_n))

    def _relative(self) -> np.ndarray:
        return self._images()[1]

    def radial_m(self) -> np.ndarray:
        return self._images()[0]

    def amplitude_dn(self, integration_time_s: float = REFERENCE_INTEGRATION_TIME_S) -> np.ndarray:
        return (self.wall.amplitude_at_1m_dn * (integration_time_s / REFERENCE_INTEGRATION_TIME_S)
                * self._relative())

    def signal(self, freq_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = self.amplitude_dn()
        phi = distance_to_phase(self.radial_m(), freq_hz)
        return a, phi, self.wall.ambient_dn + a

    def noise_model(self) -> "NoiseModel":
        return NoiseModel()

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
#: a 16-bit single-ended ADC so that only the device's 12-bit differential DCS clip. The
#: device's fixed pattern is its own, not the scene's seeded realisation (a scene written for
#: another camera carries one in electrons of that camera): it has none beyond the hidden
#: truth's clock-skew delays, as after the factory calibration a TOFcam635 ships with.
TOFCAM635_OVERRIDES: dict[str, Any] = {
    "camera": {"preset": TOFCAM635_PRESET},
    "emitter": {"power_w": 2.0},
    "sensor": {"taps": 4, "theta_deg": [0, 90, 180, 270], "integration_time_s": REFERENCE_INTEGRATION_TIME_S,
               "conversion_gain_dn_per_e": 0.15, "adc_bits": 16, "full_well_e": 1_000_000,
               "fixed_pattern": {"dsnu_e": 0.0, "prnu": 0.0}},
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
        self.scene_path = str(scene_path)
        self.scene = load_scene(scene_path, overrides=TOFCAM635_OVERRIDES)
        self.hidden = HIDDEN_TRUTH_EFFECTS if effects is None else effects
        self.seed = seed
        self.camera = self.scene.camera
        sensor = load_camera_preset(TOFCAM635_PRESET)
        if self.camera.shape != sensor.shape:
            raise InputFileError(f"camera is {self.camera.width}x{self.camera.height}", file=scene_path, field="camera",
                                 expected=f"{sensor.width}x{sensor.height} (preset {TOFCAM635_PRESET})")
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
    if "bench_demo" in bundled_scenes():
        return SimulatedSource("bench_demo")
    return AnalyticWall()


def source_from_spec(scene: str | None) -> ImageSource:
    """``None`` -> :func:`default_source`; ``wall:1.5`` -> analytic wall at 1.5 m; else a scene file/name."""
    if scene is None or scene == "":
        return default_source()
    if scene == "wall" or scene.startswith("wall:"):  # not wall_card: a scene of its own
        _, _, dist = scene.partition(":")
        try:
            distance_m = float(dist) if dist else 1.0
        except ValueError:
            distance_m = math.nan
        if not (math.isfinite(distance_m) and distance_m > 0):
            raise DeviceError(f"bad wall distance {dist!r} in scene {scene!r}", field="--scene",
                              expected="wall:METRES with a distance > 0, a scene name or a scene file")
        return AnalyticWall(WallSpec(distance_m=distance_m))
    return SimulatedSource(scene)


# --------------------------------------------------------------------------- depth frames (DepthAI host pipeline)
@dataclass
class PlaneScene:
    """What the host source renders: a Lambertian plane seen by a co-located emitter, with the
    twin's radiometry (:func:`tofhil.sim.radiometry.plane_view`).

    The plane is ``n . X = distance_m`` in the camera frame, its normal tilted by
    ``tilt_deg`` about the camera's x axis. Per pixel with unit ray ``r``: radial distance
    ``d = distance_m / (n . r)``; amplitude (counts) ``= k * albedo * p(theta) * cos(incidence) *
    cos^4(off-axis angle) / d^2`` (the emitter's ``cos^n`` beam, inverse square, Lambertian
    reflection, the lens's cos^4 law), ``k`` = ``amplitude_at_1m``; intensity = amplitude
    + ``ambient``; phase = ``2*pi*f*(2d)/c`` wrapped at the 80 MHz base frequency.
    """

    distance_m: float = 1.0
    tilt_deg: float = 0.0
    albedo: float = 0.8
    amplitude_at_1m: float = 2000.0
    ambient: float = 50.0
    #: The emitter's beam ``p(theta) = cos^n`` (the twin's default n = 1).
    profile_cos_n: float = 1.0
    fps: float = 30.0
    #: Fault injection for tests: sequence numbers whose ``amplitude`` message is not sent.
    drop_amplitude_of: tuple[int, ...] = ()
    n_frames: int | None = None

    def camera_model(self) -> CameraModel:
        return load_camera_preset(DEPTHAI_PRESET)

    def render_frames(self, camera: CameraModel) -> list[dict[str, np.ndarray]]:
        return [self.render(camera)]

    def render(self, camera: CameraModel) -> dict[str, np.ndarray]:
        d, relative = plane_images(camera, Plane.tilted(self.distance_m, self.tilt_deg, self.albedo),
                                   BeamProfile("cos_n", n=self.profile_cos_n))
        amp = self.amplitude_at_1m * relative
        phase = distance_to_phase(d, DEPTHAI_BASE_FREQ_HZ)
        return {"radial_m": d, "z_m": d * camera.ray_z, "amplitude": amp, "intensity": amp + self.ambient,
                "phase": phase}


@dataclass
class TwinScene:
    """What the host source sends: frames of the simulator twin (``tofhil.sim``) for a scene.

    The scene (a bundled name or a YAML path) is rendered once and exposed ``realisations``
    times with independent noise (``tofhil.sim.pipeline.simulate``); each raw frame is
    demodulated by the core (``depth_from_raw``) and sent as the device would: depth in mm,
    amplitude and intensity (offset) in the twin's DN, the wrapped phase of the first
    frequency. The frames cycle; the camera is the scene's.
    """

    scene: str
    realisations: int = 4
    seed: int = 0
    fps: float = 30.0
    drop_amplitude_of: tuple[int, ...] = ()
    n_frames: int | None = None

    def _load(self) -> Any:
        return load_scene(self.scene)

    def camera_model(self) -> CameraModel:
        return self._load().camera

    def color(self) -> tuple[np.ndarray, CameraModel, np.ndarray]:
        """The scene's second camera (``rgb_camera``): its grey image as 8-bit RGB (scaled to the
        99.5th percentile), its camera and the true ToF -> camera transform."""
        from tofhil.sim.rgb import render_grey

        sc = self._load()
        second = sc.rgb_camera
        if second is None:
            raise DeviceError(f"scene {self.scene!r} has no rgb_camera block", field="color",
                              expected="a scene with a second camera (docs/scene-format.md) or color: false")
        grey = np.nan_to_num(np.asarray(render_grey(sc, second.camera, second.tof_to_camera, samples=second.samples),
                                        dtype=np.float64))
        top = float(np.percentile(grey, 99.5))
        g8 = np.clip(np.round(255.0 * grey / top), 0, 255).astype(np.uint8) if top > 0 else np.zeros(grey.shape,
                                                                                                        np.uint8)
        return np.repeat(g8[..., None], 3, axis=2), second.camera, np.asarray(second.tof_to_camera, dtype=np.float64)

    def render_frames(self, camera: CameraModel) -> list[dict[str, np.ndarray]]:
        from tofhil.depth import depth_from_raw
        from tofhil.sim.pipeline import simulate

        out = []
        for raw in simulate(self._load(), frames=self.realisations, seed=self.seed):
            d = depth_from_raw(raw)
            radial = np.where(d.valid, d.radial_m, 0.0)
            f0 = float(raw.freq_hz[0])
            out.append({"radial_m": radial, "z_m": radial * camera.ray_z,
                        "amplitude": np.nan_to_num(d.amplitude), "intensity": np.nan_to_num(d.intensity),
                        "phase": distance_to_phase(radial, f0)})
        return out



def host_scene_from_spec(rest: str | None, spec: str = "depthai-sim") -> PlaneScene | TwinScene:
    """What ``depthai-sim[:REST]`` renders: a plane at 1 m, a plane at ``REST`` metres, or the
    twin's frames of the scene (name or file) ``REST``."""
    try:
        scene: PlaneScene | TwinScene = PlaneScene(distance_m=float(rest)) if rest else PlaneScene()
    except ValueError:
        return TwinScene(scene=str(rest))  # a scene name or file for the twin
    if not scene.distance_m > 0:
        raise DeviceError(f"bad spec {spec!r}", field="--device",
                          expected="depthai-sim, depthai-sim:DISTANCE_M (> 0) or depthai-sim:SCENE")
    return scene


# --------------------------------------------------------------------------- noise
@dataclass
class NoiseModel:
    """Per-frame noise of one tap, in DN: the simulator's sensor noise (``tofhil.sim.sensor``:
    shot noise of the collected electrons, then read noise), with the electrons counted at
    ``electrons_per_dn`` (``inf``: no shot noise) and the read noise given in DN."""

    read_noise_dn: float = 1.5
    electrons_per_dn: float = 8.0

    def apply(self, taps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = np.asarray(taps, dtype=np.float32)
        if math.isfinite(self.electrons_per_dn):
            e_per_dn = np.float32(self.electrons_per_dn)
            out = shot_noise(out * e_per_dn, rng) / e_per_dn
        return read_noise(out, np.float32(self.read_noise_dn), rng).astype(np.float32, copy=False)


# --------------------------------------------------------------------------- flat field (photon transfer)
@dataclass
class PixelNoise:
    """Per-frame noise of a correlation pixel's gates, in DN, with the EMVA 1288 sensor's parts:
    shot noise of the collected electrons, the full well (a gate's charge clips there), a
    per-gate dark offset that does not change from frame to frame (DSNU, ``dsnu_e`` electrons
    per gate ``[K, H, W]``) and Gaussian read noise; ``conversion_gain_dn_per_e`` turns
    electrons into DN. The dark current and the photo-response non-uniformity act on the
    expected charge, so they belong to the source (:class:`FlatField`)."""

    conversion_gain_dn_per_e: float
    read_noise_e: float
    full_well_e: float
    dsnu_e: np.ndarray

    def apply(self, taps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        k = np.float32(self.conversion_gain_dn_per_e)
        e = np.asarray(taps, dtype=np.float32) / k
        if e.shape[-2:] != self.dsnu_e.shape[-2:]:
            # the pattern is the sensor's: a cropped frame would need its origin, which a TapNoise is not given
            raise DeviceError(f"frame of {e.shape[-1]}x{e.shape[-2]} pixels", field="roi",
                              expected=f"the full {self.dsnu_e.shape[-1]}x{self.dsnu_e.shape[-2]} sensor "
                                       "for the flat-field emulation")
        e = np.minimum(shot_noise(e, rng), np.float32(self.full_well_e))
        e = read_noise(e + self.dsnu_e[: e.shape[0]].astype(np.float32), np.float32(self.read_noise_e), rng)
        return (e * k).astype(np.float32, copy=False)


class FlatField(ImageSource):
    """A uniform, diffuse, modulated light filling the view (an integrating sphere in front of
    the lens), seen through a sensor with the EMVA 1288 parts of a scene's ``sensor:`` block.

    Per pixel and gate at the reference exposure, in DN: ``c_k = g (A / m + ambient) + g A
    cos(phi - theta_k) + K D T_ref``, with ``A = amplitude_dn``, ``m`` the sensor's modulation
    contrast (so the unmodulated part of the modulated light is ``A / m``), ``g`` the pixel's
    photo-response (``1 + prnu N(0, 1)``: one photodiode feeds all of a pixel's gates), ``D``
    the dark current (e/s) and ``K`` the conversion gain. Everything scales with the exposure
    (:meth:`ImageSource.taps`); shot noise, the full well, the per-gate DSNU and read noise are
    :class:`PixelNoise`. ``amplitude_dn = 0`` and ``ambient_dn = 0`` is a dark capture.
    """

    def __init__(self, sensor: Any, camera: CameraModel | None = None, *, amplitude_dn: float = 100.0,
                 phase_rad: float = 0.0, ambient_dn: float = 0.0) -> None:
        super().__init__()
        self.sensor = sensor
        self.camera = camera or load_camera_preset(TOFCAM635_PRESET)
        self.amplitude_dn = float(amplitude_dn)
        self.phase_rad = float(phase_rad)
        self.ambient_dn = float(ambient_dn)
        fp = sensor.fixed_pattern
        rng = np.random.default_rng(fp.seed)
        shape = self.camera.shape
        self.prnu_gain = 1.0 + fp.prnu * rng.standard_normal(shape)
        self.dsnu_e = fp.dsnu_e * rng.standard_normal((sensor.taps, *shape))
        self.description = f"flat field, amplitude {self.amplitude_dn:g} DN at 125 us"

    def signal(self, freq_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = self.sensor
        g = self.prnu_gain
        a = g * self.amplitude_dn
        dark_dn = s.conversion_gain_dn_per_e * s.dark_current_e_per_s * REFERENCE_INTEGRATION_TIME_S
        contrast = s.modulation_contrast if s.modulation_contrast > 0 else 1.0
        b = g * (self.amplitude_dn / contrast + self.ambient_dn) + dark_dn
        return a, np.full(a.shape, self.phase_rad), b

    def noise_model(self) -> PixelNoise:
        s = self.sensor
        return PixelNoise(conversion_gain_dn_per_e=s.conversion_gain_dn_per_e, read_noise_e=s.read_noise_e,
                          full_well_e=s.full_well_e, dsnu_e=self.dsnu_e)

    def scene_text(self) -> str:
        import yaml

        return yaml.safe_dump({"flat_field": {"amplitude_dn_at_125us": self.amplitude_dn,
                                              "phase_rad": self.phase_rad, "ambient_dn": self.ambient_dn},
                               "sensor": self.sensor.to_dict()}, sort_keys=False)
