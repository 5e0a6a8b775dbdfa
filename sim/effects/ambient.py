"""Unmodulated light and charge: ambient irradiance on the scene (scene stage) and an offset
of every tap the scene does not explain (signal stage). Both raise the tap offset and the
shot noise, not the phase."""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from tofhil.sim.effects.base import Effect, EffectContext, Param, _same_values
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal


@register
class AmbientEffect(Effect):
    name = "ambient"
    offset_only = True
    stage = "scene"
    rank = 40
    summary = 'ambient irradiance added on every surface (offset and shot noise, no phase)'
    doc = ("Unmodulated ambient light (sun, lamps) added to the scene's ambient irradiance on every "
           "surface; it raises the tap offset and the shot noise, not the phase.")
    params = {"irradiance_w_m2": Param(0.0, 0.0, 2000.0, "W/m^2", "added ambient irradiance (NIR band)",
                                       default=1.0, fit=(0.0, 2000.0), step=1.0, start=5.0)}

    def apply_scene(self, scene: Any, values: Mapping[str, Any]) -> Any:
        return dataclasses.replace(scene, ambient_irradiance_w_m2=scene.ambient_irradiance_w_m2
                                   + float(values["irradiance_w_m2"]))

    def rescale_render(self, result: Any, values: Mapping[str, Any], rendered: Mapping[str, Any],
                       scene: Any) -> Any | None:
        """Ambient power is linear in the irradiance (the render keeps the power per W/m^2)."""
        if _same_values(values, rendered):
            return result
        if result.ambient_power_per_irradiance is None:
            return None
        e = scene.ambient_irradiance_w_m2 - float(rendered["irradiance_w_m2"]) + float(values["irradiance_w_m2"])
        return dataclasses.replace(result, ambient_power_w=result.ambient_power_per_irradiance * e)


@register
class OffsetEffect(Effect):
    name = "offset"
    calibrates = "offset"
    stage = "signal"
    rank = 80
    summary = 'unmodulated charge the scene does not explain (dark/black-level offset, LED leakage, a glowing cover): `dark_e` electrons per tap on every pixel'
    doc = ("Unmodulated charge that is not scene ambient: a dark or black-level offset the sensor "
           "model lacks, or unmodulated light not from the scene (emitter leakage, a glowing cover "
           "glass), uniform over the sensor. It raises every tap by dark_e electrons (the tap "
           "offset, and the shot noise) and leaves the phase alone; unlike ambient it does not "
           "follow the scene's reflectance or the lens.")
    params = {"dark_e": Param(0.0, 0.0, 1.0e6, "e-", "unmodulated electrons added to every tap", default=100.0,
                              fit=(0.0, 2.0e5), step=50.0, start=100.0, starts=(1.0e3, 1.0e4, 5.0e4))}

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        if ctx.sensor is None:
            raise ValueError("offset needs the sensor configuration (electrons per watt)")
        out = signal.copy()
        # the sensor turns unmodulated power P into tap_fraction * e_per_W * P electrons per tap
        e_w = ctx.sensor.tap_fraction * ctx.sensor.electrons_per_watt
        out.ambient_w = np.array(signal.ambient_w) + float(values["dark_e"]) / e_w
        return out
