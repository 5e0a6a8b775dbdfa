"""Per-frequency calibration: a phase and a gain on one modulation frequency alone.

A multi-frequency camera calibrates a phase per frequency (the electronic delay of each
demodulation reference, which differs between frequencies) and a contrast per frequency. An
error in one of them moves that frequency's phase or signal and no other's: the phases of the
frequencies then no longer follow one range, which unwraps to the wrong interval and reads as
a surface that is not there. The first frequency's own phase is a range offset and its gain a
reflectance, so the effect acts on the second and third frequencies relative to the first;
a single-frequency session has nothing for it to do (diagnosis leaves it out there).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from tofhil.sim.effects.base import Effect, EffectContext, Param
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal

#: The frequencies after the first the effect has a phase and a gain for (index 1 and 2).
FREQUENCY_INDICES = (1, 2)


@register
class FrequencyCalibrationEffect(Effect):
    name = "frequency_calibration"
    calibrates = "frequency"
    stage = "pixel"
    rank = 125
    summary = ("a calibration phase and gain on one modulation frequency alone (the 2nd and 3rd, relative to the "
               "1st): `phase_<i>_rad` turns harmonic h of frequency i by h * phase, `gain_<i>` scales its signal")
    doc = ("Per-frequency calibration errors of a multi-frequency camera: the demodulation reference of "
           "frequency i (i = 1, 2 counting from 0; the first frequency's own phase is a range offset, its "
           "gain a reflectance) delayed by phase_i (harmonic h of that frequency turns by h * phase_i, as a "
           "time delay of the reference does) and its signal scaled by gain_i. The phases of the frequencies "
           "then disagree about the range, and unwrapping picks a wrong interval.")
    params = {
        **{f"phase_{i}_rad": Param(0.0, -math.pi, math.pi, "rad", f"calibration phase of frequency {i} (from 0)",
                                   default=0.1 if i == 1 else None, fit=(-0.6, 0.6), step=0.01)
           for i in FREQUENCY_INDICES},
        **{f"gain_{i}": Param(1.0, 0.25, 4.0, "", f"signal gain of frequency {i} (from 0)",
                              fit=(0.7, 1.4), step=0.01)
           for i in FREQUENCY_INDICES},
    }

    def min_frequencies(self, param: str) -> int:
        """``phase_i`` and ``gain_i`` act on frequency ``i``: a session needs ``i + 1`` of them."""
        return int(param.split("_")[1]) + 1

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        out = signal.copy()
        h = np.asarray(signal.harmonics, dtype=np.float64)
        for i in FREQUENCY_INDICES:
            if i >= signal.freq_hz.size:
                continue
            phase, gain = float(values[f"phase_{i}_rad"]), float(values[f"gain_{i}"])
            if phase or gain != 1.0:
                out.phasor_w[i] = signal.phasor_w[i] * (gain * np.exp(1j * h * phase))[:, None, None]
        return out
