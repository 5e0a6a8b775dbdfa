"""Fused demodulation + unwrapping: any K >= 3 equally spaced taps, one to three frequencies.

One pass over the taps, block of pixels by block, computes every frequency's complex signal
from the taps (their differences for even K), its amplitude and phase, the offset, and the
unwrapping of :mod:`tofhil.unwrap` (two frequencies: Chinese remainder; three: the search
over the lowest frequency's wrap counts), so the intermediate images never leave the CPU
cache. The phase uses a branch-free arctangent polynomial (|error| < 1e-7 rad, about float32
rounding) that the compiler vectorises; the results agree with the numpy path of
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


#: Pixels per block: the block's I, Q, tap sum and validity stay in the L1/L2 cache while
#: every tap image streams through once.
_BLOCK = 1024


@njit(fastmath=_FASTMATH, cache=True)
def _fused(taps, wr, wi, lo, hi, c, r, fw, spacing, out_d, out_amp, out_int, out_conf, out_bad):  # pragma: no cover
    """taps [F, K, N] float32 -> distance, mean amplitude, mean tap (intensity), conflict
    (uint8) and bad taps (uint8: a tap not inside the open interval (lo, hi)), in one pass.

    Per block of pixels: I and Q of every frequency (tap differences ``c_j - c_{j+K/2}``
    for even K, as :func:`tofhil.demod.iq`), then phase, amplitude and the unwrapping of
    :mod:`tofhil.unwrap` (F = 2: Chinese remainder; F = 3: search over the lowest
    frequency's wrap counts). ``c`` = [m2/2pi, m1/2pi, r1/2pi, -b*r1, r2/2pi, a*r2, m1^2, m2^2,
    range, 1/range, margin/2, 1/(F*K), reference frequency, its multiple],
    ``r`` the wrap ranges, ``fw`` the weight factors ``(f_i/f_0)^2``, ``spacing`` the
    conflict thresholds ``margin * decision spacing``.
    """
    nf = taps.shape[0]
    k = taps.shape[1]
    n = taps.shape[2]
    half = k // 2 if k % 2 == 0 else 0
    bi = np.empty((nf, _BLOCK), np.float32)
    bq = np.empty((nf, _BLOCK), np.float32)
    S = np.empty(_BLOCK, np.float32)
    G = np.empty(_BLOCK, np.uint8)
    ph = np.empty(3, np.float32)
    am = np.empty(3, np.float32)
    wrp = np.empty(3, np.float32)
    us = np.empty(3, np.float32)
    best = np.empty(3, np.float32)
    wt = np.empty(3, np.float32)
    inv_two_pi = np.float32(1.0 / (2.0 * math.pi))
    for b0 in range(0, n, _BLOCK):
        m = min(_BLOCK, n - b0)
        for j in range(m):
            S[j] = 0.0
            G[j] = np.uint8(1)
        for f in range(nf):
            for j in range(m):
                bi[f, j] = 0.0
                bq[f, j] = 0.0
            if half:
                for t in range(half):
                    ta = taps[f, t, b0:b0 + m]
                    tb = taps[f, t + half, b0:b0 + m]
                    a_r = wr[t]
                    a_i = wi[t]
                    for j in range(m):
                        x = ta[j]
                        y = tb[j]
                        dd = x - y
                        bi[f, j] += a_r * dd
                        bq[f, j] += a_i * dd
                        S[j] += x + y
                        ok = (x > lo) & (x < hi) & (y > lo) & (y < hi)
                        G[j] &= np.uint8(1) if ok else np.uint8(0)
            else:
                for t in range(k):
                    ta = taps[f, t, b0:b0 + m]
                    a_r = wr[t]
                    a_i = wi[t]
                    for j in range(m):
                        x = ta[j]
                        bi[f, j] += a_r * x
                        bq[f, j] += a_i * x
                        S[j] += x
                        ok = (x > lo) & (x < hi)
                        G[j] &= np.uint8(1) if ok else np.uint8(0)
        for j in range(m):
            p = b0 + j
            out_int[p] = S[j] * c[11]
            out_bad[p] = np.uint8(1) - G[j]
            asum = np.float32(0.0)
            for f in range(nf):
                i_ = bi[f, j]
                q_ = bq[f, j]
                am[f] = math.sqrt(i_ * i_ + q_ * q_)
                ph[f] = _phase(q_, i_)
                asum += am[f]
            out_amp[p] = asum / np.float32(nf) if nf != 2 else np.float32(0.5) * (am[0] + am[1])
            if nf == 1:
                out_d[p] = ph[0] * (r[0] * inv_two_pi)
                out_conf[p] = np.uint8(0)
            elif nf == 2:
                x = ph[0] * c[0] - ph[1] * c[1]
                e = np.floor(x + np.float32(0.5))
                resid = abs(x - e)
                u1 = ph[0] * c[2] + e * c[3]
                u2 = ph[1] * c[4] + e * c[5]
                w1 = c[6] * am[0] * am[0]
                w2 = c[7] * am[1] * am[1]
                d = u1 + (u2 - u1) * (w2 / (w1 + w2 + np.float32(1e-30)))
                d = d - np.floor(d * c[9]) * c[8]
                out_d[p] = min(d, c[8])
                out_conf[p] = np.uint8(1) if resid > c[10] else np.uint8(0)
            else:
                ref = int(c[12])
                wsum = np.float32(0.0)
                for f in range(nf):
                    wrp[f] = ph[f] * (r[f] * inv_two_pi)
                    wt[f] = fw[f] * am[f] * am[f] + np.float32(1e-30)
                    wsum += wt[f]
                best_cost = np.float32(np.inf)
                for cnt in range(int(c[13])):
                    cand = wrp[ref] + np.float32(cnt) * r[ref]
                    mean = np.float32(0.0)
                    for f in range(nf):
                        us[f] = wrp[f] + np.floor((cand - wrp[f]) / r[f] + np.float32(0.5)) * r[f]
                        mean += wt[f] * us[f]
                    mean /= wsum
                    cost = np.float32(0.0)
                    for f in range(nf):
                        cost += wt[f] * (us[f] - mean) * (us[f] - mean)
                    if cnt == 0 or cost < best_cost:
                        best_cost = cost
                        for f in range(nf):
                            best[f] = us[f]
                num = np.float32(0.0)
                conf = np.uint8(0)
                for f in range(nf):
                    num += wt[f] * best[f]
                    for g in range(f + 1, nf):
                        if abs(best[f] - best[g]) > spacing[f, g]:
                            conf = np.uint8(1)
                d = num / wsum
                d = d - np.floor(d * c[9]) * c[8]
                out_d[p] = min(d, c[8])
                out_conf[p] = conf


def fused_supported(taps: np.ndarray, theta_rad: np.ndarray) -> bool:
    """Float32 taps ``[F, K, H, W]``: any K >= 3 equally spaced phases, one to three frequencies."""
    from tofhil.demod import estimator_weights

    if taps.ndim != 4 or taps.shape[1] < 3 or taps.shape[0] not in (1, 2, 3) or taps.dtype != np.float32:
        return False
    try:
        estimator_weights(theta_rad)
    except ValueError:
        return False
    return len(np.atleast_1d(theta_rad)) == taps.shape[1]


def fused_depth(taps: np.ndarray, theta_rad: np.ndarray, freq_hz: np.ndarray, margin: float,
                limits: TapLimits | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """``(distance, amplitude mean, intensity mean, conflict, unambiguous range, bad taps)``
    for float32 taps ``[F, K, H, W]`` with F = 1, 2 or 3; ``bad taps`` is
    :func:`tofhil.demod.bad_tap_pixels` of ``taps`` and ``limits``."""
    from tofhil.demod import estimator_weights
    from tofhil.unwrap import _ext_gcd, frequency_plan

    nf, k, h, wd = taps.shape
    wts = estimator_weights(theta_rad)   # w_{k+K/2} = -w_k for equally spaced taps
    wr = np.ascontiguousarray(wts.real, dtype=np.float32)
    wi = np.ascontiguousarray(wts.imag, dtype=np.float32)
    flat = np.ascontiguousarray(taps).reshape(nf, k, h * wd)
    lo, hi = (limits or TapLimits()).bounds(np.float32)
    plan = frequency_plan(freq_hz)
    if len(plan.freq_hz) != nf:
        raise ValueError(f"taps have {nf} frequencies, freq_hz has {len(plan.freq_hz)}")
    rng = plan.unambiguous_range_m
    two_pi = 2 * np.pi
    c = np.zeros(14, np.float32)
    c[8], c[9], c[11] = rng, 1.0 / rng, 1.0 / (nf * k)
    r = np.array([plan.wrap_range_m(i) for i in range(nf)], np.float32)
    fw = np.array([(f / plan.freq_hz[0]) ** 2 for f in plan.freq_hz], np.float32)
    spacing = np.zeros((3, 3), np.float32)
    if nf == 2:
        m1, m2 = plan.multiples
        a, b = _ext_gcd(m1, m2)
        r1, r2 = plan.wrap_range_m(0), plan.wrap_range_m(1)
        c[:8] = [m2 / two_pi, m1 / two_pi, r1 / two_pi, -b * r1, r2 / two_pi, a * r2, m1 * m1, m2 * m2]
        c[10] = margin / 2
    elif nf == 3:
        ref = int(np.argmin(plan.multiples))
        c[12], c[13] = ref, plan.multiples[ref]
        for i in range(nf):
            for j in range(i + 1, nf):
                spacing[i, j] = margin * plan.decision_spacing_m(i, j)
    distance = np.empty(h * wd, np.float32)
    amplitude = np.empty(h * wd, np.float32)
    intensity = np.empty(h * wd, np.float32)
    conflict = np.empty(h * wd, np.uint8)
    bad = np.empty(h * wd, np.uint8)
    _fused(flat, wr, wi, lo, hi, c, r, fw, spacing, distance, amplitude, intensity, conflict, bad)
    return (distance.reshape(h, wd), amplitude.reshape(h, wd), intensity.reshape(h, wd),
            conflict.view(bool).reshape(h, wd), rng, bad.view(bool).reshape(h, wd))
