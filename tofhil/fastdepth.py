"""Fused demodulation + unwrapping for the common case: 4 taps, one or two frequencies.

One pass over the taps per frequency computes the complex signal from the tap differences,
its amplitude and phase, the offset, and (two frequencies) the Chinese-remainder unwrapping
of :mod:`tofhil.unwrap`, so the intermediate images never leave the CPU cache. The phase uses
a branch-free arctangent polynomial (|error| < 1e-7 rad, about float32 rounding) that the
compiler vectorises; the results agree with the numpy path of
:func:`tofhil.depth.depth_from_raw` to that level (tested). The same pass flags pixels with a
saturated or non-finite tap (:func:`tofhil.demod.bad_tap_pixels`), so the kernels are
compiled without the no-NaN/no-inf fast-math assumptions (a NaN tap must be seen as one).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tofhil.demod import TapLimits

_PI = np.float32(math.pi)
_HALF_PI = np.float32(math.pi / 2)
_TWO_PI = np.float32(2 * math.pi)
#: Fast-math without ``nnan``/``ninf``: NaN and inf taps must compare as such.
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(inline="always", fastmath=_FASTMATH)
def _phase(y: float, x: float) -> float:
    """atan2(y, x) mapped into [0, 2 pi).

    atan(a) = a P(a^2) on [0, 1] with P of degree 7 (a Chebyshev fit: |error| < 8e-8 rad);
    one division, and every branch a select, so the pixel loop vectorises.
    """
    ax = abs(x)
    ay = abs(y)
    a = min(ax, ay) / max(max(ax, ay), np.float32(1e-30))
    s = a * a
    r = a * (np.float32(9.9999989775e-01) + s * (np.float32(-3.3331959724e-01) + s * (np.float32(1.9969235395e-01)
             + s * (np.float32(-1.4016585043e-01) + s * (np.float32(9.9060968994e-02) + s * (np.float32(-5.9367100835e-02)
             + s * (np.float32(2.4166189554e-02) + s * np.float32(-4.6687733166e-03))))))))
    r = _HALF_PI - r if ay > ax else r
    r = _PI - r if x < 0 else r
    r = _TWO_PI - r if y < 0 else r
    return min(r, np.float32(6.2831850))  # the largest float32 below 2 pi


@njit(fastmath=_FASTMATH, cache=True)
def _demod4(taps, w, lo, hi, out_phase, out_amp, out_sum, out_bad):
    """taps [F, 4, N] -> phase [F, N], amplitude [F, N], tap sum over all F*4 taps [N], and
    ``out_bad`` [N] uint8: 1 where a tap is not inside the open interval (lo, hi)."""
    nf = taps.shape[0]
    n = taps.shape[2]
    for p in range(n):
        out_sum[p] = 0.0
        out_bad[p] = np.uint8(0)
    for f in range(nf):
        t0 = taps[f, 0]
        t1 = taps[f, 1]
        t2 = taps[f, 2]
        t3 = taps[f, 3]
        for p in range(n):
            d0 = t0[p] - t2[p]
            d1 = t1[p] - t3[p]
            i = w[0] * d0 + w[1] * d1
            q = w[2] * d0 + w[3] * d1
            out_amp[f, p] = math.sqrt(i * i + q * q)
            out_phase[f, p] = _phase(q, i)
            out_sum[p] += t0[p] + t1[p] + t2[p] + t3[p]
            good = ((t0[p] > lo) & (t0[p] < hi) & (t1[p] > lo) & (t1[p] < hi)
                    & (t2[p] > lo) & (t2[p] < hi) & (t3[p] > lo) & (t3[p] < hi))
            out_bad[p] |= np.uint8(0) if good else np.uint8(1)


@njit(fastmath=_FASTMATH, cache=True)
def _unwrap2(phase, amp, c, out_d, out_conflict, out_amp):
    """Two-frequency Chinese-remainder unwrapping (see tofhil.unwrap._unwrap_two), and the
    mean amplitude. ``out_conflict`` is uint8 (a bool store would stop vectorisation).

    c = [m2/2pi, m1/2pi, r1/2pi, -b*r1, r2/2pi, a*r2, m1^2, m2^2, range, 1/range, margin/2]
    """
    n = phase.shape[1]
    half = np.float32(0.5)
    for p in range(n):
        x = phase[0, p] * c[0] - phase[1, p] * c[1]
        e = np.floor(x + half)
        resid = abs(x - e)
        u1 = phase[0, p] * c[2] + e * c[3]
        u2 = phase[1, p] * c[4] + e * c[5]
        a0 = amp[0, p]
        a1 = amp[1, p]
        w1 = c[6] * a0 * a0
        w2 = c[7] * a1 * a1
        d = u1 + (u2 - u1) * (w2 / (w1 + w2 + np.float32(1e-30)))
        d = d - np.floor(d * c[9]) * c[8]
        out_d[p] = min(d, c[8])
        out_conflict[p] = np.uint8(1) if resid > c[10] else np.uint8(0)
        out_amp[p] = half * (a0 + a1)


def fused_supported(taps: np.ndarray, theta_rad: np.ndarray) -> bool:
    """Four taps in order (tap k + 2 opposite tap k), one or two frequencies, float32."""
    from tofhil.demod import estimator_weights

    if taps.ndim != 4 or taps.shape[1] != 4 or taps.shape[0] not in (1, 2) or taps.dtype != np.float32:
        return False
    w = estimator_weights(theta_rad)
    return bool(np.allclose(w[2], -w[0]) and np.allclose(w[3], -w[1]))


def fused_depth(taps: np.ndarray, theta_rad: np.ndarray, freq_hz: np.ndarray, margin: float,
                limits: TapLimits | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """``(distance, amplitude mean, intensity mean, conflict, unambiguous range, bad taps)``
    for float32 taps ``[F, 4, H, W]`` with F = 1 or 2; ``bad taps`` is
    :func:`tofhil.demod.bad_tap_pixels` of ``taps`` and ``limits``."""
    from tofhil.demod import estimator_weights
    from tofhil.unwrap import _ext_gcd, frequency_plan

    nf, k, h, wd = taps.shape
    wts = estimator_weights(theta_rad)  # w_{k+2} = -w_k for equally spaced taps
    w = np.array([wts[0].real, wts[1].real, wts[0].imag, wts[1].imag], dtype=np.float32)
    flat = np.ascontiguousarray(taps).reshape(nf, k, h * wd)
    phase = np.empty((nf, h * wd), np.float32)
    amp = np.empty((nf, h * wd), np.float32)
    total = np.empty(h * wd, np.float32)
    bad = np.empty(h * wd, np.uint8)
    lo, hi = (limits or TapLimits()).bounds(np.float32)
    _demod4(flat, w, lo, hi, phase, amp, total, bad)
    plan = frequency_plan(freq_hz)
    rng = plan.unambiguous_range_m
    if nf == 1:
        distance = phase[0] * np.float32(plan.wrap_range_m(0) / (2 * np.pi))
        conflict = np.zeros(h * wd, bool)
    else:
        m1, m2 = plan.multiples
        a, b = _ext_gcd(m1, m2)
        r1, r2 = plan.wrap_range_m(0), plan.wrap_range_m(1)
        two_pi = 2 * np.pi
        c = np.array([m2 / two_pi, m1 / two_pi, r1 / two_pi, -b * r1, r2 / two_pi, a * r2, m1 * m1, m2 * m2,
                      rng, 1.0 / rng, margin / 2], dtype=np.float32)
        distance = np.empty(h * wd, np.float32)
        conflict = np.empty(h * wd, np.uint8)
        amplitude = np.empty(h * wd, np.float32)
        _unwrap2(phase, amp, c, distance, conflict, amplitude)
        conflict = conflict.view(bool)
    if nf == 1:
        amplitude = amp[0]
    intensity = total * np.float32(1.0 / (nf * k))
    return (distance.reshape(h, wd), amplitude.reshape(h, wd), intensity.reshape(h, wd),
            conflict.reshape(h, wd), rng, bad.view(bool).reshape(h, wd))
