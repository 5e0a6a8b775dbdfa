"""Smooth fields over the sensor that no physical effect of the library has the shape of: a gain
of the emitter's light and an unmodulated offset, each a low-order polynomial over the frame.

They are the generic forms of the amplitude and offset channels (issue 32, item 2). A physical
cause with a shape of its own (a radial beam, a reflector, the lens's veil) explains its part
with fewer parameters and is preferred; a field that none of them has (a linear illumination
gradient, a warm corner of the sensor, a vignetting the lens model lacks) would otherwise be
read as the nearest physical cause. Both fields are linear in their coefficients, so the
signature's score test is exact for them.

The basis is the tensor product of Legendre polynomials of order 0-2 in x and in y, x and y
from -1 at the first column (row) to +1 at the last: ``P_i(x) P_j(y)`` with ``P_0 = 1, P_1 = t,
P_2 = (3t^2 - 1)/2``, nine terms (nearly orthogonal on a full frame, so each coefficient reads
about its own part of the field). A product basis, not a total degree: a field that rises
toward one corner (``(1 + x)^2 (1 + y)^2``) is in it, as a vignetting of a rectangular sensor
is. The parameter names group the terms by total order (``mean``, ``linear``, ``quad``,
``cubic``, ``quartic``): diagnosis can leave an order out where the data cannot tell it from the
rest of the model.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from tofhil.sim.effects.base import Effect, EffectContext, Param
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal

#: The basis terms ``P_i(x) P_j(y)``, in the order of the parameters' suffixes, with ``(i, j)``.
TERMS = {"mean": (0, 0), "linear_x": (1, 0), "linear_y": (0, 1), "quad_xx": (2, 0), "quad_xy": (1, 1),
         "quad_yy": (0, 2), "cubic_xxy": (2, 1), "cubic_xyy": (1, 2), "quartic_xxyy": (2, 2)}


def legendre(order: int, t: np.ndarray) -> np.ndarray:
    """The Legendre polynomial of ``order`` 0, 1 or 2 at ``t``."""
    return np.ones_like(t) if order == 0 else t if order == 1 else 1.5 * t * t - 0.5


def basis(ctx: EffectContext, signal_shape: tuple[int, int]) -> np.ndarray:
    """The nine basis fields ``[9, ...]`` at the pixels the signal holds (the frame's, or
    ``ctx.pixels``), in the order of :data:`TERMS`."""
    h, w = ctx.frame_shape(signal_shape)
    v, u = ctx.pixel_grid(signal_shape)
    x = 2.0 * u / max(w - 1, 1) - 1.0
    y = 2.0 * v / max(h - 1, 1) - 1.0
    return np.stack([legendre(i, x) * legendre(j, y) for i, j in TERMS.values()])


def field(values: Mapping[str, Any], ctx: EffectContext, signal_shape: tuple[int, int], suffix: str = "") -> np.ndarray:
    """The polynomial ``sum_k c_k B_k`` with ``c_k = values[term + suffix]``."""
    c = np.array([float(values.get(t + suffix, 0.0)) for t in TERMS])  # (the dict's keys, in order)
    return np.tensordot(c, basis(ctx, signal_shape), axes=1)


@register
class GainFieldEffect(Effect):
    name = "gain_field"
    calibrates = "amplitude"
    stage = "signal"
    rank = 65
    summary = ("smooth gain of the emitter's light over the sensor the scene lacks: times "
               "`1 + sum c_ij P_i(x) P_j(y)`, Legendre polynomials of order 0-2 in x and y (in [-1, 1] over the "
               "frame; 9 terms, `mean`, `linear_x`, ..., `quartic_xxyy`)")
    doc = ("A gain of the emitter's light (modulated and unmodulated, not ambient) that varies smoothly over "
           "the sensor with no shape of a physical effect: an illumination profile that is not radial (a tilted "
           "or offset emitter, a diffuser's gradient), a vignetting or pixel responsivity the lens and sensor "
           "models lack. The light on each pixel times 1 + sum_ij c_ij P_i(x) P_j(y), a product of Legendre "
           "polynomials of order 0-2 in the pixel's position (x, y from -1 at the first column/row to +1 at "
           "the last; P_0 = 1, P_1 = t, P_2 = (3t^2 - 1)/2; nine terms), clipped at 0. Changes the "
           "amplitude, not the phase; acts before the lens's stray light. The generic form of the amplitude "
           "channel: a physical cause that explains as well with fewer parameters (reflectance for a uniform "
           "gain, illumination for a radial one) is preferred.")
    params = {
        "mean": Param(0.0, -1.0, 20.0, "", "gain change over the whole frame (a relative factor - 1)",
                      fit=(-0.9, 5.0), step=0.01),
        **{t: Param(0.0, -5.0, 5.0, "", f"relative gain per unit of the {t.replace('_', ' ')} term",
                    default=0.1 if t == "linear_x" else None, fit=(-2.0, 2.0), step=0.01) for t in list(TERMS)[1:]},
    }

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        g = np.maximum(1.0 + field(values, ctx, signal.shape), 0.0)
        out = signal.copy()
        out.phasor_w = signal.phasor_w * g
        out.dc_w = np.asarray(signal.dc_w) * g
        return out


@register
class OffsetFieldEffect(Effect):
    name = "offset_field"
    calibrates = "offset"
    stage = "signal"
    rank = 82
    offset_only = True
    summary = ("unmodulated charge varying smoothly over the sensor: `sum c_ij P_i(x) P_j(y)` electrons per "
               "tap, the basis of `gain_field` (9 terms, `mean_e`, ..., `quartic_xxyy_e`), the total unmodulated "
               "light kept >= 0")
    doc = ("Unmodulated charge the scene does not explain that varies smoothly over the sensor: a dark "
           "current with a warm corner, emitter leakage or a glowing cover lit from one side, a black level "
           "with a gradient. Every tap of a pixel gains sum_ij c_ij P_i(x) P_j(y) electrons, the product "
           "Legendre basis of gain_field (order 0-2 in x and y), the pixel's total unmodulated light kept "
           ">= 0. Raises the tap offset and the shot noise, not the phase. The generic form of the offset "
           "channel: offset (uniform) and ambient (following the scene's reflectance) are preferred where "
           "they explain as well with fewer parameters.")
    params = {t + "_e": Param(0.0, -1.0e6, 1.0e6, "e-", f"electrons per tap of the {t.replace('_', ' ')} term",
                              default={"mean": 200.0, "linear_x": 100.0}.get(t), fit=(-2.0e5, 2.0e5), step=50.0)
              for t in TERMS}

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        if ctx.sensor is None:
            raise ValueError("offset_field needs the sensor configuration (electrons per watt)")
        e_w = ctx.sensor.tap_fraction * ctx.sensor.electrons_per_watt
        out = signal.copy()
        out.ambient_w = np.maximum(np.asarray(signal.ambient_w) + field(values, ctx, signal.shape, "_e") / e_w, 0.0)
        return out
