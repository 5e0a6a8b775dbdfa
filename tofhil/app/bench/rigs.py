"""Rigs: a device on its bench, for the campaign runner (``tofhil.app.campaign.Rig``).

* :class:`EmulatedTofCamRig` -- the emulated TOFcam635 through its pyusb backend (the device
  path of ``tofhil capture --device emulator``), whose emulator performs the bench changes:
  each change builds the frame source again from the bench's parameters (a flat field's
  light, a scene's parameters and hidden effects) and hands it to the running emulator.
* :class:`EmulatedDepthAIRig` -- the DepthAI host pipeline (``depthai-sim``) sending the
  twin's frames of the bench scene; a change gives the pipeline a new scene (it restarts on
  the next capture, as the driver does for any host-side change).
* :class:`DeviceRig` -- any other device: bench changes are asked of the operator (a
  ``prompt`` callable from the CLI) or made by a stage callable, if one is given.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, Mapping

from tofhil.app.campaign import DeviceCapabilities
from tofhil.errors import TofhilError

#: The TOFcam635's integration time range and modes (the driver's and firmware's limits).
TOFCAM635_CAPS = dict(modes=("dcs", "distance"), integration_time_s=(1e-6, 65535e-6), channels=(0, 15))


def tofcam635_freqs() -> tuple[float, ...]:
    from tofhil.drivers.tofcam635.profile import TOFCAM635

    return tuple(TOFCAM635.mod_freqs_hz)


class _Rig:
    """What every rig does alike: open its driver on first use, give the twin's scene text of the
    bench as it stands (a string, or a callable of the state), close its driver."""

    _driver: Any
    _scene_text: Any
    state: Mapping[str, Any]

    def driver(self) -> Any:
        if not self._driver.is_open:
            self._driver.open()
        return self._driver

    def scene_text(self) -> str:
        """The twin's scene for the bench as it stands (a callable of the state), never the hidden truth."""
        return self._scene_text(self.state) if callable(self._scene_text) else self._scene_text

    def close(self) -> None:
        if self._driver.is_open:
            self._driver.close()


class EmulatedTofCamRig(_Rig):
    """The emulated TOFcam635 (pyusb backend) with a bench its emulator performs.

    ``make_source(params)`` returns the frame source (``tofhil.frame_source.ImageSource``) of
    the bench in the state ``params``; ``defaults`` is the state before any change."""

    def __init__(self, make_source: Callable[[Mapping[str, Any]], Any], defaults: Mapping[str, Any], *,
                 seed: int = 0, scene_text: str | Callable[[Mapping[str, Any]], str] = "",
                 device: str = "emulator") -> None:
        from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator

        self.device = device
        self.make_source = make_source
        self.defaults = dict(defaults)
        self.capabilities = DeviceCapabilities(mod_freqs_hz=tofcam635_freqs(), bench_by=("emulator",),
                                               bench_params=tuple(self.defaults), **TOFCAM635_CAPS)
        self.state = dict(self.defaults)
        #: Seconds the emulator spent rendering its sources (inside the captures' time).
        self.render_s = 0.0
        self.emulator = Epc635Emulator(self._timed(make_source(self.state)), seed=seed)
        self._driver = EmulatedTofCam635(device, emulator=self.emulator)
        self._scene_text = scene_text
        self.renders = 0

    def _timed(self, src: Any) -> Any:
        """``src`` with its render (``signal``, called once per frequency) timed into ``render_s``
        (of a wrapper, the sources it renders through: ``rendered_by``)."""
        import time

        for part in getattr(src, "rendered_by", (src,)):
            signal = part.signal

            def timed(freq_hz: float, signal: Callable[[float], Any] = signal) -> Any:
                t0 = time.monotonic()
                try:
                    return signal(freq_hz)
                finally:
                    self.render_s += time.monotonic() - t0

            part.signal = timed
        return src

    def apply_bench(self, params: Mapping[str, Any], by: str, message: str) -> None:
        self.state = {**self.defaults, **params}
        src = self._timed(self.make_source(self.state))
        self.renders += 1
        with self.emulator._lock:  # the backend may read a frame from another thread
            self.emulator.source = src
            self.emulator.noise = src.noise_model()


class EmulatedDepthAIRig(_Rig):
    """The DepthAI host pipeline sending frames made by ``make_scene(params)`` (a DepthScene)."""

    def __init__(self, make_scene: Callable[[Mapping[str, Any]], Any], defaults: Mapping[str, Any], *,
                 scene_text: str | Callable[[Mapping[str, Any]], str] = "", device: str = "depthai-sim") -> None:
        from tofhil.drivers.depthai.driver import DepthAIToF

        self.device = device
        self.make_scene = make_scene
        self.defaults = dict(defaults)
        self.capabilities = DeviceCapabilities(modes=("distance",), bench_by=("emulator",),
                                               bench_params=tuple(self.defaults))
        self.state = dict(self.defaults)
        self._driver = DepthAIToF("depthai-sim", host_scene=make_scene(self.state))
        self._scene_text = scene_text

    def apply_bench(self, params: Mapping[str, Any], by: str, message: str) -> None:
        self.state = {**self.defaults, **params}
        self._driver.host_scene = self.make_scene(self.state)  # the pipeline restarts on the next configure


class DeviceRig(_Rig):
    """A real device (or a replay): bench changes by the operator or a stage."""

    def __init__(self, device: str, *, prompt: Callable[[str], None] | None = None,
                 stage: Callable[[Mapping[str, Any]], None] | None = None, stage_params: tuple[str, ...] = (),
                 scene_text: str = "") -> None:
        from tofhil.drivers.base import create_driver, parse_spec

        self.device = device
        scheme, _ = parse_spec(device)
        self._driver = create_driver(device)
        by = tuple(b for b, f in (("prompt", prompt), ("stage", stage)) if f is not None)
        if scheme in ("usb", "serial"):
            caps = DeviceCapabilities(mod_freqs_hz=tofcam635_freqs(), bench_by=by, bench_params=stage_params,
                                      **TOFCAM635_CAPS)
        elif scheme.startswith("depthai"):
            caps = DeviceCapabilities(modes=("distance",), bench_by=by, bench_params=stage_params)
        else:  # a replay: what was recorded, nothing settable
            caps = DeviceCapabilities(modes=("dcs", "distance"), bench_by=by, bench_params=stage_params)
        self.capabilities = caps
        self.prompt = prompt
        self.stage = stage
        self._scene_text = scene_text

    def apply_bench(self, params: Mapping[str, Any], by: str, message: str) -> None:
        if by == "stage" and self.stage is not None:
            self.stage(params)
            return
        if self.prompt is None:
            raise TofhilError(f"a bench change ({params}) needs the operator", field="by",
                              expected="an interactive run or a stage")
        text = message or "set the bench: " + ", ".join(f"{k} = {v}" for k, v in params.items())
        self.prompt(text)


# --------------------------------------------------------------------------- emulated benches
def flat_field_bench(path: str | Path | None = None) -> tuple[Any, dict[str, float], str]:
    """The flat-field bench file (default: the bundled TOFcam635 one): its sensor
    (``SensorConfig``), the light's default parameters and the file's text."""
    from tofhil.camera import load_camera_preset
    from tofhil.sim.sensor import SensorConfig
    from tofhil.yamlio import load_yaml_file

    if path is None:
        from tofhil.sim.scene import scenes_dir

        path = scenes_dir().parent / "bench" / "tofcam635_flat_field.yaml"
    data = load_yaml_file(path)
    if not isinstance(data, Mapping) or "sensor" not in data:
        raise TofhilError("no sensor block", file=path, field="sensor", expected="a flat-field bench file with sensor:")
    ff = dict(data.get("flat_field") or {})
    unknown = sorted(set(ff) - {"amplitude_dn", "phase_deg", "ambient_dn"})
    if unknown:
        raise TofhilError("unknown field", file=path, field=f"flat_field.{unknown[0]}",
                          expected="amplitude_dn, phase_deg, ambient_dn")
    sensor = SensorConfig.from_dict(data["sensor"], source=path, camera=load_camera_preset("epc635"))
    light = {"light_amplitude_dn": float(ff.get("amplitude_dn", 100.0)),
             "light_phase_deg": float(ff.get("phase_deg", 0.0)), "ambient_dn": float(ff.get("ambient_dn", 0.0))}
    return sensor, light, Path(path).read_text(encoding="utf-8")


def flat_field_source(sensor: Any, params: Mapping[str, Any]) -> Any:
    from tofhil.sim.sources import FlatField

    return FlatField(sensor, amplitude_dn=float(params["light_amplitude_dn"]),
                     phase_rad=math.radians(float(params.get("light_phase_deg", 0.0))),
                     ambient_dn=float(params.get("ambient_dn", 0.0)))


class ThermalDrift:
    """A frame source whose range drifts with the emulated camera's temperature (a hidden
    truth of the warm-up procedure): every pixel reads ``m_per_c * (T - t_ref_c)`` farther,
    ``T`` the emulator's chip temperature when the frame is taken (its warm-up curve). The
    phase of the rendered signal turns by ``4 pi f dd / c``; amplitude and offset stay."""

    def __init__(self, inner: Any, temperature_c: Callable[[], float], m_per_c: float, t_ref_c: float) -> None:
        self.inner = inner
        self.temperature_c = temperature_c
        self.m_per_c = float(m_per_c)
        self.t_ref_c = float(t_ref_c)
        self.camera = inner.camera
        self.rendered_by = (inner,)
        self.description = f"{inner.description}, range drifting {m_per_c * 1e3:g} mm/degC"

    def taps(self, freq_hz: float, integration_time_s: float, theta_rad: Any) -> Any:
        import numpy as np

        from tofhil import C_M_PER_S
        from tofhil.demod import offset, phasor

        c = self.inner.taps(freq_hz, integration_time_s, theta_rad)
        dd = self.m_per_c * (self.temperature_c() - self.t_ref_c)
        s = phasor(c.astype(np.float64), theta_rad) * np.exp(1j * 4 * np.pi * freq_hz * dd / C_M_PER_S)
        th = np.asarray(theta_rad, dtype=np.float64)[:, None, None]
        out = offset(c.astype(np.float64))[None] + np.real(s[None] * np.exp(-1j * th))
        return out.astype(np.float32)

    def signal(self, freq_hz: float) -> Any:
        return self.inner.signal(freq_hz)

    def noise_model(self) -> Any:
        return self.inner.noise_model()

    def scene_text(self) -> str:
        return self.inner.scene_text()


class FrequencyError:
    """A frame source whose modulation frequency is ``1 + k`` times the one the device demodulates
    with (a hidden truth: a crystal off by ``k``): the light's phase is that of ``f (1 + k)``, so
    each path reads ``1 + k`` times its length, every pixel and bounce alike -- a range scale over
    the whole volume, about the camera centre (a sphere at ``c`` is read at ``c (1 + k)``, radius
    ``r (1 + k)``). Amplitude and offset stay (the render's do not depend on the frequency)."""

    def __init__(self, inner: Any, k: float) -> None:
        self.inner = inner
        self.k = float(k)
        self.camera = inner.camera
        self.scene = getattr(inner, "scene", None)
        self.rendered_by = getattr(inner, "rendered_by", (inner,))
        self.description = f"{inner.description}, modulation frequency x {1 + self.k:g}"
        self._cache: dict[float, Any] = {}

    def taps(self, freq_hz: float, integration_time_s: float, theta_rad: Any) -> Any:
        import numpy as np

        from tofhil.demod import taps_from_signal
        from tofhil.frame_source import REFERENCE_INTEGRATION_TIME_S

        ref = self._cache.get(float(freq_hz))
        if ref is None:
            a, phi, b = self.signal(freq_hz)
            ref = self._cache[float(freq_hz)] = taps_from_signal(a, phi, b, theta_rad).astype(np.float32)
        return ref * np.float32(integration_time_s / REFERENCE_INTEGRATION_TIME_S)

    def signal(self, freq_hz: float) -> Any:
        return self.inner.signal(float(freq_hz) * (1.0 + self.k))

    def noise_model(self) -> Any:
        return self.inner.noise_model()

    def scene_text(self) -> str:
        return self.inner.scene_text()
