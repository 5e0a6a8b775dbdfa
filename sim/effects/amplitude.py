"""Range error depending on the signal strength: an exponential in the modulation amplitude,
and as a flexible form a monotone spline in its logarithm (:func:`monotone_spline`)."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from tofhil.sim.effects.base import Effect, EffectContext, Param, _rotate_phase
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal

#: Knots of the amplitude-dependent spline, log10 of the modulation amplitude in electrons per tap.
AMPLITUDE_KNOTS_LOG10_E = (2.0, 2.75, 3.5, 4.25, 5.0)
_SPLINE = ("spline",)


def stick_breaking(q: np.ndarray) -> np.ndarray:
    """Fractions ``w_1..w_m >= 0`` summing to 1 from ``m - 1`` numbers in [0, 1]: ``w_j = q_j
    prod_{i<j} (1 - q_i)``, the last takes what is left. ``q_j = 1 / (m - j + 1)`` gives equal parts."""
    rest = np.concatenate([[1.0], np.cumprod(1.0 - q)])
    return np.concatenate([q, [1.0]]) * rest


def monotone_spline(x: np.ndarray, knots: np.ndarray, level: float, span: float, q: np.ndarray) -> np.ndarray:
    """Piecewise linear in ``x`` through the knots, ``level`` at and below the first knot,
    ``level + span`` at and above the last, the rise between knots ``span * w_j`` with ``w`` from
    :func:`stick_breaking`: monotone (in the sign of ``span``) for every parameter value."""
    steps = span * stick_breaking(np.asarray(q, dtype=np.float64))
    values = level + np.concatenate([[0.0], np.cumsum(steps)])
    return np.interp(x, knots, values)


@register
class AmplitudeDependentEffect(Effect):
    name = "amplitude_dependent"
    stage = "signal"
    rank = 130
    summary = ('radial error as a function of A, the modulation amplitude per tap in electrons: '
               '`error_m * exp(-A / amplitude_e)` plus, as the flexible form `spline`, a monotone piecewise-linear '
               'function of log10 A (knots at 10^2 ... 10^5 e-)')
    doc = ("Range error that depends on the signal strength (pixel nonlinearity and charge-transfer "
           "lag at low signal): radial error = error_m * exp(-A / amplitude_e) + s(log10 A), with A the "
           "pixel's modulation amplitude in electrons per tap at that frequency (needs the sensor block). "
           "s is monotone by construction: piecewise linear through knots at log10 A = "
           + ", ".join(f"{k:g}" for k in AMPLITUDE_KNOTS_LOG10_E) + ", spline_level_m at and below the "
           "first, rising (or falling) by spline_span_m to the last, the share of each interval from the "
           "stick-breaking fractions spline_q1..q3 (their off values give equal shares: an error linear in "
           "log A). Diagnosis fits the exponential (simple form) or the spline (form `spline`).")
    forms = {"spline": "monotone piecewise-linear error in log10 amplitude (level, span, 3 shape fractions)"}
    params = {
        "error_m": Param(0.0, -0.5, 0.5, "m", "radial error at zero amplitude", default=0.01, fit=(-0.5, 0.5),
                         step=0.01, start=0.02, starts=(-0.02,)),
        "amplitude_e": Param(1000.0, 1.0, 1.0e6, "e-", "amplitude scale A0 over which the error decays",
                             fit=(0.0, 6.0), step=0.2, log=True, start=1000.0,
                             starts=(10.0 ** 2.5, 10.0 ** 3.5)),
        "spline_level_m": Param(0.0, -0.5, 0.5, "m", "spline: radial error at and below the first knot",
                                fit=(-0.3, 0.3), step=0.005, start=-0.02, starts=(0.02,), forms=_SPLINE),
        "spline_span_m": Param(0.0, -0.5, 0.5, "m", "spline: error at the last knot minus at the first",
                               fit=(-0.3, 0.3), step=0.005, start=0.03, starts=(-0.03,), forms=_SPLINE),
        "spline_q1": Param(0.25, 0.0, 1.0, "", "spline: share of the span in the 1st interval",
                           fit=(0.0, 1.0), step=0.05, forms=_SPLINE),
        "spline_q2": Param(1.0 / 3.0, 0.0, 1.0, "", "spline: share of the rest in the 2nd interval",
                           fit=(0.0, 1.0), step=0.05, forms=_SPLINE),
        "spline_q3": Param(0.5, 0.0, 1.0, "", "spline: share of the rest in the 3rd interval (the 4th takes the rest)",
                           fit=(0.0, 1.0), step=0.05, forms=_SPLINE),
    }

    def is_off(self, values: Mapping[str, Any]) -> bool:
        return float(values.get("error_m", 0.0)) == 0.0 and float(values.get("spline_level_m", 0.0)) == 0.0 \
            and float(values.get("spline_span_m", 0.0)) == 0.0

    def roughness(self, form: str, values: Mapping[str, Any]) -> np.ndarray | None:
        # a smoothness prior: the second differences of the spline's values at its knots, in
        # units of 5 mm; an error linear in log A (any level and span) costs nothing
        if form != "spline":
            return None
        p = self.params
        q = np.array([float(values.get(f"spline_q{j}", p[f"spline_q{j}"].off)) for j in (1, 2, 3)])
        knots = np.asarray(AMPLITUDE_KNOTS_LOG10_E)
        at_knots = monotone_spline(knots, knots, float(values.get("spline_level_m", 0.0)),
                                   float(values.get("spline_span_m", 0.0)), q)
        return np.diff(at_knots, 2) / 0.005

    @staticmethod
    def error_m(values: Mapping[str, Any], amp_e: np.ndarray) -> np.ndarray:
        """The radial error at modulation amplitude ``amp_e`` (electrons per tap)."""
        p = AmplitudeDependentEffect.params
        err = float(values.get("error_m", 0.0)) * np.exp(-amp_e / float(values.get("amplitude_e", 1000.0)))
        level, span = float(values.get("spline_level_m", 0.0)), float(values.get("spline_span_m", 0.0))
        if level or span:
            q = np.array([float(values.get(f"spline_q{j}", p[f"spline_q{j}"].off)) for j in (1, 2, 3)])
            x = np.log10(np.maximum(amp_e, 1e-3))
            err = err + monotone_spline(x, np.asarray(AMPLITUDE_KNOTS_LOG10_E), level, span, q)
        return err

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        if ctx.sensor is None:
            raise ValueError("amplitude_dependent needs the sensor configuration (electrons per watt)")
        s = ctx.sensor
        amp_e = (s.tap_fraction * s.modulation_contrast * s.electrons_per_watt
                 * np.abs(signal.phasor_w[:, signal.harmonics.index(1)]))  # [F, H, W]
        return _rotate_phase(signal, 2.0 * self.error_m(values, amp_e))  # radial error -> optical path
