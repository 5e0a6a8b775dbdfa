"""The emitter's illumination profile differing from the scene's beam."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from tofhil.camera import CameraModel
from tofhil.sim.effects.base import Effect, EffectContext, Param
from tofhil.sim.effects.range_errors import FieldAngleEffect
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal


@register
class IlluminationEffect(Effect):
    name = "illumination"
    stage = "signal"
    rank = 60
    summary = ("emitter illumination profile the scene lacks: the emitter light on each pixel times "
               "`cos(alpha)^dn (1 + b4 t^4 + b6 t^6)`, alpha the pixel ray's field angle, t = tan(alpha)")
    doc = ("The emitter's illumination profile differing from the scene's beam (a cos^n beam of "
           "another exponent, a diffuser, an LED array, a cover glass): the emitter's light on each "
           "pixel (modulated and unmodulated, not ambient) times cos(alpha)^dn (1 + b4 t^4 + b6 t^6), "
           "clipped at 0, with alpha the pixel ray's angle to the optical axis and t = tan(alpha) "
           "(emitter next to the lens: a point seen at field angle alpha is lit at about alpha; "
           "indirect light is scaled like the direct light of its pixel). dn changes the exponent of "
           "the scene's cos^n beam (the simple form); b4 and b6 bend the profile further (the flexible "
           "form `radial`; no t^2 term: to first order it is dn). Changes the amplitude only; acts "
           "before the lens's stray light.")
    forms = {"radial": "cos^dn times a radial polynomial 1 + b4 t^4 + b6 t^6"}
    params = {
        "dn": Param(0.0, -20.0, 20.0, "", "change of the beam's cos^n exponent", default=1.0,
                    fit=(-10.0, 10.0), step=0.05, forms=("", "radial")),
        "b4": Param(0.0, -50.0, 50.0, "", "relative change per tan^4 of the field angle",
                    fit=(-20.0, 20.0), step=0.05, forms=("radial",)),
        "b6": Param(0.0, -200.0, 200.0, "", "relative change per tan^6 of the field angle",
                    fit=(-100.0, 100.0), step=0.1, forms=("radial",)),
    }

    def roughness(self, form: str, values: Mapping[str, Any]) -> np.ndarray | None:
        # the radial terms shrink to the simple cos^dn form: a ridge on what each changes at
        # t = 0.5 (about the field edge of the presets), in units of 1 % of the light
        if form != "radial":
            return None
        return np.array([float(values.get("b4", 0.0)) * 0.5 ** 4 / 0.01, float(values.get("b6", 0.0)) * 0.5 ** 6 / 0.01])

    @staticmethod
    def factor(values: Mapping[str, Any], camera: CameraModel, shape: tuple[int, int],
               ctx: EffectContext | None = None) -> np.ndarray:
        t2 = FieldAngleEffect.tan2(camera, shape, ctx)
        poly = 1.0 + float(values.get("b4", 0.0)) * t2 ** 2 + float(values.get("b6", 0.0)) * t2 ** 3
        # cos^2(alpha) = 1 / (1 + tan^2(alpha))
        return (1.0 + t2) ** (-0.5 * float(values.get("dn", 0.0))) * np.maximum(poly, 0.0)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        g = self.factor(values, ctx.camera, ctx.frame_shape(signal.shape), ctx)
        out = signal.copy()
        out.phasor_w = signal.phasor_w * g
        out.dc_w = np.asarray(signal.dc_w) * g
        return out
