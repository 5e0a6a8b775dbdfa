"""Multi-frequency phase unwrapping.

With modulation frequencies ``f_i = M_i * g`` (``M_i`` coprime integers, ``g`` their
greatest common divisor) the combined unambiguous range is ``R = c / (2 g)``; 80 + 100 MHz
gives g = 20 MHz, R = 7.49 m. Each frequency measures ``d mod R_i`` with ``R_i = R / M_i``.

Two frequencies use the Chinese-remainder form: ``M_2 phi_1 - M_1 phi_2 = 2 pi (M_1 n_2 -
M_2 n_1)``, so one rounding per pixel gives both wrap counts (Jongenelen et al. 2010).
Three or more use a candidate search over the wrap counts of the lowest frequency,
choosing the candidate whose unwrapped distances agree best (weighted variance).

Either way the result is the inverse-variance weighted mean of the unwrapped distances
(weights ``(f_i A_i)^2``: phase noise is ~1/A, distance noise ~1/(f A)), and each pixel is
flagged where two frequencies disagree by more than ``margin`` of the spacing at which a
wrong wrap count would be chosen.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache
from math import gcd

import numpy as np

from tofhil import C_M_PER_S


@dataclass(frozen=True)
class FrequencyPlan:
    freq_hz: tuple[float, ...]
    multiples: tuple[int, ...]
    base_hz: float

    @property
    def unambiguous_range_m(self) -> float:
        return C_M_PER_S / (2.0 * self.base_hz)

    def wrap_range_m(self, i: int) -> float:
        return C_M_PER_S / (2.0 * self.freq_hz[i])

    def decision_spacing_m(self, i: int, j: int) -> float:
        """Disagreement between frequencies i and j at which unwrapping picks a wrong count."""
        return self.unambiguous_range_m / (2.0 * self.multiples[i] * self.multiples[j])


def frequency_plan(freq_hz: np.ndarray | list[float], max_multiple: int = 1000) -> FrequencyPlan:
    """Integer multiples ``M_i`` and the common base frequency of a set of frequencies."""
    return _frequency_plan(tuple(float(x) for x in np.atleast_1d(freq_hz)), max_multiple)


@lru_cache(maxsize=64)
def _frequency_plan(f: tuple[float, ...], max_multiple: int) -> FrequencyPlan:
    if any(x <= 0 for x in f):
        raise ValueError(f"frequencies must be positive, got {f}")
    ratios = [Fraction(x / f[0]).limit_denominator(max_multiple) for x in f]
    den = 1
    for r in ratios:
        den = den * r.denominator // gcd(den, r.denominator)
    mult = [int(r * den) for r in ratios]
    g = 0
    for m in mult:
        g = gcd(g, m)
    mult = [m // g for m in mult]
    base = f[0] / mult[0]
    for x, m in zip(f, mult):
        if abs(x - m * base) > 1e-6 * x:
            raise ValueError(f"frequencies {f} have no common base frequency with multiples <= {max_multiple}")
    return FrequencyPlan(tuple(f), tuple(mult), base)


@dataclass
class UnwrapResult:
    distance_m: np.ndarray  # radial distance in [0, R)
    conflict: np.ndarray  # bool: frequencies disagree
    disagreement_m: np.ndarray  # largest pairwise disagreement after unwrapping
    unambiguous_range_m: float


def ext_gcd(a: int, b: int) -> tuple[int, int]:
    """x, y with a*x + b*y = 1 for coprime a, b."""
    old_r, r, old_s, s, old_t, t = a, b, 1, 0, 0, 1
    while r:
        q = old_r // r
        old_r, r = r, old_r - q * r
        old_s, s = s, old_s - q * s
        old_t, t = t, old_t - q * t
    return old_s, old_t


def unwrap(phase_rad: np.ndarray, freq_hz: np.ndarray | list[float],
           amplitude: np.ndarray | None = None, margin: float = 0.5) -> UnwrapResult:
    """Unwrap wrapped phases ``[F, H, W]`` (each in [0, 2 pi)) into one radial distance.

    ``margin`` (0..1) sets the conflict flag: a pixel is flagged where two frequencies'
    unwrapped distances differ by more than ``margin`` times their decision spacing (the
    disagreement at which a wrong wrap count would be chosen).
    """
    phase = np.asarray(phase_rad)
    dtype = np.float32 if phase.dtype == np.float32 else np.float64
    plan = frequency_plan(freq_hz)
    nf = len(plan.freq_hz)
    if phase.shape[0] != nf:
        raise ValueError(f"phase has {phase.shape[0]} frequencies, freq_hz has {nf}")
    rng = plan.unambiguous_range_m
    if nf == 2:
        return _unwrap_two(phase, plan, amplitude, margin, dtype)
    wrapped = [phase[i].astype(dtype, copy=False) * dtype(plan.wrap_range_m(i) / (2 * np.pi)) for i in range(nf)]
    if nf == 1:
        d = wrapped[0]
        zero = np.zeros(d.shape, dtype=dtype)
        return UnwrapResult(d, np.zeros(d.shape, bool), zero, rng)

    unwrapped = _search(wrapped, plan, amplitude, dtype)

    weights = _weights(plan, amplitude, dtype, phase.shape[1:])
    num = sum(w * u for w, u in zip(weights, unwrapped))
    den = sum(weights)
    d = _wrap_into(num / den, rng, dtype)
    worst = np.zeros(phase.shape[1:], dtype=dtype)
    conflict = np.zeros(phase.shape[1:], dtype=bool)
    for i in range(nf):
        for j in range(i + 1, nf):
            dis = np.abs(unwrapped[i] - unwrapped[j])
            np.maximum(worst, dis, out=worst)
            conflict |= dis > dtype(margin * plan.decision_spacing_m(i, j))
    return UnwrapResult(d.astype(dtype, copy=False), conflict, worst, rng)


def _wrap_into(x: np.ndarray, period: float, dtype) -> np.ndarray:
    """``x mod period`` in place (np.mod is ~50x slower than floor for float32)."""
    x -= np.floor(x * dtype(1 / period)) * dtype(period)
    np.copyto(x, 0, where=x >= dtype(period))  # float32 rounding can land exactly on the period
    return x


def _unwrap_two(phase: np.ndarray, plan: FrequencyPlan, amplitude: np.ndarray | None, margin: float,
                dtype) -> UnwrapResult:
    """Chinese-remainder unwrapping of two frequencies, in as few array passes as possible."""
    m1, m2 = plan.multiples
    rng = plan.unambiguous_range_m
    r1, r2 = plan.wrap_range_m(0), plan.wrap_range_m(1)
    inv_two_pi = dtype(1 / (2 * np.pi))
    x = phase[0] * dtype(m2 * inv_two_pi)
    x -= phase[1] * dtype(m1 * inv_two_pi)  # = m1*n2 - m2*n1 + residual
    e = np.rint(x)
    x -= e  # residual in cycles; |x| = 0.5 is the decision boundary
    a, b = ext_gcd(m1, m2)  # m1*a + m2*b = 1  ->  n2 = e*a, n1 = -e*b
    u1 = phase[0] * dtype(r1 * inv_two_pi)
    u1 += e * dtype(-b * r1)
    u2 = phase[1] * dtype(r2 * inv_two_pi)
    u2 += e * dtype(a * r2)
    # weighted mean u1 + (u2 - u1) * w2 / (w1 + w2), weights (f A)^2
    if amplitude is None:
        frac = dtype(m2 * m2 / (m1 * m1 + m2 * m2))
    else:
        w1 = np.square(amplitude[0], dtype=dtype) * dtype(m1 * m1)
        w2 = np.square(amplitude[1], dtype=dtype) * dtype(m2 * m2)
        w1 += w2
        w1 += dtype(1e-30)
        frac = np.divide(w2, w1, out=w2)
    u2 -= u1
    u2 *= frac
    u1 += u2
    d = _wrap_into(u1, rng, dtype)
    resid = np.abs(x, out=x)
    conflict = resid > dtype(margin / 2)
    disagreement = np.multiply(resid, dtype(rng / (m1 * m2)), out=resid)
    return UnwrapResult(d, conflict, disagreement, rng)


def _weights(plan: FrequencyPlan, amplitude: np.ndarray | None, dtype, shape) -> list:
    w = []
    for i, f in enumerate(plan.freq_hz):
        fi = dtype(f / plan.freq_hz[0])
        if amplitude is None:
            w.append(fi * fi)
        else:
            a = np.asarray(amplitude[i], dtype=dtype)
            w.append((fi * a) ** 2 + dtype(1e-30))
    return w


def _search(wrapped: list[np.ndarray], plan: FrequencyPlan, amplitude, dtype) -> list[np.ndarray]:
    """Wrap counts for F >= 3 by trying every count of the lowest frequency."""
    nf = len(wrapped)
    ref = int(np.argmin(plan.multiples))
    weights = _weights(plan, amplitude, dtype, wrapped[0].shape)
    wsum = sum(weights)
    best_cost = None
    best: list[np.ndarray] | None = None
    for n in range(plan.multiples[ref]):
        cand = wrapped[ref] + dtype(n * plan.wrap_range_m(ref))
        us = []
        for j in range(nf):
            rj = dtype(plan.wrap_range_m(j))
            us.append(wrapped[j] + np.rint((cand - wrapped[j]) / rj) * rj)
        mean = sum(w * u for w, u in zip(weights, us)) / wsum
        cost = sum(w * (u - mean) ** 2 for w, u in zip(weights, us))
        if best_cost is None:
            best_cost, best = cost, us
        else:
            better = cost < best_cost
            best_cost = np.where(better, cost, best_cost)
            best = [np.where(better, u, b) for u, b in zip(us, best)]
    assert best is not None
    return best
