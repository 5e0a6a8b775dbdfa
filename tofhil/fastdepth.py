"""Fused demodulation + unwrapping: any K >= 3 equally spaced taps, one to three frequencies.

One pass over the taps, block of pixels by block, computes every frequency's complex signal
from the taps (their differences for even K), its amplitude and phase, the offset, and the
unwrapping of :mod:`tofhil.unwrap` (two frequencies: Chinese remainder; three: the search
over the lowest frequency's wrap counts), so the intermediate images never leave the CPU
cache. The phase uses a branch-free arctangent polynomial (|error| < 1e-7 rad, about float32
rounding) that the compiler vectorises; the results agree with the numpy path of
:func:`tofhil.depth.depth_from_raw` to that level (tested). The same pass flags pixels with a
saturated or non-finite tap (:func:`tofhil.demod.bad_tap_pixels`), so the kernels are
compiled without the no-NaN/no-inf fast-math assumptions (a NaN tap must be seen as one),
and with numpy's error model: numba's default checks every float division for a zero divisor
(a branch that raises), and that branch alone kept each pixel loop with a division scalar.
One frequency with K = 3 or 4 (nothing to unwrap) takes a single loop that writes every output
from registers (:func:`_fused_one`), the same numbers.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numba import njit

from tofhil.demod import TapLimits

_PI = np.float32(math.pi)
_HALF_PI = np.float32(math.pi / 2)
_TWO_PI = np.float32(2 * math.pi)
#: Fast-math without ``nnan``/``ninf``: NaN and inf taps must compare as such.
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(inline="always", fastmath=_FASTMATH, error_model="numpy")
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


@njit(inline="always", fastmath=_FASTMATH, error_model="numpy")
def _iq4(x0, x1, x2, x3, w0r, w1r, w0i, w1i, lo, hi):  # pragma: no cover
    """Four taps -> I, Q, their sum and whether every tap is inside (lo, hi): the arithmetic
    :func:`_fused` and :func:`_fused_one` share (I/Q from the differences c_j - c_{j+2})."""
    d0 = x0 - x2
    d1 = x1 - x3
    ok = ((x0 > lo) & (x0 < hi) & (x1 > lo) & (x1 < hi)
          & (x2 > lo) & (x2 < hi) & (x3 > lo) & (x3 < hi))
    return w0r * d0 + w1r * d1, w0i * d0 + w1i * d1, x0 + x1 + x2 + x3, ok


@njit(inline="always", fastmath=_FASTMATH, error_model="numpy")
def _iq3(x0, x1, x2, w0r, w1r, w2r, w0i, w1i, w2i, lo, hi):  # pragma: no cover
    """Three taps (odd K: no differences) -> I, Q, their sum and whether every tap is inside (lo, hi)."""
    ok = (x0 > lo) & (x0 < hi) & (x1 > lo) & (x1 < hi) & (x2 > lo) & (x2 < hi)
    return w0r * x0 + w1r * x1 + w2r * x2, w0i * x0 + w1i * x1 + w2i * x2, x0 + x1 + x2, ok


@njit(fastmath=_FASTMATH, error_model="numpy", cache=True)
def _fused(taps, wr, wi, lo, hi, c, r, fw, spacing, out_d, out_amp, out_int, out_conf, out_valid):  # pragma: no cover
    """taps [F, K, N] float32 -> distance, mean amplitude, mean tap (intensity), conflict
    (uint8) and validity (uint8: no conflict, no bad tap -- a tap not inside the open
    interval (lo, hi) -- and a finite distance and amplitude), in one pass. (The bad-tap
    map itself is not written: it only enters the validity, and every output byte written
    is memory traffic of the same order as the taps read.)

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
    ph = np.empty((nf, _BLOCK), np.float32)
    am = np.empty((nf, _BLOCK), np.float32)
    S = np.empty(_BLOCK, np.float32)
    G = np.empty(_BLOCK, np.uint8)
    inv_two_pi = np.float32(1.0 / (2.0 * math.pi))
    for b0 in range(0, n, _BLOCK):
        m = min(_BLOCK, n - b0)
        S[:m] = 0.0
        G[:m] = 1
        for f in range(nf):
            fp = ph[f]
            fa = am[f]
            if k == 4:
                # The common case in one loop per pixel: I, Q, amplitude and phase from the
                # four taps while they are in registers.
                t0 = taps[f, 0, b0:b0 + m]
                t1 = taps[f, 1, b0:b0 + m]
                t2 = taps[f, 2, b0:b0 + m]
                t3 = taps[f, 3, b0:b0 + m]
                w0r, w1r, w0i, w1i = wr[0], wr[1], wi[0], wi[1]
                for j in range(m):
                    i_, q_, s4, ok = _iq4(t0[j], t1[j], t2[j], t3[j], w0r, w1r, w0i, w1i, lo, hi)
                    fa[j] = math.sqrt(i_ * i_ + q_ * q_)
                    fp[j] = _phase(q_, i_)
                    S[j] += s4
                    G[j] &= np.uint8(1) if ok else np.uint8(0)
                continue
            if k == 3:
                # Three taps (odd K: no differences) likewise in one loop per pixel.
                t0 = taps[f, 0, b0:b0 + m]
                t1 = taps[f, 1, b0:b0 + m]
                t2 = taps[f, 2, b0:b0 + m]
                w0r, w1r, w2r, w0i, w1i, w2i = wr[0], wr[1], wr[2], wi[0], wi[1], wi[2]
                for j in range(m):
                    i_, q_, s3, ok = _iq3(t0[j], t1[j], t2[j], w0r, w1r, w2r, w0i, w1i, w2i, lo, hi)
                    fa[j] = math.sqrt(i_ * i_ + q_ * q_)
                    fp[j] = _phase(q_, i_)
                    S[j] += s3
                    G[j] &= np.uint8(1) if ok else np.uint8(0)
                continue
            fi = bi[f]
            fq = bq[f]
            fi[:m] = 0.0
            fq[:m] = 0.0
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
                        fi[j] += a_r * dd
                        fq[j] += a_i * dd
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
                        fi[j] += a_r * x
                        fq[j] += a_i * x
                        S[j] += x
                        ok = (x > lo) & (x < hi)
                        G[j] &= np.uint8(1) if ok else np.uint8(0)
            for j in range(m):
                i_ = fi[j]
                q_ = fq[j]
                fa[j] = math.sqrt(i_ * i_ + q_ * q_)
                fp[j] = _phase(q_, i_)
        o_int = out_int[b0:b0 + m]
        o_d = out_d[b0:b0 + m]
        o_amp = out_amp[b0:b0 + m]
        o_conf = out_conf[b0:b0 + m]
        inv_n = c[11]
        for j in range(m):
            o_int[j] = S[j] * inv_n
        if nf == 1:
            scale = r[0] * inv_two_pi
            p0 = ph[0]
            a0 = am[0]
            for j in range(m):
                o_d[j] = p0[j] * scale
                o_conf[j] = np.uint8(0)
                o_amp[j] = a0[j]
        elif nf == 2:
            p0, p1, a0, a1 = ph[0], ph[1], am[0], am[1]
            half_ = np.float32(0.5)
            # The constants in registers: read from ``c`` inside the loop they would have to
            # be reloaded after every store (the compiler cannot rule out that an output
            # aliases ``c``), which keeps the loop from vectorising.
            c0, c1, c2, c3, c4, c5, c6, c7 = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
            rng_, inv_rng, half_margin = c[8], c[9], c[10]
            for j in range(m):
                x = p0[j] * c0 - p1[j] * c1
                e = np.floor(x + half_)
                resid = abs(x - e)
                u1 = p0[j] * c2 + e * c3
                u2 = p1[j] * c4 + e * c5
                w1 = c6 * a0[j] * a0[j]
                w2 = c7 * a1[j] * a1[j]
                d = u1 + (u2 - u1) * (w2 / (w1 + w2 + np.float32(1e-30)))
                d = d - np.floor(d * inv_rng) * rng_
                o_d[j] = min(d, rng_)
                o_conf[j] = np.uint8(1) if resid > half_margin else np.uint8(0)
                o_amp[j] = half_ * (a0[j] + a1[j])
        else:
            _search3(ph, am, m, c, r, fw, spacing, o_d, o_amp, o_conf)
        o_val = out_valid[b0:b0 + m]
        for j in range(m):
            # As tofhil.depth._depth_frame: no conflict, no bad tap, finite distance and amplitude.
            fin = np.isfinite(o_d[j]) & np.isfinite(o_amp[j])
            o_val[j] = np.uint8(1) if (fin & (o_conf[j] == 0) & (G[j] == 1)) else np.uint8(0)


@njit(fastmath=_FASTMATH, error_model="numpy", cache=True)
def _fused_one(taps, wr, wi, lo, hi, scale, inv_n, out_d, out_amp, out_int, out_valid):  # pragma: no cover
    """One frequency, K = 3 or 4: :func:`_fused`'s arithmetic (the same numbers) in ONE loop
    over the pixels that writes every output straight from registers. The block buffers of
    :func:`_fused` (phase, amplitude, tap sum, validity written, then read back by three more
    loops) cost more than the arithmetic when there is nothing to unwrap: 2.9x -> 1.9x one
    pass over the taps for 640 x 480 x 3 taps. No conflict output: one frequency has none."""
    k = taps.shape[1]
    n = taps.shape[2]
    # The two loops differ only in the I/Q kernel: written out twice on purpose, because a
    # shared store function (inlined by numba) stops the loop vectorising: 0.51 -> 3.9 ms per
    # 640 x 480 x 4-tap frame, measured when it was tried.
    if k == 4:
        t0, t1, t2, t3 = taps[0, 0], taps[0, 1], taps[0, 2], taps[0, 3]
        w0r, w1r, w0i, w1i = wr[0], wr[1], wi[0], wi[1]
        for j in range(n):
            i_, q_, s, ok = _iq4(t0[j], t1[j], t2[j], t3[j], w0r, w1r, w0i, w1i, lo, hi)
            a = math.sqrt(i_ * i_ + q_ * q_)
            d = _phase(q_, i_) * scale
            out_int[j] = s * inv_n
            out_d[j] = d
            out_amp[j] = a
            fin = np.isfinite(d) & np.isfinite(a)
            out_valid[j] = np.uint8(1) if (ok & fin) else np.uint8(0)
    else:
        t0, t1, t2 = taps[0, 0], taps[0, 1], taps[0, 2]
        w0r, w1r, w2r, w0i, w1i, w2i = wr[0], wr[1], wr[2], wi[0], wi[1], wi[2]
        for j in range(n):
            i_, q_, s, ok = _iq3(t0[j], t1[j], t2[j], w0r, w1r, w2r, w0i, w1i, w2i, lo, hi)
            a = math.sqrt(i_ * i_ + q_ * q_)
            d = _phase(q_, i_) * scale
            out_int[j] = s * inv_n
            out_d[j] = d
            out_amp[j] = a
            fin = np.isfinite(d) & np.isfinite(a)
            out_valid[j] = np.uint8(1) if (ok & fin) else np.uint8(0)


#: Most wrap counts of the reference frequency the vectorised three-frequency search unrolls
#: (80/100/120 MHz: 4); plans with more take the same search with a runtime trip count.
_UNROLL3 = 8


@njit(fastmath=_FASTMATH, error_model="numpy", cache=True, inline="always")
def _candidate(cnt, rref, wref, w0, w1, w2, k0, k1, k2, ks, r0, r1, r2, i0, i1, i2):  # pragma: no cover
    """Wrap count ``cnt`` of the reference frequency, the others' counts by rounding: the three
    unwrapped distances and their weighted variance (times the weight sum)."""
    half_ = np.float32(0.5)
    cand = wref + np.float32(cnt) * rref
    u0 = w0 + np.floor((cand - w0) * i0 + half_) * r0
    u1 = w1 + np.floor((cand - w1) * i1 + half_) * r1
    u2 = w2 + np.floor((cand - w2) * i2 + half_) * r2
    mean = (k0 * u0 + k1 * u1 + k2 * u2) * ks
    e0, e1, e2 = u0 - mean, u1 - mean, u2 - mean
    cost = k0 * e0 * e0 + k1 * e1 * e1 + k2 * e2 * e2
    return cost, u0, u1, u2


@njit(fastmath=_FASTMATH, error_model="numpy", cache=True, inline="always")
def _search3(ph, am, m, c, r, fw, spacing, o_d, o_amp, o_conf):  # pragma: no cover
    """Three frequencies: every wrap count of the reference (lowest) frequency, the others'
    counts by rounding; the candidate with the least weighted variance (as
    :func:`tofhil.unwrap._search`; the first of equal ones), then the weighted mean wrapped
    into the range. Up to :data:`_UNROLL3` counts the candidate loop has a constant trip
    count (counts past the plan's cost nothing: they are never taken), so the compiler
    unrolls it and vectorises the pixel loop; the choice between the two trip counts is made
    once, outside the pixel loop (inside it, it kept the loop scalar)."""
    if int(c[13]) <= 4:                     # 80/100/120 MHz: no work on counts past the plan's
        _search3_pixels(ph, am, m, c, r, fw, spacing, o_d, o_amp, o_conf, 4)
    elif int(c[13]) <= _UNROLL3:
        _search3_pixels(ph, am, m, c, r, fw, spacing, o_d, o_amp, o_conf, _UNROLL3)
    else:
        _search3_pixels(ph, am, m, c, r, fw, spacing, o_d, o_amp, o_conf, int(c[13]))


@njit(fastmath=_FASTMATH, error_model="numpy", cache=True, inline="always")
def _search3_pixels(ph, am, m, c, r, fw, spacing, o_d, o_amp, o_conf, trips):  # pragma: no cover
    """The pixel loop of :func:`_search3`, ``trips`` wrap counts per pixel (of which the
    plan's ``c[13]`` are candidates)."""
    inv_two_pi = np.float32(1.0 / (2.0 * math.pi))
    ref = int(c[12])
    ncount = int(c[13])
    r0, r1, r2 = r[0], r[1], r[2]
    i0, i1, i2 = np.float32(1.0) / r0, np.float32(1.0) / r1, np.float32(1.0) / r2
    rref = r0 if ref == 0 else (r1 if ref == 1 else r2)
    # Every constant in a register (see the two-frequency loop), and the fit weights too.
    rng_, inv_rng = c[8], c[9]
    s01, s02, s12 = spacing[0, 1], spacing[0, 2], spacing[1, 2]
    fw0, fw1, fw2 = fw[0], fw[1], fw[2]
    ph0, ph1, ph2, am0, am1, am2 = ph[0], ph[1], ph[2], am[0], am[1], am[2]
    for j in range(m):
        w0 = ph0[j] * (r0 * inv_two_pi)
        w1 = ph1[j] * (r1 * inv_two_pi)
        w2 = ph2[j] * (r2 * inv_two_pi)
        k0 = fw0 * am0[j] * am0[j] + np.float32(1e-30)
        k1 = fw1 * am1[j] * am1[j] + np.float32(1e-30)
        k2 = fw2 * am2[j] * am2[j] + np.float32(1e-30)
        ks = np.float32(1.0) / (k0 + k1 + k2)
        wref = w0 if ref == 0 else (w1 if ref == 1 else w2)
        best, b0, b1, b2 = _candidate(0, rref, wref, w0, w1, w2, k0, k1, k2, ks, r0, r1, r2, i0, i1, i2)
        for cnt in range(1, trips):
            cost, u0, u1, u2 = _candidate(cnt, rref, wref, w0, w1, w2, k0, k1, k2, ks, r0, r1, r2, i0, i1, i2)
            better = (cost < best) & (cnt < ncount)
            best = cost if better else best
            b0 = u0 if better else b0
            b1 = u1 if better else b1
            b2 = u2 if better else b2
        d = (k0 * b0 + k1 * b1 + k2 * b2) * ks
        d = d - np.floor(d * inv_rng) * rng_
        o_d[j] = min(d, rng_)
        conf = (abs(b0 - b1) > s01) | (abs(b0 - b2) > s02) | (abs(b1 - b2) > s12)
        o_conf[j] = np.uint8(1) if conf else np.uint8(0)
        o_amp[j] = (am0[j] + am1[j] + am2[j]) * np.float32(1.0 / 3.0)


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


@lru_cache(maxsize=64)
def _constants(theta: tuple[float, ...], freq_hz: tuple[float, ...], margin: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The kernels' constant arrays for a tap and frequency plan (see :func:`_fused`), made
    once per plan: building them took ~10 % of a 640 x 480 one-frequency frame. Shared by
    every call with the plan: never written. (Not flagged read-only: numba would compile
    the kernels again for read-only array types.)"""
    from tofhil.demod import estimator_weights
    from tofhil.unwrap import ext_gcd, frequency_plan

    k = len(theta)
    wts = estimator_weights(np.array(theta))   # w_{k+K/2} = -w_k for equally spaced taps
    wr = np.ascontiguousarray(wts.real, dtype=np.float32)
    wi = np.ascontiguousarray(wts.imag, dtype=np.float32)
    plan = frequency_plan(freq_hz)
    nf = len(plan.freq_hz)
    rng = plan.unambiguous_range_m
    two_pi = 2 * np.pi
    c = np.zeros(14, np.float32)
    c[8], c[9], c[11] = rng, 1.0 / rng, 1.0 / (nf * k)
    r = np.array([plan.wrap_range_m(i) for i in range(nf)], np.float32)
    fw = np.array([(f / plan.freq_hz[0]) ** 2 for f in plan.freq_hz], np.float32)
    spacing = np.zeros((3, 3), np.float32)
    if nf == 2:
        m1, m2 = plan.multiples
        a, b = ext_gcd(m1, m2)
        r1, r2 = plan.wrap_range_m(0), plan.wrap_range_m(1)
        c[:8] = [m2 / two_pi, m1 / two_pi, r1 / two_pi, -b * r1, r2 / two_pi, a * r2, m1 * m1, m2 * m2]
        c[10] = margin / 2
    elif nf == 3:
        ref = int(np.argmin(plan.multiples))
        c[12], c[13] = ref, plan.multiples[ref]
        for i in range(nf):
            for j in range(i + 1, nf):
                spacing[i, j] = margin * plan.decision_spacing_m(i, j)
    return wr, wi, c, r, fw, spacing, rng


def fused_depth(taps: np.ndarray, theta_rad: np.ndarray, freq_hz: np.ndarray, margin: float,
                limits: TapLimits | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """``(distance, amplitude mean, intensity mean, conflict, unambiguous range, valid)`` for
    float32 taps ``[F, K, H, W]`` with F = 1, 2 or 3; ``valid`` is the validity rule of
    :func:`tofhil.depth.depth_from_raw` before any amplitude threshold (no conflict, no tap
    flagged by :func:`tofhil.demod.bad_tap_pixels` with ``limits``, finite results)."""
    nf, k, h, wd = taps.shape
    flat = np.ascontiguousarray(taps).reshape(nf, k, h * wd)
    lo, hi = (limits or TapLimits()).bounds(np.float32)
    wr, wi, c, r, fw, spacing, rng = _constants(tuple(float(t) for t in np.atleast_1d(theta_rad)),
                                                tuple(float(f) for f in np.atleast_1d(freq_hz)), float(margin))
    if r.size != nf:
        raise ValueError(f"taps have {nf} frequencies, freq_hz has {r.size}")
    distance = np.empty(h * wd, np.float32)
    amplitude = np.empty(h * wd, np.float32)
    intensity = np.empty(h * wd, np.float32)
    valid = np.empty(h * wd, np.uint8)
    if nf == 1 and k in (3, 4):
        conflict = np.zeros(h * wd, np.uint8)
        scale = np.float32(r[0] * np.float32(1.0 / (2.0 * math.pi)))   # as _fused computes it
        _fused_one(flat, wr, wi, lo, hi, scale, c[11], distance, amplitude, intensity, valid)
    else:
        conflict = np.empty(h * wd, np.uint8)
        _fused(flat, wr, wi, lo, hi, c, r, fw, spacing, distance, amplitude, intensity, conflict, valid)
    return (distance.reshape(h, wd), amplitude.reshape(h, wd), intensity.reshape(h, wd),
            conflict.view(bool).reshape(h, wd), rng, valid.view(bool).reshape(h, wd))
