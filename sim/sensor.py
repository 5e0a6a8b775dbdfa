"""Sensor model: optical phasors on the pixels -> correlation taps in DN, as a device reports them.

Chain (per pixel, per modulation frequency f, per tap phase theta_k), all in electrons until
the ADC:

1. Optical power (W) -> photo-electrons in one tap's integration:
   ``e_per_W = QE * T_int * lambda / (h_planck * c)``.
2. Expected tap charge, for waveform correlation harmonics ``h`` with amplitude ``a_h`` and
   phase ``psi_h`` (the emitter's waveform correlated with the pixel's demodulation gate)::

       mu_k = g_pix * tap_fraction * e_per_W * [ (P_dc + P_ambient)
              + contrast * sum_h a_h Re(S_h exp(-i h theta_k) exp(i psi_h)) ]
              + dark_current * T_int

   ``S_h`` is the renderer's phasor ``sum w exp(+i 2 pi h f L / c)`` (watts), ``P_dc`` the
   emitter power on the pixel (the h = 0 term), ``tap_fraction`` the share of the pixel's
   photo-electrons one tap collects (0.5 for an A/B two-gate pixel), ``contrast`` the
   modulation x demodulation contrast, ``g_pix`` the per-pixel photo-response gain (PRNU).
   With ``a_1 = 1, psi_1 = 0`` and no other harmonics this is ``B + A cos(phi - theta_k)``.
3. Photon shot noise: exact Poisson for small means, normal with variance = mean above
   ``POISSON_EXACT_BELOW`` electrons; charge clipped at the full well (saturation).
4. Readout: + per-pixel, per-tap dark offset (DSNU) + Gaussian read noise (electrons),
   x conversion gain (DN/e) + black level, rounded and clipped to ``adc_bits``.

The noise-free mode skips shot noise, read noise and ADC rounding, so the taps are the exact
expectation (still clipped at the full well and the ADC range). Random numbers come from a
generator seeded with ``(seed, frame_index)``: the same seed gives identical frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil import C_M_PER_S
from tofhil.binning import bin_mean
from tofhil.camera import CameraModel
from tofhil.frames import RawFrame

#: Planck constant, J s (exact, SI definition).
H_PLANCK = 6.626_070_15e-34
#: Below this mean (electrons) shot noise is drawn exactly from a Poisson distribution.
POISSON_EXACT_BELOW = 1000.0


# ---------------------------------------------------------------------------------------------
# Configuration: the scene file's `sensor:` block
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FixedPatternConfig:
    """Per-pixel, per-tap fixed-pattern noise of the readout (seeded, identical every frame)."""

    #: Dark-signal non-uniformity: standard deviation of a per-pixel, per-tap offset (electrons).
    dsnu_e: float = 0.0
    #: Photo-response non-uniformity: standard deviation of a per-pixel, per-tap relative gain.
    prnu: float = 0.0
    #: Seed of the pattern (independent of the per-frame noise seed).
    seed: int = 0
    #: ``(b, height, width)``: the camera's pixels are ``b x b`` bins of a sensor of that size,
    #: whose pattern (drawn from the seed) each bin averages. None: the camera's own pixels.
    binned: tuple[int, int, int] | None = None


@dataclass(frozen=True)
class SensorConfig:
    """The interpreted `sensor:` block of a scene file (see docs/effects.md for the schema)."""

    freq_hz: tuple[float, ...]
    theta_rad: tuple[float, ...]
    integration_time_s: float = 1.0e-3
    frame_period_s: float = 1.0 / 30.0
    wavelength_m: float = 850.0e-9
    quantum_efficiency: float = 0.35
    modulation_contrast: float = 0.8
    tap_fraction: float = 0.5
    conversion_gain_dn_per_e: float = 0.2
    full_well_e: float = 20_000.0
    read_noise_e: float = 5.0
    dark_current_e_per_s: float = 100.0
    adc_bits: int = 12
    black_level_dn: float = 0.0
    temperature_c: float = math.nan
    fixed_pattern: FixedPatternConfig = field(default_factory=FixedPatternConfig)

    @property
    def taps(self) -> int:
        return len(self.theta_rad)

    @property
    def adc_max_dn(self) -> float:
        return float(2 ** self.adc_bits - 1)

    @property
    def electrons_per_joule(self) -> float:
        """Photo-electrons generated per joule of light at the sensor's wavelength."""
        return self.quantum_efficiency * self.wavelength_m / (H_PLANCK * C_M_PER_S)

    @property
    def electrons_per_watt(self) -> float:
        """Photo-electrons generated in one tap's integration per watt on the pixel."""
        return self.electrons_per_joule * self.integration_time_s

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, *, source: str | Path = "<scene>",
                  camera: CameraModel | None = None) -> "SensorConfig":
        """Validate a `sensor:` mapping; defaults for the frequencies, taps and wavelength come
        from the camera preset's extra facts. Errors name the file, ``sensor.<field>`` and what
        was expected."""
        return _parse_sensor(d, source=source, camera=camera)

    def to_dict(self) -> dict[str, Any]:
        """The mapping that :meth:`from_dict` reads back to an equal config."""
        return {
            "taps": self.taps, "theta_deg": [math.degrees(t) for t in self.theta_rad],
            "freq_hz": list(self.freq_hz), "integration_time_s": self.integration_time_s,
            "frame_period_s": self.frame_period_s, "wavelength_m": self.wavelength_m,
            "quantum_efficiency": self.quantum_efficiency,
            "modulation_contrast": self.modulation_contrast, "tap_fraction": self.tap_fraction,
            "conversion_gain_dn_per_e": self.conversion_gain_dn_per_e,
            "full_well_e": self.full_well_e, "read_noise_e": self.read_noise_e,
            "dark_current_e_per_s": self.dark_current_e_per_s, "adc_bits": self.adc_bits,
            "black_level_dn": self.black_level_dn,
            "temperature_c": None if math.isnan(self.temperature_c) else self.temperature_c,
            "fixed_pattern": {"dsnu_e": self.fixed_pattern.dsnu_e, "prnu": self.fixed_pattern.prnu,
                              "seed": self.fixed_pattern.seed}
            | ({"binned": list(self.fixed_pattern.binned)} if self.fixed_pattern.binned else {}),
        }


# name -> range of the number (schema keywords); every other key is handled below.
_NUMBERS: dict[str, dict[str, Any]] = {
    "integration_time_s": {"lo": 0.0, "lo_open": True, "expected": "a positive number of seconds"},
    "frame_period_s": {"lo": 0.0, "lo_open": True, "expected": "a positive number of seconds"},
    "wavelength_m": {"lo": 1e-7, "hi": 1e-5, "expected": "a wavelength in metres between 1e-7 and 1e-5"},
    "quantum_efficiency": {"lo": 0.0, "hi": 1.0, "lo_open": True},
    "modulation_contrast": {"lo": 0.0, "hi": 1.0},
    "tap_fraction": {"lo": 0.0, "hi": 1.0, "lo_open": True},
    "conversion_gain_dn_per_e": {"lo": 0.0, "lo_open": True, "expected": "a positive number (DN per electron)"},
    "full_well_e": {"lo": 0.0, "lo_open": True, "expected": "a positive number of electrons"},
    "read_noise_e": {"lo": 0.0, "expected": "a number of electrons >= 0"},
    "dark_current_e_per_s": {"lo": 0.0, "expected": "a number of electrons per second >= 0"},
    "black_level_dn": {"lo": 0.0, "expected": "a number of DN >= 0"},
    "temperature_c": {"lo": -273.15, "expected": "a temperature in degrees Celsius"},
}
SENSOR_KEYS = frozenset(_NUMBERS) | {"taps", "theta_deg", "freq_hz", "adc_bits", "fixed_pattern"}
_FP_KNOWN = ("dsnu_e", "prnu", "seed", "binned")


def _with_preset_defaults(d: Mapping[str, Any], camera: CameraModel | None) -> dict[str, Any]:
    """The block over the camera preset's sensor facts (``freq_hz``, ``wavelength_m``, ``taps``
    or any other sensor key a preset states): the block wins key by key; tap phases are taken
    from the preset only when the block gives neither ``taps`` nor ``theta_deg``."""
    extra = dict(camera.extra) if camera is not None else {}
    merged = {k: v for k, v in extra.items() if k in SENSOR_KEYS}
    if "taps" in d or "theta_deg" in d:
        merged.pop("taps", None)
        merged.pop("theta_deg", None)
    merged.update(d)
    return merged


def _parse_sensor(d: Mapping[str, Any] | None, *, source: str | Path,
                  camera: CameraModel | None) -> SensorConfig:
    from tofhil.schema import Schema

    v = Schema(source)
    d = v.mapping(d, "sensor", allowed=SENSOR_KEYS, expected="a mapping (see docs/scene-format.md)")
    d = _with_preset_defaults(d, camera)
    kw: dict[str, Any] = {}

    # Modulation frequencies: the block, else the camera preset's.
    if d.get("freq_hz") is None:
        raise v.error("missing (and the camera preset names none)", "sensor.freq_hz",
                      "a list of modulation frequencies in Hz")
    kw["freq_hz"] = tuple(v.numbers(d["freq_hz"], "sensor.freq_hz", scalar_ok=True, max_len=16, lo=0.0,
                                    lo_open=True, hi=1e12,
                                    expected="a list of 1 to 16 positive modulation frequencies in Hz"))

    # Tap phases: explicit, else K equally spaced from 0.
    k: int | None = None
    if d.get("taps") is not None:
        k = v.integer(d["taps"], "sensor.taps", lo=3, hi=64,
                      expected="an integer from 3 to 64 (2-tap A/B pixels: give their 2M phases)")
    if d.get("theta_deg") is not None:
        theta_deg = v.numbers(d["theta_deg"], "sensor.theta_deg", min_len=3, max_len=64,
                              expected="a list of tap phases in degrees")
        if k is not None and len(theta_deg) != k:
            raise v.error(f"has {len(theta_deg)} phases but taps is {k}", "sensor.theta_deg", f"{k} phases")
        theta = np.radians(theta_deg)
        from tofhil.demod import estimator_weights

        try:
            estimator_weights(theta)
        except ValueError as exc:
            raise v.error(str(exc), "sensor.theta_deg", ">= 3 phases equally spaced over 360 deg") from None
    else:
        theta = 2.0 * np.pi * np.arange(4 if k is None else k) / (4 if k is None else k)
    kw["theta_rad"] = tuple(float(t) for t in theta)

    for name, rng in _NUMBERS.items():
        if d.get(name) is not None:
            kw[name] = v.number(d[name], f"sensor.{name}", **rng)
    if "adc_bits" in d:
        kw["adc_bits"] = v.integer(d["adc_bits"], "sensor.adc_bits", lo=1, hi=32)
    if "conversion_gain_dn_per_e" not in kw:
        # Default: the full well maps onto the ADC's full scale.
        bits = kw.get("adc_bits", SensorConfig.adc_bits)
        fw = kw.get("full_well_e", SensorConfig.full_well_e)
        gain = (2 ** bits - 1 - kw.get("black_level_dn", 0.0)) / fw
        if not gain > 0:
            raise v.error(f"black_level_dn {kw.get('black_level_dn')} leaves no ADC range", "sensor.black_level_dn",
                          f"a black level below the ADC's full scale {2 ** bits - 1} DN")
        kw["conversion_gain_dn_per_e"] = gain

    fp = d.get("fixed_pattern")
    if fp is not None:
        fp = v.mapping(fp, "sensor.fixed_pattern", allowed=_FP_KNOWN, expected="a mapping with dsnu_e, prnu, seed")
        kw["fixed_pattern"] = FixedPatternConfig(
            dsnu_e=v.number(fp.get("dsnu_e", 0.0), "sensor.fixed_pattern.dsnu_e", lo=0.0,
                            expected="a number of electrons >= 0"),
            prnu=v.number(fp.get("prnu", 0.0), "sensor.fixed_pattern.prnu", lo=0.0, hi=0.5,
                          expected="a relative gain spread in [0, 0.5]"),
            seed=v.integer(fp.get("seed", 0), "sensor.fixed_pattern.seed", lo=0, hi=2 ** 63 - 1),
            binned=_binned_from(fp.get("binned"), v))
    return SensorConfig(**kw)


def _binned_from(value: Any, v: Any) -> tuple[int, int, int] | None:
    """``sensor.fixed_pattern.binned``: ``[b, height, width]`` of the sensor the pattern is drawn on."""
    if value is None:
        return None
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise v.error(f"is {value!r}", "sensor.fixed_pattern.binned",
                      "[bin, sensor height, sensor width]: three integers")
    b, h, w = (v.integer(x, f"sensor.fixed_pattern.binned[{i}]", lo=1, hi=1 << 16) for i, x in enumerate(value))
    return (b, h, w)


def take_pixels(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """A per-pixel array ``[..., H, W]`` at the flat pixel indices ``index``, as one row
    ``[..., 1, N]`` (the layout of a signal, taps or field of some pixels only)."""
    a = np.asarray(a)
    lead = a.shape[:-2]
    # (np.take: 2-4x faster than the same fancy index along the last axis)
    return np.take(a.reshape(lead + (-1,)), index, axis=-1).reshape(lead + (1, index.size))


# ---------------------------------------------------------------------------------------------
# The optical signal handed from the renderer (through the effects) to the sensor
# ---------------------------------------------------------------------------------------------
@dataclass
class OpticalSignal:
    """Light on the sensor, per pixel: what the sensor model turns into taps.

    ``phasor_w[F, NH, H, W]`` holds ``sum_paths w exp(+i 2 pi h f L / c)`` for each frequency
    and each harmonic order in ``harmonics`` (watts). ``dc_w`` is the emitter's power on the
    pixel, ``ambient_w`` the unmodulated ambient light's. ``waveform`` maps harmonic order h to
    the complex correlation coefficient ``a_h exp(i psi_h)``.
    """

    freq_hz: np.ndarray
    harmonics: tuple[int, ...]
    phasor_w: np.ndarray
    dc_w: np.ndarray
    ambient_w: np.ndarray
    waveform: dict[int, complex] = field(default_factory=lambda: {1: 1.0 + 0.0j})

    def __post_init__(self) -> None:
        self.freq_hz = np.atleast_1d(np.asarray(self.freq_hz, dtype=np.float64))
        self.harmonics = tuple(int(h) for h in self.harmonics)
        self.phasor_w = np.asarray(self.phasor_w, dtype=np.complex128)
        if self.phasor_w.ndim != 4 or self.phasor_w.shape[:2] != (self.freq_hz.size, len(self.harmonics)):
            raise ValueError(f"phasor_w must be [F={self.freq_hz.size}, NH={len(self.harmonics)}, H, W], "
                             f"got {self.phasor_w.shape}")
        if 1 not in self.harmonics:
            raise ValueError("the signal must carry the fundamental (harmonic 1)")
        hw = self.phasor_w.shape[-2:]
        self.dc_w = np.broadcast_to(np.asarray(self.dc_w, dtype=np.float64), hw)
        self.ambient_w = np.broadcast_to(np.asarray(self.ambient_w, dtype=np.float64), hw)

    @property
    def shape(self) -> tuple[int, int]:
        return self.phasor_w.shape[-2:]  # type: ignore[return-value]

    def copy(self) -> "OpticalSignal":
        return replace(self, phasor_w=self.phasor_w.copy(), dc_w=np.array(self.dc_w),
                       ambient_w=np.array(self.ambient_w), waveform=dict(self.waveform))

    def at(self, index: np.ndarray) -> "OpticalSignal":
        """The light of the pixels at flat indices ``index`` only, as one row ``[..., 1, N]``."""
        return replace(self, phasor_w=take_pixels(self.phasor_w, index),
                       dc_w=take_pixels(np.broadcast_to(self.dc_w, self.shape), index),
                       ambient_w=take_pixels(np.broadcast_to(self.ambient_w, self.shape), index),
                       waveform=dict(self.waveform))

    def harmonic(self, h: int) -> np.ndarray:
        """``S_h [F, H, W]``; an order the renderer did not compute is synthesised from the
        fundamental as ``|S_1| exp(i h arg S_1)``, exact for pixels seeing a single path."""
        return self.harmonic_terms({h: 1.0})[0][1]

    def harmonic_terms(self, coefficients: Mapping[int, complex]) -> list[tuple[int, np.ndarray]]:
        """``[(h, c_h S_h)]`` for every nonzero coefficient (:meth:`harmonic`); the fundamental's
        magnitude and phase are taken once for all the orders synthesised."""
        polar: tuple[np.ndarray, np.ndarray] | None = None
        out = []
        for h, coef in coefficients.items():
            if coef == 0:
                continue
            rendered = h in self.harmonics
            if rendered:
                s_h = self.phasor_w[:, self.harmonics.index(h)]
            else:
                if polar is None:
                    s1 = self.phasor_w[:, self.harmonics.index(1)]
                    polar = np.abs(s1), np.angle(s1)
                s_h = polar[0] * np.exp(1j * h * polar[1])
            # (a rendered order at coefficient 1 is the render's own array, not a copy)
            out.append((h, s_h if coef == 1.0 and rendered else coef * s_h))
        return out

    @classmethod
    def from_render(cls, result: Any, waveform: Mapping[int, complex] | None = None,
                    *, multipath_scale: float | None = None, index: np.ndarray | None = None) -> "OpticalSignal":
        """From a renderer ``RenderResult``. With ``multipath_scale`` the phasor is rebuilt as
        ``direct + scale * indirect`` (needs the render's separate direct/indirect phasors).

        A rendered modulation frequency of 0 Hz is not a sensor frequency: its phasor is the
        plain power ``sum w``, which gives the direct/indirect split of the unmodulated part.
        """
        freq = np.atleast_1d(np.asarray(result.freq_hz, dtype=np.float64))
        keep = np.flatnonzero(freq != 0.0)
        zero = np.flatnonzero(freq == 0.0)
        h1 = tuple(result.harmonics).index(1)
        # (some pixels: gathered before the frequencies are picked, which copies)
        phasor = result.phasor[keep] if index is None else take_pixels(result.phasor, index)[keep]
        dc = result.power_w
        if multipath_scale is not None:
            if getattr(result, "phasor_direct", None) is None or getattr(result, "phasor_indirect", None) is None:
                raise ValueError("the multipath effect needs a render with separate_direct=True")
            if index is not None:
                raise ValueError("the multipath effect rebuilds the whole frame's light: no pixel index")
            phasor = result.phasor_direct[keep] + multipath_scale * result.phasor_indirect[keep]
            if zero.size:
                dc_direct = result.phasor_direct[zero[0], h1].real
            else:
                # Fallback: |S_direct| at the fundamental equals the direct power for pixels that
                # see one direct path (all but mixed pixels at depth edges).
                dc_direct = np.minimum(np.abs(result.phasor_direct[keep[0], h1]), result.power_w)
            dc = dc_direct + multipath_scale * np.clip(result.power_w - dc_direct, 0.0, None)
        ambient = getattr(result, "ambient_power_w", None)
        ambient = np.zeros_like(result.power_w) if ambient is None else ambient
        if index is not None:  # the pixels at flat indices ``index`` only, as one row (:meth:`at`)
            dc, ambient = take_pixels(dc, index), take_pixels(ambient, index)
        return cls(freq_hz=freq[keep], harmonics=tuple(result.harmonics), phasor_w=phasor, dc_w=dc, ambient_w=ambient,
                   waveform=dict(waveform) if waveform else {1: 1.0 + 0.0j})


def waveform_from_scene(scene: Any) -> dict[int, complex]:
    """The emitter's correlation waveform ``{h: a_h exp(i psi_h)}`` from a Scene.

    Accepts ``scene.emitter.waveform`` as a list of ``(h, amplitude, phase_rad)`` or of
    mappings with those keys, or an object with ``.harmonics``; default: a pure sinusoid."""
    emitter = getattr(scene, "emitter", None)
    wf = getattr(emitter, "waveform", None) if emitter is not None else None
    if wf is None:
        return {1: 1.0 + 0.0j}
    items = getattr(wf, "harmonics", wf)
    out: dict[int, complex] = {}
    for item in items:
        if isinstance(item, Mapping):
            h, a, p = item.get("h", item.get("order")), item.get("amplitude", 1.0), item.get("phase_rad", 0.0)
        elif hasattr(item, "order"):
            h, a, p = item.order, item.amplitude, getattr(item, "phase_rad", 0.0)
        else:
            h, a, p = item
        out[int(h)] = complex(float(a) * np.exp(1j * float(p)))
    if 1 not in out:
        out[1] = 1.0 + 0.0j
    return out


# ---------------------------------------------------------------------------------------------
# The sensor
# ---------------------------------------------------------------------------------------------
def frame_rng(seed: int, frame_index: int, stream: int = 0) -> np.random.Generator:
    """Independent, reproducible generator for one frame (and one use within it)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), int(frame_index), stream])))


@dataclass
class SensorModel:
    """A configured sensor for one camera: signal -> expected electrons -> noisy DN taps."""

    config: SensorConfig
    camera: CameraModel
    _pattern: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False)
    # (the pattern at the last pixel index asked for: a fit asks for the same pixels at every
    # evaluation, and gathering them from the whole-frame pattern was ~3 % of a diagnosis)
    _pattern_at: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False)

    @property
    def theta_rad(self) -> np.ndarray:
        return np.asarray(self.config.theta_rad)

    @property
    def freq_hz(self) -> np.ndarray:
        return np.asarray(self.config.freq_hz)

    def fixed_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel, per-tap ``(gain [K,H,W], offset_e [K,H,W])`` from the fixed-pattern seed."""
        if self._pattern is None:
            fp = self.config.fixed_pattern
            b, *sensor = fp.binned or (1, *self.camera.shape)
            shape = (self.config.taps, *sensor)
            rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(fp.seed), 0x5eed])))
            gain = 1.0 + fp.prnu * rng.standard_normal(shape) if fp.prnu > 0 else np.ones(shape)
            off = fp.dsnu_e * rng.standard_normal(shape) if fp.dsnu_e > 0 else np.zeros(shape)
            gain = np.clip(gain, 0.0, None)
            if b > 1:
                gain, off = bin_mean(gain, b), bin_mean(off, b)
            h, w = self.camera.shape
            if gain.shape[-2:] != (h, w):
                from tofhil.errors import TofhilError

                raise TofhilError(f"is {[b, *sensor]}: binned, {gain.shape[-2]} x {gain.shape[-1]} pixels (height x "
                                  f"width)", field="sensor.fixed_pattern.binned",
                                  expected=f"a sensor that binned {b} x {b} gives the camera's {h} x {w} pixels")
            self._pattern = (gain, off)
        return self._pattern

    def _fixed_pattern_at(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`fixed_pattern` at the flat pixel indices ``index``, as one row."""
        last = self._pattern_at
        if last is not None and (last[0] is index or np.array_equal(last[0], index)):
            return last[1], last[2]
        gain, offset = self.fixed_pattern()
        at = (np.array(index), take_pixels(gain, index), take_pixels(offset, index))
        self._pattern_at = at
        return at[1], at[2]

    def _check_signal(self, signal: OpticalSignal) -> None:
        """The light is on this sensor's pixels at its frequencies."""
        if signal.shape != self.camera.shape:
            raise ValueError(f"signal is {signal.shape}, camera is {self.camera.shape}")
        self._check_frequencies(signal)

    def _check_frequencies(self, signal: OpticalSignal) -> None:
        freq = self.config.freq_hz
        # (np.allclose's test, |a - b| <= 1e-8 + 1e-9 |b|, on the few frequencies as floats:
        # numpy's overhead was a percent of a fit)
        if signal.freq_hz.size != len(freq) or not all(abs(float(a) - float(b)) <= 1e-8 + 1e-9 * abs(float(b))
                                                       for a, b in zip(signal.freq_hz, freq)):
            raise ValueError(f"signal frequencies {signal.freq_hz.tolist()} differ from the sensor's {list(freq)}")

    def expected_electrons(self, signal: OpticalSignal) -> np.ndarray:
        """Mean collected charge per tap, ``[F, K, H, W]`` electrons (before saturation)."""
        cfg = self.config
        self._check_signal(signal)
        e_w = cfg.tap_fraction * cfg.electrons_per_watt
        theta = self.theta_rad
        dc = (signal.dc_w + signal.ambient_w)[None, None]  # [1, 1, H, W]
        mod = np.zeros((signal.freq_hz.size, theta.size) + signal.shape)
        for h, coef in signal.waveform.items():
            if coef == 0:
                continue
            s = coef * signal.harmonic(h)  # [F, H, W]
            # Re(s exp(-i h theta_k)) = Re(s) cos(h theta_k) + Im(s) sin(h theta_k)
            c, sn = np.cos(h * theta)[None, :, None, None], np.sin(h * theta)[None, :, None, None]
            mod += s.real[:, None] * c + s.imag[:, None] * sn
        gain, _ = self.fixed_pattern()
        photo = e_w * (dc + cfg.modulation_contrast * mod)
        return gain[None] * np.clip(photo, 0.0, None) + cfg.dark_current_e_per_s * cfg.integration_time_s

    def taps_dn(self, signal: OpticalSignal, *, rng: np.random.Generator | None = None,
                noise: bool = True) -> np.ndarray:
        """Taps in DN, float32 ``[F, K, H, W]``: shot noise, full well, offsets, read noise, ADC."""
        cfg = self.config
        if not noise:
            return self._noise_free_taps(signal)
        mu = self.expected_electrons(signal)
        if rng is None:
            raise ValueError("noise=True needs a random generator")
        q = shot_noise(mu, rng)
        q = np.minimum(q, cfg.full_well_e)  # saturation: the well holds no more charge
        _, offset = self.fixed_pattern()
        v = read_noise(q + offset[None], cfg.read_noise_e, rng)
        dn = np.rint(v * cfg.conversion_gain_dn_per_e + cfg.black_level_dn)
        return np.clip(dn, 0.0, cfg.adc_max_dn).astype(np.float32)

    def _noise_free_taps(self, signal: OpticalSignal, index: np.ndarray | None = None, *,
                         signal_at_index: bool = False) -> np.ndarray:
        """``taps_dn(signal, noise=False)`` in one compiled pass over the pixels
        (:mod:`tofhil.sim.sensor_kernels`, bit-identical to the numpy expressions); with
        ``index`` (flat pixel indices) only those pixels, as ``[F, K, 1, N]``;
        ``signal_at_index``: the signal holds those pixels only (:meth:`OpticalSignal.at`)."""
        from tofhil.sim.sensor_kernels import noise_free_taps

        cfg = self.config
        if signal_at_index:
            if index is None or signal.shape != (1, index.size):
                raise ValueError(f"signal is {signal.shape}, not the {0 if index is None else index.size} pixels asked for")
            self._check_frequencies(signal)
        else:
            self._check_signal(signal)
        theta = self.theta_rad
        terms = signal.harmonic_terms(signal.waveform)
        shape = (signal.freq_hz.size,) + signal.shape
        s = np.stack([t for _, t in terms]) if terms else np.zeros((0,) + shape, dtype=np.complex128)
        hs = np.array([h for h, _ in terms], dtype=np.float64)
        cos_h = np.cos(hs[:, None] * theta[None, :]) if terms else np.zeros((0, theta.size))
        sin_h = np.sin(hs[:, None] * theta[None, :]) if terms else np.zeros((0, theta.size))
        dc = np.ascontiguousarray(np.broadcast_to(signal.dc_w + signal.ambient_w, signal.shape), dtype=np.float64)
        if index is not None:  # the pixels asked for, as one row
            if not signal_at_index:
                s, dc = take_pixels(s, index), take_pixels(dc, index)
            gain, offset = self._fixed_pattern_at(index)
        else:
            gain, offset = self.fixed_pattern()
        out = np.empty((signal.freq_hz.size, theta.size) + s.shape[-2:], dtype=np.float32)
        noise_free_taps(np.ascontiguousarray(s.real), np.ascontiguousarray(s.imag), cos_h, sin_h, dc,
                        np.ascontiguousarray(gain, dtype=np.float64), np.ascontiguousarray(offset, dtype=np.float64),
                        float(cfg.tap_fraction * cfg.electrons_per_watt), float(cfg.modulation_contrast),
                        float(cfg.dark_current_e_per_s * cfg.integration_time_s), float(cfg.full_well_e),
                        float(cfg.conversion_gain_dn_per_e), float(cfg.black_level_dn), float(cfg.adc_max_dn), out)
        return out

    def expose(self, signal: OpticalSignal, *, seed: int = 0, frame_index: int = 0, noise: bool = True,
               meta: dict[str, Any] | None = None) -> RawFrame:
        """One raw frame: taps in DN with sequence number and timestamp from the frame period."""
        cfg = self.config
        taps = self.taps_dn(signal, rng=frame_rng(seed, frame_index) if noise else None, noise=noise)
        m = {"units": "DN", "source": "tofhil-sim", "noise": noise, "seed": int(seed),
             "conversion_gain_dn_per_e": cfg.conversion_gain_dn_per_e, "black_level_dn": cfg.black_level_dn,
             "saturation_dn": min(cfg.adc_max_dn, cfg.full_well_e * cfg.conversion_gain_dn_per_e
                                  + cfg.black_level_dn)}
        m.update(meta or {})
        return RawFrame(taps=taps, freq_hz=self.freq_hz, theta_rad=self.theta_rad,
                        integration_time_s=cfg.integration_time_s, camera=self.camera,
                        timestamp_s=frame_index * cfg.frame_period_s, sequence=int(frame_index),
                        temperature_c=cfg.temperature_c, meta=m)


def read_noise(v_e: np.ndarray, read_noise_e: float, rng: np.random.Generator) -> np.ndarray:
    """``v_e`` plus Gaussian read noise of ``read_noise_e`` electrons rms."""
    return v_e + read_noise_e * rng.standard_normal(v_e.shape, dtype=_draw_dtype(v_e)) if read_noise_e > 0 else v_e


def _draw_dtype(a: np.ndarray) -> type:
    """float32 draws for float32 data (the emulator's frames), float64 otherwise (the sim's)."""
    return np.float32 if a.dtype == np.float32 else np.float64


def shot_noise(mu: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poisson draws with mean ``mu``: exact for small means, normal (var = mean) for large."""
    mu = np.clip(mu, 0.0, None)
    small = mu < POISSON_EXACT_BELOW
    if not small.any():  # bright frames: no masked copies (same draws as below)
        return mu + np.sqrt(mu) * rng.standard_normal(mu.shape, dtype=_draw_dtype(mu))
    out = np.empty_like(mu)
    out[small] = rng.poisson(mu[small])
    big = ~small
    if big.any():
        m = mu[big]
        out[big] = m + np.sqrt(m) * rng.standard_normal(m.shape)
    return out
