"""Random disturbances of a simulated session, per channel and field shape: a development
instrument for diagnosis (issue 32), written without the effect library's code.

Each draw hides one or two distortions in a session of a bundled scene: a channel (the signal's
gain, its range, an unmodulated offset, one frequency's gain or phase, one tap's gain or offset,
a gain or a range that drifts over the frames) times a shape over the field (uniform, smooth,
radial, linear, rows, columns, local) and a strength. The strength is a z-score: the
distortion's whitened size summed over the pixels, ``sqrt(sum (delta / sigma)^2)``, with
``sigma`` the noise of one frame's signal measured on two noisy frames of the same light (so
z 10 is at the edge of what a 4-frame session shows and z 1000 far above it). The distortions
act on the light on the sensor or on the recorded taps with the sensor's own noise and ADC
after them, as a camera would; the judge of a diagnosis (:func:`judge`) knows which family of
effects or which channel and shape is the right answer.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tofhil import C_M_PER_S

CHANNELS = ("gain", "range", "offset", "freq_gain", "freq_phase", "tap_gain", "tap_offset", "frame_gain",
            "frame_range")
#: Channels whose distortion is one number (a calibration constant or a drift), not a field.
UNIFORM_ONLY = {"freq_gain", "freq_phase", "tap_gain", "tap_offset", "frame_gain", "frame_range"}
SHAPES = ("uniform", "smooth", "radial", "linear", "rows", "columns", "local")

#: The families of effects that name a channel's distortion (the judge's right answers).
FAMILIES: dict[tuple[str, str], set[str]] = {}
for _s in SHAPES:
    FAMILIES[("gain", _s)] = {"reflectance", "illumination", "gain_field"}
    FAMILIES[("offset", _s)] = {"offset", "ambient", "offset_field"}
    FAMILIES[("range", _s)] = {"range_offset_map"}
FAMILIES[("range", "uniform")] |= {"range_offset"}
FAMILIES[("range", "radial")] |= {"field_angle"}
FAMILIES[("range", "smooth")] |= {"field_angle"}
FAMILIES[("range", "linear")] |= {"fixed_pattern", "pose"}
FAMILIES[("freq_gain", "uniform")] = {"frequency_calibration"}
FAMILIES[("freq_phase", "uniform")] = {"frequency_calibration"}
FAMILIES[("tap_gain", "uniform")] = {"tap_calibration"}
FAMILIES[("tap_offset", "uniform")] = {"tap_calibration"}
FAMILIES[("frame_gain", "uniform")] = {"drift"}
FAMILIES[("frame_range", "uniform")] = {"drift"}

#: The residual channel (``residual_by_channel``) or field map (``structure``) each channel shows in.
SAID_IN = {"gain": "amplitude", "range": "depth", "offset": "offset", "freq_gain": "frequency",
           "freq_phase": "frequency", "tap_gain": "tap", "tap_offset": "tap", "frame_gain": "frame",
           "frame_range": "frame"}
#: The structure kinds (``eval/diagnose/structure.py``) a field shape reads as.
SHAPE_WORDS = {"uniform": {"smooth"}, "smooth": {"smooth"}, "radial": {"smooth"}, "linear": {"smooth"},
               "rows": {"row pattern", "smooth"}, "columns": {"column pattern", "smooth"}, "local": {"spot", "smooth"}}


@dataclass
class Disturbance:
    channel: str
    shape: str
    z: float
    #: the relative or absolute size the z-score gave (per channel's unit), for the table
    size: float = 0.0
    index: int = 0  # the frequency or tap it acts on
    params: dict[str, Any] = field(default_factory=dict)

    def label(self) -> str:
        return f"{self.channel}/{self.shape}"


def field_shape(shape: str, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A field of unit rms over the image with the named shape (random within it)."""
    v, u = np.mgrid[0:h, 0:w].astype(float)
    x, y = 2 * u / (w - 1) - 1, 2 * v / (h - 1) - 1
    if shape == "uniform":
        f = np.ones((h, w))
    elif shape == "smooth":
        c = rng.normal(size=6)
        f = c[0] * x + c[1] * y + c[2] * x * x + c[3] * x * y + c[4] * y * y + 0.3 * c[5] * x * y * (x + y)
    elif shape == "radial":
        cx, cy = rng.uniform(-0.15, 0.15, 2)
        r2 = (x - cx) ** 2 + (y - cy) ** 2
        f = r2 if rng.random() < 0.5 else r2 ** 2
    elif shape == "linear":
        a = rng.uniform(0, 2 * math.pi)
        f = math.cos(a) * x + math.sin(a) * y
    elif shape in ("rows", "columns"):
        n = h if shape == "rows" else w
        prof = np.cumsum(rng.normal(size=n)) if rng.random() < 0.5 else rng.normal(size=n)
        prof = prof - prof.mean()
        f = np.repeat(prof[:, None], w, axis=1) if shape == "rows" else np.repeat(prof[None, :], h, axis=0)
    elif shape == "local":
        cx, cy = rng.uniform(0.2, 0.8) * (w - 1), rng.uniform(0.2, 0.8) * (h - 1)
        s = rng.uniform(0.05, 0.15) * w
        f = np.exp(-((u - cx) ** 2 + (v - cy) ** 2) / (2 * s * s))
    else:
        raise ValueError(shape)
    if shape not in ("uniform", "local"):
        f = f - f.mean()
    rms = float(np.sqrt(np.mean(f * f)))
    return f / rms if rms > 0 else f


def draw(rng: np.random.Generator, n_freq: int, n_taps: int, *, pair: bool = False) -> list[Disturbance]:
    """One draw: a disturbance (or two of different channels) the sensor can show."""
    channels = [c for c in CHANNELS if not (c.startswith("freq") and n_freq < 2)]
    picked = rng.choice(channels, size=2 if pair else 1, replace=False)
    out = []
    for c in picked:
        shape = "uniform" if c in UNIFORM_ONLY else str(rng.choice(SHAPES))
        z = float(math.exp(rng.uniform(math.log(10.0), math.log(1000.0))))
        index = int(rng.integers(1, n_freq)) if c.startswith("freq") else int(rng.integers(1, n_taps)) \
            if c.startswith("tap") else 0
        out.append(Disturbance(str(c), shape, z, index=index, params={"seed": int(rng.integers(1 << 30))}))
    return out


def _signal_noise(scene: Any) -> np.ndarray:
    """The noise of one frame's complex signal per pixel and frequency (per component), from
    two noisy frames of the undisturbed light: ``|S_1 - S_2| / 2`` pooled over 5 x 5 pixels."""
    from scipy import ndimage

    from tofhil.demod import phasor
    from tofhil.sim.twin import Twin

    twin = Twin(scene)
    sig, sensor = twin.signal(), twin.sensor()
    s = [phasor(np.asarray(sensor.expose(sig, seed=s, frame_index=0, noise=True).taps, float),
                np.asarray(sensor.config.theta_rad)) for s in (101, 202)]
    d2 = np.abs(s[0] - s[1]) ** 2 / 4.0  # per component: var(Re) = var(Im) = |d|^2 / 4 on average
    return np.sqrt(ndimage.uniform_filter(d2, size=(1, 5, 5)))


def write_disturbed(scene: Any, path: Path, disturbances: list[Disturbance], *, frames: int = 4, seed: int = 0) -> Path:
    """A session of ``scene`` with the disturbances hidden (sizes set from their z-scores)."""
    from tests.eval import hidden_forms as hf
    from tofhil.demod import phasor
    from tofhil.sim.twin import Twin

    twin = Twin(scene)
    sig = twin.signal()
    h, w = sig.shape
    sigma = _signal_noise(scene)                      # [F, H, W] per component, one frame
    sensor = twin.sensor()
    amp_dn = np.abs(phasor(np.asarray(sensor.taps_dn(sig, noise=False), float),
                           np.asarray(sensor.config.theta_rad)))  # [F, H, W] the modulated signal in DN
    lit = amp_dn.min(axis=0) > 3 * sigma.max(axis=0)
    n_lit = max(int(lit.sum()), 1)
    nf = sig.freq_hz.size
    changes, frame_changes, tap_changes = [], [], []
    for d in disturbances:
        r = np.random.default_rng(d.params["seed"])
        f = field_shape(d.shape, h, w, r)
        # the whitened size of a relative change e of the signal is e |S| / sigma per component
        snr = float(np.sqrt(np.mean((amp_dn / sigma)[:, lit] ** 2)))
        per_px = d.z / math.sqrt(n_lit * nf * frames)  # rms whitened change per value
        if d.channel in ("gain", "freq_gain", "frame_gain"):
            d.size = per_px / snr                          # relative gain (rms)
        elif d.channel in ("range", "freq_phase", "frame_range"):
            d.size = per_px / snr                          # radians of phase (rms) at the first frequency
        elif d.channel == "offset":
            d.size = per_px / snr                          # relative to the mean modulated light (taps' K)
        elif d.channel == "tap_gain":
            d.size = per_px / snr * 2.0
        elif d.channel == "tap_offset":
            d.size = per_px * float(np.median(sigma[:, lit])) * 2.0  # DN
        sign = 1.0 if r.random() < 0.5 else -1.0
        changes_of = _change_for(d, f * sign, sig, nf)
        if d.channel.startswith("frame"):
            frame_changes.append(changes_of)
        elif d.channel.startswith("tap"):
            tap_changes.append(changes_of)
        else:
            changes.append(changes_of)

    def change(signal: Any, sensor: Any) -> Any:
        for c in changes:
            signal = c(signal)
        return signal

    def frame_change(signal: Any, i: int, n: int) -> Any:
        for c in frame_changes:
            signal = c(signal, i, n)
        return signal

    def tap_change(taps: np.ndarray, i: int) -> np.ndarray:
        for c in tap_changes:
            taps = c(taps)
        return taps

    return hf.write_session(scene, path, change if changes else None, frames=frames, seed=seed,
                            frame_change=frame_change if frame_changes else None,
                            tap_change=tap_change if tap_changes else None)


def _rotate(signal: Any, phase_fundamental: np.ndarray, only: int | None = None) -> Any:
    out = signal.copy()
    h = np.asarray(signal.harmonics, float)[:, None, None]
    out.phasor_w = np.array(signal.phasor_w)
    for k in range(signal.freq_hz.size):
        if only is None or k == only:
            scale = signal.freq_hz[k] / signal.freq_hz[0] if only is None else 1.0
            out.phasor_w[k] = signal.phasor_w[k] * np.exp(1j * h * phase_fundamental[None] * scale)
    return out


def _change_for(d: Disturbance, f: np.ndarray, sig: Any, nf: int) -> Any:
    s = d.size
    if d.channel == "gain":
        g = np.clip(1.0 + s * f, 0.05, None)

        def c(signal: Any) -> Any:
            out = signal.copy()
            out.phasor_w = signal.phasor_w * g[None, None]
            out.dc_w = np.asarray(signal.dc_w) * g
            return out
        return c
    if d.channel == "range":
        return lambda signal: _rotate(signal, s * f)
    if d.channel == "offset":
        def c(signal: Any) -> Any:
            out = signal.copy()
            level = float(np.mean(np.abs(signal.phasor_w[0, signal.harmonics.index(1)])))
            # an unmodulated light of this rms relative to the mean modulated light, kept >= 0
            # (a uniform field drawn negative would be no light at all: light is added either way)
            shifted = f - min(float(f.min()), 0.0)
            extra = s * level * (shifted if shifted.any() else np.abs(f)) * 4.0
            out.ambient_w = np.asarray(signal.ambient_w) + extra
            return out
        return c
    if d.channel == "freq_gain":
        def c(signal: Any) -> Any:
            out = signal.copy()
            out.phasor_w = np.array(signal.phasor_w)
            out.phasor_w[d.index] = signal.phasor_w[d.index] * (1.0 + s * float(f.mean()))
            return out
        return c
    if d.channel == "freq_phase":
        return lambda signal: _rotate(signal, np.full(signal.shape, s * float(f.mean())), only=d.index)
    if d.channel == "tap_gain":
        def c(taps: np.ndarray) -> np.ndarray:
            taps = np.array(taps, dtype=np.float64)
            taps[:, d.index] *= 1.0 + s * float(f.mean())
            return taps
        return c
    if d.channel == "tap_offset":
        def c(taps: np.ndarray) -> np.ndarray:
            taps = np.array(taps, dtype=np.float64)
            taps[:, d.index] += s * float(f.mean())
            return taps
        return c
    if d.channel == "frame_gain":
        def c(signal: Any, i: int, n: int) -> Any:
            g = 1.0 + s * math.sqrt(3.0) * (2 * i / max(n - 1, 1) - 1) * float(f.mean())
            out = signal.copy()
            out.phasor_w = signal.phasor_w * g
            out.dc_w = np.asarray(signal.dc_w) * g
            return out
        return c
    if d.channel == "frame_range":
        def c(signal: Any, i: int, n: int) -> Any:
            t = math.sqrt(3.0) * (2 * i / max(n - 1, 1) - 1)
            return _rotate(signal, np.full(signal.shape, s * t * float(f.mean())))
        return c
    raise ValueError(d.channel)


def sensor_variant(scene: Any, variant: str) -> Any:
    """The scene's sensor as drawn: ``"1f4t"`` (as written) or ``"2f3t"`` (44 + 60 MHz, three
    taps at 0, 120, 240 degrees)."""
    if variant == "1f4t":
        return scene
    sensor = dataclasses.replace(scene.sensor, freq_hz=(44e6, 60e6),
                                 theta_rad=tuple(2 * math.pi * k / 3 for k in range(3)))
    return dataclasses.replace(scene, sensor=sensor)


@dataclass
class Judgement:
    right: bool
    how: str           # "named" | "said" | "" (wrong)
    scene_mismatch: bool
    named: list[str]
    verdict: str


def judge(res: Any, disturbances: list[Disturbance]) -> Judgement:
    """Right when, for each disturbance, a family of its channel is named, or the verdict says
    its channel (and, for a field, a shape it reads as) in what is left; the scene mismatch
    verdict is counted apart (it is wrong for every draw: the geometry is right)."""
    named = list(res.causes) + (["drift"] if (res.drift or {}).get("named") else [])
    left = res.channel_table.get("after", {}).get("readings", []) if res.channel_table else []
    said_channels = {r["channel"] for r in left if r.get("significant")}
    fields = {(f["channel"], f["kind"]) for f in res.structure}
    hows = []
    for d in disturbances:
        fam = FAMILIES.get((d.channel, d.shape), set())
        if fam & set(named):
            hows.append("named")
            continue
        ch = SAID_IN[d.channel]
        if res.left is None:
            ok = False  # nothing is said to be left: a channel reading alone is no statement
        elif ch in ("amplitude", "depth"):
            ok = any(c == ch and k in SHAPE_WORDS[d.shape] for c, k in fields)
        else:
            ok = ch in said_channels
        hows.append("said" if ok else "")
    right = all(hows)
    return Judgement(right, ",".join(hows), res.verdict.kind == "scene does not match", named, res.verdict.kind)


C = C_M_PER_S  # (re-exported for the benchmark's unit conversions)
