"""Demodulation: correlation taps -> complex signal -> phase, amplitude, offset, distance.

Canonical tap model: ``c_k = B + A*cos(phi - theta_k)``. For K >= 3 taps equally spaced over
2*pi the estimator ``S = (2/K) * sum_k c_k * exp(i*theta_k)`` returns ``A*exp(i*phi)``
exactly (the second harmonic of the sum vanishes). Holmlund's 4-phase AB values
(theta = 0, 90, 180, 270 deg) and 3-phase devices are special cases.

Two-tap (A/B differential) pixels read two complementary taps per sub-frame: tap A at
``theta_m``, tap B at ``theta_m + pi``. Their difference ``D_m = a_m - b_m = 2A cos(phi -
theta_m)`` cancels the offset and the ambient light; ``S = (1/M) sum_m D_m exp(i theta_m)``
for M >= 2 sub-frames equally spaced over pi.

Device-specific tap order and sign are data (:class:`TapConvention`) converted at the
driver edge, never folded into the estimator.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from tofhil import C_M_PER_S


def ambiguity_range_m(freq_hz: float | np.ndarray) -> float | np.ndarray:
    """Unambiguous radial range ``c / (2 f)``."""
    return C_M_PER_S / (2.0 * np.asarray(freq_hz, dtype=np.float64))


def equally_spaced_phases(k: int, start_rad: float = 0.0) -> np.ndarray:
    """``k`` demodulation phases ``start + 2*pi*j/k``."""
    return start_rad + 2.0 * np.pi * np.arange(k) / k


def _check_equally_spaced(theta_rad: np.ndarray, period: float) -> None:
    k = theta_rad.size
    steps = np.diff(np.sort(np.mod(theta_rad - theta_rad[0], period)))
    if k < 2 or not np.allclose(steps, period / k, atol=1e-6):
        raise ValueError(f"phases {np.degrees(theta_rad).round(3).tolist()} deg are not "
                         f"{k} equally spaced steps over {np.degrees(period):.0f} deg")


def estimator_weights(theta_rad: np.ndarray) -> np.ndarray:
    """Complex weights ``w_k`` with ``S = sum_k w_k c_k`` (``[K]`` complex128)."""
    w = _estimator_weights(tuple(float(t) for t in np.atleast_1d(theta_rad)))
    return w.copy()


@lru_cache(maxsize=64)
def _estimator_weights(theta_t: tuple[float, ...]) -> np.ndarray:
    theta = np.asarray(theta_t, dtype=np.float64)
    if theta.size < 3:
        raise ValueError(f"the K-tap estimator needs K >= 3 taps, got {theta.size}; "
                         "use differential_phasor() for 2-tap A/B readouts")
    _check_equally_spaced(theta, 2 * np.pi)
    return (2.0 / theta.size) * np.exp(1j * theta)


def iq(taps: np.ndarray, theta_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-phase and quadrature parts ``(Re S, Im S)`` from taps ``[..., K, H, W]``.

    Weighted sums tap by tap, skipping zero weights (half of them for 4-phase taps): the
    hot path of every frame, kept to the fewest passes over memory.
    """
    w = estimator_weights(theta_rad)
    taps = np.asarray(taps)
    k = taps.shape[-3]
    if k != w.size:
        raise ValueError(f"taps have K={k}, theta_rad has {w.size} phases")
    dtype = np.float32 if taps.dtype == np.float32 else np.float64
    if k % 2 == 0:
        # Equally spaced with even K: tap k + K/2 has the opposite weight of tap k, so
        # work on the K/2 differences (for 4 taps: I = (c0 - c2)/2, Q = (c1 - c3)/2).
        half = k // 2
        diffs = [np.subtract(taps[..., j, :, :], taps[..., j + half, :, :], dtype=dtype) for j in range(half)]
        w = w[:half]
    else:
        diffs = [taps[..., j, :, :] for j in range(k)]
    parts = []
    for weights in (w.real, w.imag):
        acc = None
        for d, wj in zip(diffs, weights):
            if abs(wj) < 1e-12:
                continue
            term = d * dtype(wj)
            if acc is None:
                acc = term
            else:
                acc += term
        parts.append(acc if acc is not None else np.zeros(diffs[0].shape, dtype))
    return parts[0], parts[1]


def phasor(taps: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """Complex signal ``S = A exp(i phi)`` from taps ``[..., K, H, W]`` -> ``[..., H, W]``."""
    i, q = iq(taps, theta_rad)
    return i + 1j * q if i.dtype == np.float64 else (i + np.complex64(1j) * q)


def offset(taps: np.ndarray) -> np.ndarray:
    """Offset ``B`` (mean of equally spaced taps): ``[..., K, H, W]`` -> ``[..., H, W]``."""
    return np.mean(taps, axis=-3)


def taps_from_signal(amplitude: np.ndarray, phase_rad: np.ndarray, offset_b: np.ndarray,
                     theta_rad: np.ndarray) -> np.ndarray:
    """Forward model ``c_k = B + A cos(phi - theta_k)``: ``[..., H, W]`` -> ``[..., K, H, W]``."""
    a = np.asarray(amplitude)[..., None, :, :]
    p = np.asarray(phase_rad)[..., None, :, :]
    b = np.asarray(offset_b)[..., None, :, :]
    th = np.asarray(theta_rad, dtype=np.float64)[:, None, None]
    return b + a * np.cos(p - th)


def differential_phasor(tap_a: np.ndarray, tap_b: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """2-tap A/B differential readouts -> complex signal.

    ``tap_a[..., M, H, W]`` sampled at ``theta_m``, ``tap_b`` at ``theta_m + pi``; the
    M >= 2 phases ``theta_m`` are equally spaced over pi (0 and 90 deg for M = 2).
    Offset and tap-independent ambient light cancel in ``a - b``.
    """
    theta = np.asarray(theta_rad, dtype=np.float64)
    if theta.size < 2:
        raise ValueError("differential demodulation needs M >= 2 sub-frames")
    _check_equally_spaced(theta, np.pi)
    d = np.asarray(tap_a, dtype=np.float64) - np.asarray(tap_b, dtype=np.float64)
    w = np.exp(1j * theta) / theta.size
    return np.tensordot(w, d, axes=([0], [-3])) if d.ndim == 3 else np.einsum("m,...mhw->...hw", w, d)


def differential_offset(tap_a: np.ndarray, tap_b: np.ndarray) -> np.ndarray:
    """Offset ``B`` from A/B readouts: mean over sub-frames of ``(a + b) / 2``."""
    return 0.5 * np.mean(np.asarray(tap_a, dtype=np.float64) + np.asarray(tap_b, dtype=np.float64), axis=-3)


def differential_to_taps(tap_a: np.ndarray, tap_b: np.ndarray, theta_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interleave A/B sub-frames into canonical taps ``[..., 2M, H, W]`` and their phases.

    Sub-frame m gives tap A at ``theta_m`` and tap B at ``theta_m + pi``; the 2M phases
    are then equally spaced over 2*pi, so :func:`phasor` applies unchanged.
    """
    theta = np.asarray(theta_rad, dtype=np.float64)
    _check_equally_spaced(theta, np.pi)
    taps = np.concatenate([np.asarray(tap_a), np.asarray(tap_b)], axis=-3)
    phases = np.concatenate([theta, theta + np.pi])
    order = np.argsort(np.mod(phases, 2 * np.pi))
    return np.take(taps, order, axis=-3), np.mod(phases[order], 2 * np.pi)


def radians_per_metre(freq_hz: float | np.ndarray) -> np.ndarray:
    """Phase per metre of radial distance, ``4 pi f / c`` (the light goes there and back)."""
    return 4.0 * np.pi * np.asarray(freq_hz) / C_M_PER_S


def phase_to_distance(phase_rad: np.ndarray, freq_hz: float | np.ndarray) -> np.ndarray:
    """Phase in [0, 2*pi) -> radial distance ``d = c*phi/(4*pi*f)`` (wrapped at ``c/2f``)."""
    return np.asarray(phase_rad) * (C_M_PER_S / (4.0 * np.pi * np.asarray(freq_hz)))


def distance_to_phase(distance_m: np.ndarray, freq_hz: float | np.ndarray) -> np.ndarray:
    """Radial distance -> phase ``phi = 4*pi*f*d/c`` wrapped into [0, 2*pi)."""
    return np.mod(np.asarray(distance_m) * radians_per_metre(freq_hz), 2 * np.pi)


def wrapped_phase(s: np.ndarray) -> np.ndarray:
    """Phase of a complex signal in [0, 2*pi)."""
    return phase_from_iq(s.real, s.imag)


def phase_from_iq(i: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Phase in [0, 2*pi) from in-phase and quadrature parts.

    ``atan2(-q, -i) + pi`` lands in [0, 2*pi] without a branch (only -0.0 maps to 2*pi,
    which every user treats modulo 2*pi).
    """
    p = np.arctan2(-q, -i)
    p += p.dtype.type(np.pi)
    return p


@dataclass(frozen=True)
class TapConvention:
    """How a device's taps map onto the canonical model, declared per device profile.

    ``order[j]`` is the index in the device's tap stack of canonical tap ``j``;
    ``theta_rad[j]`` its demodulation phase; ``sign`` is +1 when the device reports
    ``B + A cos(phi - theta)`` and -1 when it reports the negated correlation
    ``B - A cos(phi - theta)`` (as DCS differences of some sensors do).
    """

    theta_rad: tuple[float, ...]
    order: tuple[int, ...] | None = None
    sign: float = 1.0

    def to_canonical(self, device_taps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Device tap stack ``[..., K, H, W]`` -> canonical taps and their phases."""
        taps = np.asarray(device_taps)
        if self.order is not None:
            taps = np.take(taps, list(self.order), axis=-3)
        if self.sign < 0:
            # B - A cos(phi - theta) = B + A cos(phi - (theta + pi)): shift phases, keep data.
            theta = np.mod(np.asarray(self.theta_rad) + np.pi, 2 * np.pi)
        else:
            theta = np.asarray(self.theta_rad, dtype=np.float64)
        return taps, theta


# ---------------------------------------------------------------------------- tap validity
@dataclass(frozen=True)
class TapLimits:
    """The range a device's ADC can report for a tap, in DN.

    A tap at or beyond either end is **saturated** (clipped: the true value is unknown);
    a non-finite tap is invalid as well. ``None`` means the end is not known. Signed
    differential devices (the TOFcam635: 12-bit DCS minus its 2048 mid-scale) clip at both
    ends; single-ended sensors at the top only.
    """

    high_dn: float | None = None
    low_dn: float | None = None

    @classmethod
    def from_meta(cls, meta: dict) -> "TapLimits":
        """The limits a frame declares (``meta['saturation_dn']`` and ``meta['saturation_low_dn']``)."""
        hi, lo = meta.get("saturation_dn"), meta.get("saturation_low_dn")
        return cls(high_dn=None if hi is None else float(hi), low_dn=None if lo is None else float(lo))

    def bounds(self, dtype: np.dtype | type = np.float32) -> tuple[float, float]:
        """Open interval ``(lo, hi)`` of good taps: a tap ``t`` is good iff ``lo < t < hi``
        (NaN fails both comparisons; unknown ends are infinite, so +-inf taps fail too)."""
        t = np.dtype(dtype).type
        return (t(-np.inf) if self.low_dn is None else t(self.low_dn),
                t(np.inf) if self.high_dn is None else t(self.high_dn))


def bad_tap_pixels(taps: np.ndarray, limits: TapLimits | None = None) -> np.ndarray:
    """Pixels ``[H, W]`` where any tap ``[..., K, H, W]`` is saturated or not finite.

    The one definition of a saturated tap: at or beyond :class:`TapLimits` (the diagnosis
    split uses it too, through :func:`bad_extremes`).
    """
    taps = np.asarray(taps)
    lo, hi = (limits or TapLimits()).bounds(taps.dtype if taps.dtype.kind == "f" else np.float64)
    good = (taps > lo) & (taps < hi)
    return ~good.reshape((-1,) + taps.shape[-2:]).all(axis=0)


def bad_extremes(taps_max: np.ndarray, taps_min: np.ndarray, limits: TapLimits | None = None) -> np.ndarray:
    """:func:`bad_tap_pixels` from per-pixel extremes of the taps (over frames, frequencies
    and taps): a pixel is bad if its largest tap reaches the top or its smallest the bottom."""
    lo, hi = (limits or TapLimits()).bounds(np.float64)
    with np.errstate(invalid="ignore"):
        return ~((np.asarray(taps_max) < hi) & (np.asarray(taps_min) > lo))


def clip_limits(taps_max: np.ndarray, taps_min: np.ndarray, declared: TapLimits | None = None,
                high_dn: float | None = None) -> TapLimits:
    """The clip levels to apply to a session's taps: ``high_dn`` given by the user wins, then the
    limits the device declares, then :func:`detect_clipping` on the data (per end)."""
    declared = declared or TapLimits()
    detected = detect_clipping(taps_max, taps_min)
    hi = high_dn if high_dn is not None else declared.high_dn if declared.high_dn is not None else detected.high_dn
    lo = declared.low_dn if declared.low_dn is not None else detected.low_dn
    return TapLimits(high_dn=hi, low_dn=lo)


def detect_clipping(taps_max: np.ndarray, taps_min: np.ndarray, *, min_pixels: int = 5) -> TapLimits:
    """Clipping levels inferred from data whose device declares none: the largest (and, for
    signed taps, the most negative) value shared by ``min_pixels`` or more pixels is where
    the ADC or the full well stopped. Use on many frames of a real capture, not on synthetic
    frames (a noise-free uniform image would look clipped everywhere)."""
    tmax = np.asarray(taps_max, dtype=np.float64)
    tmin = np.asarray(taps_min, dtype=np.float64)
    finite_max, finite_min = tmax[np.isfinite(tmax)], tmin[np.isfinite(tmin)]
    hi = lo = None
    if finite_max.size:
        top = float(finite_max.max())
        if (finite_max >= top).sum() >= min_pixels:
            hi = top
    if finite_min.size:
        bottom = float(finite_min.min())
        if bottom < 0 and (finite_min <= bottom).sum() >= min_pixels:
            lo = bottom
    return TapLimits(high_dn=hi, low_dn=lo)


def tap_pattern(taps: np.ndarray) -> np.ndarray:
    """The taps' alternating part ``(1/K) sum_k (-1)^k c_k`` of taps ``[..., K, H, W]`` (K even,
    4 or more) -> ``[..., H, W]``: orthogonal to the offset and to the fundamental, so no change
    of the light (a range, a gain, a phase, a pose) makes it; tap gains (with an offset), tap
    offsets and even harmonics do. It is what an even number of taps holds beyond ``B`` and ``S``."""
    k = taps.shape[-3]
    sign = (-1.0) ** np.arange(k)
    return np.tensordot(taps, sign, axes=([taps.ndim - 3], [0])) / k
