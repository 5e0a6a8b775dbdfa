"""Sessions from the twin with one hidden change of a form the effect library lacks.

The change acts on the light on the sensor (an :class:`~tofhil.sim.sensor.OpticalSignal`)
between the render and the sensor model, so the frames carry the sensor's own noise, ADC
quantisation and clipping, exactly as a simulated session does; only the hidden change is
outside the library. Shared by the verdict tests and benchmarks/diagnose_sweep.py's forms.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil import C_M_PER_S
from tofhil.sim.sensor import OpticalSignal

Change = Callable[[OpticalSignal, Any], OpticalSignal]


def small_dark_square(width: int = 80) -> Any:
    """The bundled dark_square scene on a small camera (``width`` x 3/4 width pixels)."""
    from tofhil.sim.scene import load_scene

    scene = load_scene("dark_square")
    return dataclasses.replace(scene, camera=scene.camera.scaled(width / scene.camera.width))


def rotate_radial(signal: OpticalSignal, radial_m: np.ndarray | float) -> OpticalSignal:
    """Every harmonic's phase as if the pixel read ``radial_m`` farther (optical path 2 d)."""
    out = signal.copy()
    path = 2.0 * np.asarray(radial_m, dtype=np.float64)
    f = signal.freq_hz[:, None, None, None]
    h = np.asarray(signal.harmonics, dtype=np.float64)[None, :, None, None]
    out.phasor_w = signal.phasor_w * np.exp(1j * 2.0 * np.pi * h * f * path / C_M_PER_S)
    return out


def column_row_offsets(rng: np.random.Generator, col_sd_m: float = 0.008, pixel_sd_m: float = 0.006) -> Change:
    """Random per-column and per-pixel range offsets (fixed pattern noise of the readout)."""
    seed = int(rng.integers(1 << 30))

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        r = np.random.default_rng(seed)
        h, w = signal.shape
        offs = col_sd_m * r.standard_normal(w)[None, :] + pixel_sd_m * r.standard_normal((h, w))
        return rotate_radial(signal, offs)

    return change


def log_amplitude_error(rng: np.random.Generator, m_per_decade: float | None = None) -> Change:
    """A range error proportional to log10 of the pixel's amplitude (zero at the median)."""
    k = float(m_per_decade if m_per_decade is not None else rng.uniform(0.02, 0.04))

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        a = np.abs(signal.phasor_w[:, signal.harmonics.index(1)]).mean(axis=0)
        lit = a > 0
        ref = np.median(a[lit])
        err = np.where(lit, k * np.log10(np.maximum(a, 1e-30) / ref), 0.0)
        return rotate_radial(signal, err)

    return change


def unmodulated_offset(rng: np.random.Generator, times_signal: float = 2.0) -> Change:
    """A uniform unmodulated light about ``times_signal`` times the mean emitter light (not
    scene ambient: it does not follow the scene's reflectance or the lens)."""

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        out = signal.copy()
        out.ambient_w = np.array(signal.ambient_w) + times_signal * float(np.mean(signal.dc_w))
        return out

    return change


FrameChange = Callable[[OpticalSignal, int, int], OpticalSignal]
#: A change of the recorded taps ``[F, K, H, W]`` of frame ``i``.
TapChange = Callable[[np.ndarray, int], np.ndarray]


def _some_pixels(r: np.random.Generator, fraction: float, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``fraction`` of the pixels (at least one), drawn from ``r``: rows and columns."""
    h, w = shape
    idx = r.choice(h * w, max(int(round(fraction * h * w)), 1), replace=False)
    return np.unravel_index(idx, (h, w))


def stuck_pixels(rng: np.random.Generator, fraction: float = 0.003) -> TapChange:
    """A fraction of the pixels stuck: their taps random constants, the same in every frame
    (dead and stuck pixels of real sensors)."""
    seed = int(rng.integers(1 << 30))

    def change(taps: np.ndarray, i: int) -> np.ndarray:
        r = np.random.default_rng(seed)  # the same pixels and values every frame
        f, k = taps.shape[:2]
        v, u = _some_pixels(r, fraction, taps.shape[-2:])
        hi = float(np.percentile(taps, 99))
        taps[:, :, v, u] = r.uniform(0.0, hi, (f, k, v.size))
        return taps

    return change


def hot_pixels(rng: np.random.Generator, fraction: float = 0.003, times_noise: float = 20.0) -> TapChange:
    """Hot pixels: a dark charge far above the signal's, with its shot noise, new every frame."""
    seed = int(rng.integers(1 << 30))

    def change(taps: np.ndarray, i: int) -> np.ndarray:
        f, k = taps.shape[:2]
        v, u = _some_pixels(np.random.default_rng(seed), fraction, taps.shape[-2:])  # the same pixels every frame
        spread = float(np.median(np.abs(np.diff(taps, axis=-1)))) + 1.0
        noise = np.random.default_rng((seed, i)).standard_normal((f, k, v.size))
        taps[:, :, v, u] += times_noise * spread * (1.0 + noise)
        return taps

    return change


def linear_drift(rng: np.random.Generator, span_m: float | None = None) -> FrameChange:
    """A range drift linear in the frame index over ``span_m`` (first to last frame), zero
    on average over the session (warm-up: every pixel reads the same amount farther)."""
    span = float(span_m if span_m is not None else rng.uniform(0.008, 0.015) * rng.choice([-1.0, 1.0]))

    def change(signal: OpticalSignal, index: int, frames: int) -> OpticalSignal:
        t = index / max(frames - 1, 1) - 0.5
        return rotate_radial(signal, span * t)

    return change


def emitter_power_drift(span: float) -> FrameChange:
    """The emitter's power changing linearly over the frames by the relative ``span`` (first to
    last, zero on average; warm-up): its modulated light and its unmodulated part alike, the
    ambient not."""

    def change(signal: OpticalSignal, index: int, frames: int) -> OpticalSignal:
        g = 1.0 + span * (index / max(frames - 1, 1) - 0.5)
        out = signal.copy()
        out.phasor_w = signal.phasor_w * g
        out.dc_w = np.asarray(signal.dc_w) * g
        return out

    return change


def write_session(scene: Any, path: Path, change: Change | None, *, frames: int = 4, seed: int = 0,
                  frame_change: FrameChange | None = None, tap_change: TapChange | None = None) -> Path:
    """A session of ``frames`` noisy frames of the scene's twin with ``change`` applied to its
    light, ``frame_change`` to each frame's (given its index and the number of frames), and
    ``tap_change`` to each frame's recorded taps (what the pixels themselves do wrong)."""
    from tofhil.depth import depth_from_raw
    from tofhil.session import SessionWriter
    from tofhil.sim.scene import scene_to_yaml
    from tofhil.sim.twin import Twin

    twin = Twin(scene)
    signal = twin.signal()
    sensor = twin.sensor()
    if change is not None:
        signal = change(signal, sensor)
    device = {"model": "tofhil-sim", "scene": str(getattr(scene, "source", "")), "seed": int(seed), "noise": True}
    with SessionWriter(path, scene.camera, device=device, scene_text=scene_to_yaml(scene), force=True,
                       sensor_config=twin.config.to_dict(), derived=True) as w:
        for i in range(frames):
            light = signal if frame_change is None else frame_change(signal, i, frames)
            raw = sensor.expose(light, seed=seed, frame_index=i, noise=True)
            if tap_change is not None:
                raw = dataclasses.replace(raw, taps=tap_change(np.array(raw.taps), i).astype(raw.taps.dtype))
            w.append(raw, depth_from_raw(raw))
    return path


# ----------------------------------------------------------------------------- channel classes
# Classes of real camera behaviour that act on one calibration channel (issue: "Diagnosis that
# reads the evidence channel by channel"); each with random parameters from its generator.

def frequency_phase_offset(rng: np.random.Generator, index: int = 1, phase_rad: float | None = None) -> Change:
    """A calibration phase offset on one modulation frequency alone (an electronic delay of
    its demodulation reference): harmonic h of that frequency turns by h * phase."""
    phase = float(phase_rad if phase_rad is not None else rng.choice([-1.0, 1.0]) * rng.uniform(0.06, 0.15))

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        out = signal.copy()
        h = np.asarray(signal.harmonics, dtype=np.float64)
        out.phasor_w = np.array(signal.phasor_w)
        out.phasor_w[index] = signal.phasor_w[index] * np.exp(1j * h * phase)[:, None, None]
        return out

    change.phase_rad = phase  # type: ignore[attr-defined]
    return change


def tap_gain_imbalance(rng: np.random.Generator, gains: tuple[float, ...] | None = None,
                       offsets_dn: tuple[float, ...] | None = None) -> TapChange:
    """Taps 1 and 3 with 2-5 % more gain than taps 0 and 2 (and small tap offsets): the
    readout's per-tap imbalance, applied to the recorded taps (noise and all)."""
    g = gains if gains is not None else (1.0, 1.0 + rng.uniform(0.02, 0.05), 1.0, 1.0 + rng.uniform(0.02, 0.05))
    o = offsets_dn if offsets_dn is not None else (0.0,) * len(g)

    def change(taps: np.ndarray, i: int) -> np.ndarray:
        k = taps.shape[1]
        return taps * np.asarray(g[:k])[None, :, None, None] + np.asarray(o[:k])[None, :, None, None]

    return change


def radial_falloff(rng: np.random.Generator, extra: float | None = None) -> Change:
    """The modulated light falls toward the corners ``extra`` (30 %) more than cos^4 does (an
    emitter profile or a vignetting the twin lacks); depth untouched."""
    k = float(extra if extra is not None else rng.uniform(0.2, 0.4))

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        h, w = signal.shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        r2 = ((u - (w - 1) / 2) ** 2 + (v - (h - 1) / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        factor = 1.0 - k * r2          # 1 on the axis, 1 - extra in the corners
        out = signal.copy()
        out.phasor_w = signal.phasor_w * factor[None, None]
        out.dc_w = np.asarray(signal.dc_w) * factor
        return out

    return change


def _frame_xy(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """x, y from -1 at the first column (row) to +1 at the last."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return 2 * u / (w - 1) - 1, 2 * v / (h - 1) - 1


def gain_gradient(rng: np.random.Generator) -> Change:
    """The emitter's light rising linearly across the field by ``2 a`` (a = 10-25 %) in a random
    direction: a tilted emitter or a diffuser's gradient, which no radial beam makes. The
    change's ``slope_xy`` is ``a (cos t, sin t)`` per unit of x and y."""
    a, t = float(rng.uniform(0.10, 0.25)), float(rng.uniform(0, 2 * np.pi))

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        x, y = _frame_xy(signal.shape)
        factor = 1.0 + a * (np.cos(t) * x + np.sin(t) * y)
        out = signal.copy()
        out.phasor_w = signal.phasor_w * factor[None, None]
        out.dc_w = np.asarray(signal.dc_w) * factor
        return out

    change.slope_xy = (a * np.cos(t), a * np.sin(t))  # type: ignore[attr-defined]
    return change


def warm_corner(rng: np.random.Generator) -> Change:
    """Unmodulated charge rising toward one corner of the sensor (a dark current warmed by the
    driver beside it): ``L (0.3 + ((1 + sx x)(1 + sy y) / 4)^2)``, L 0.5-1.5 times the mean
    emitter light, the corner ``(sx, sy)`` random. The change's ``corner`` is ``(sx, sy)``."""
    level = float(rng.uniform(0.5, 1.5))
    sx, sy = (float(rng.choice([-1.0, 1.0])) for _ in range(2))

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        x, y = _frame_xy(signal.shape)
        shape = 0.3 + ((1 + sx * x) * (1 + sy * y) / 4) ** 2
        out = signal.copy()
        out.ambient_w = np.array(signal.ambient_w) + level * float(np.mean(signal.dc_w)) * shape
        return out

    change.corner = (sx, sy)  # type: ignore[attr-defined]
    return change


def warm_up_drift(rng: np.random.Generator, span_m: float | None = None, amplitude_per_frame: float = -0.01
                  ) -> FrameChange:
    """A warm-up drift: the range moves by ``span_m`` (12-25 mm) over the frames, slowing as
    it settles, and the modulated light falls by 1 % per frame."""
    span = float(span_m if span_m is not None else rng.uniform(0.012, 0.025))

    def change(signal: OpticalSignal, i: int, n: int) -> OpticalSignal:
        t = i / max(n - 1, 1)
        out = rotate_radial(signal, span * (1.0 - np.exp(-3.0 * t)) / (1.0 - np.exp(-3.0)))
        out.phasor_w = out.phasor_w * (1.0 + amplitude_per_frame * i)
        return out

    return change


def with_frequencies(scene: Any, freq_hz: tuple[float, ...]) -> Any:
    """The scene with its sensor demodulating at ``freq_hz``."""
    return dataclasses.replace(scene, sensor=dataclasses.replace(scene.sensor, freq_hz=tuple(freq_hz)))


def outside_panel_multipath(rng: np.random.Generator, camera: Any = None, *, side: float | None = None,
                            size_m: float | None = None, albedo: float = 0.9, profile_n: float = 2.0,
                            patches: int = 12) -> Change:
    """A white panel beside the camera, outside its field of view, that the emitter lights and
    that lights the scene in turn (one indirect bounce the twin lacks: its scene has no panel).

    Computed in closed form, independently of the renderer: each panel patch ``j`` receives
    ``I(theta_j) cos / r1^2`` from the emitter (at the camera, profile ``cos^n``), sends
    ``albedo / pi`` of it as a Lambertian patch, and the scene point ``X_i`` (a Lambertian
    surface, as the twin's) receives ``cos_out cos_in dA / r2^2`` of that. Both the direct and
    the panel's light leave ``X_i`` toward the camera by the same BRDF, so the panel adds
    ``ratio_ij = E_panel_ij / E_direct_i`` of the direct light with the path longer by
    ``r1 + r2 - |X_i|``. The scene points come from the signal's own path length and the
    camera's rays (``camera``, else the sensor's; a noise-free twin: exact)."""
    sgn = float(side if side is not None else rng.choice([-1.0, 1.0]))
    size = float(size_m if size_m is not None else rng.uniform(0.35, 0.55))
    centre = np.array([sgn * rng.uniform(0.40, 0.50), rng.uniform(-0.05, 0.05), rng.uniform(0.30, 0.40)])

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        f0 = float(signal.freq_hz[0])
        h1 = signal.harmonics.index(1)
        path = np.angle(signal.phasor_w[0, h1]) % (2 * np.pi) * C_M_PER_S / (2 * np.pi * f0)   # L = 2 r
        cam = camera if camera is not None else sensor.camera
        x = cam.rays * (path / 2.0)[..., None]                                                    # [H, W, 3]
        n = np.cross(np.gradient(x, axis=1), np.gradient(x, axis=0))
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        n *= -np.sign(np.sum(n * x, axis=-1, keepdims=True))           # facing the camera
        # the panel faces a point between the camera and the scene's centre
        aim = np.array([0.0, 0.0, 0.5 * float(np.median(x[..., 2]))])
        m = (aim - centre) / np.linalg.norm(aim - centre)
        a = np.cross(m, [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(m, a)
        s = (np.arange(patches) + 0.5) / patches - 0.5
        pts = centre + size * (s[:, None, None] * a + s[None, :, None] * b).reshape(-1, 3)  # [J, 3]
        d_a = (size / patches) ** 2
        r1 = np.linalg.norm(pts, axis=-1)
        to_emitter = -pts / r1[:, None]
        e_panel = (pts[:, 2] / r1) ** profile_n * np.clip(to_emitter @ m, 0, None) / r1 ** 2      # [J]
        xi = x.reshape(-1, 3)
        ni = n.reshape(-1, 3)
        d = pts[None] - xi[:, None]                                      # [P, J, 3] scene -> panel
        r2 = np.linalg.norm(d, axis=-1)
        u = d / r2[..., None]
        cos_panel = np.clip(-(u @ m), 0, None)
        cos_scene = np.clip(np.einsum("pjk,pk->pj", u, ni), 0, None)
        ri = np.linalg.norm(xi, axis=-1)
        e_direct = (xi[:, 2] / ri) ** profile_n * np.clip(np.sum(-xi / ri[:, None] * ni, axis=-1), 0, None) / ri ** 2
        ratio = (e_panel[None] * albedo / np.pi * cos_panel * cos_scene * d_a / r2 ** 2
                 / np.maximum(e_direct, 1e-30)[:, None])                 # [P, J]
        excess = r1[None] + r2 - ri[:, None]
        out = signal.copy()
        hw = signal.shape
        h = np.asarray(signal.harmonics, dtype=np.float64)
        k = 2 * np.pi * signal.freq_hz[:, None, None] * h[None, :, None] / C_M_PER_S      # [F, NH, 1]
        factor = 1.0 + np.einsum("pj,fhpj->fhp", ratio, np.exp(1j * k[..., None] * excess[None, None]))
        out.phasor_w = signal.phasor_w * factor.reshape(signal.phasor_w.shape[:2] + hw)
        out.dc_w = np.asarray(signal.dc_w) * (1.0 + ratio.sum(axis=1)).reshape(hw)
        change.ratio = ratio.sum(axis=1).reshape(hw)  # type: ignore[attr-defined]
        return out

    change.side = sgn  # type: ignore[attr-defined]
    return change
