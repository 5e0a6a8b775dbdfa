"""Per-tap calibration: a gain and an offset of each tap of the readout, relative to tap 0.

Every correlation pixel reads its taps through its own path (a storage node, an amplifier, a
column circuit per tap): their gains and offsets differ by per cents, which a camera's
calibration file corrects per tap. An imbalance makes a pattern that alternates with the tap
index, which no change of the light can make (a range, a phase, a pose): odd and even taps
read differently in proportion to the offset level. Acts on the recorded taps, noise and all.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from tofhil.sim.effects.base import Effect, EffectContext, Param
from tofhil.sim.effects.registry import register

#: Taps (after the reference tap 0) the effect has a gain and an offset for.
TAP_INDICES = (1, 2, 3)


@register
class TapCalibrationEffect(Effect):
    name = "tap_calibration"
    calibrates = "tap"
    stage = "taps"
    rank = 150
    summary = ("per-tap gain and offset of the readout relative to tap 0 (`gain_<k>`, `offset_<k>_dn`, k = 1..3): "
               "a pattern that alternates with the tap index")
    doc = ("The readout's per-tap imbalance: tap k (k = 1, 2, 3; tap 0 is the reference, a common gain is "
           "a reflectance and a common offset the offset effect) reads gain_k times its charge plus "
           "offset_k_dn. Applied to the recorded taps, so a gain scales their noise too. What a camera's "
           "per-tap calibration corrects (tofhil calibrate-taps measures it from flat captures).")
    params = {
        **{f"gain_{k}": Param(1.0, 0.5, 2.0, "", f"gain of tap {k} relative to tap 0",
                              default=1.03 if k % 2 else None,
                              fit=(0.8, 1.25), step=0.005)
           for k in TAP_INDICES},
        **{f"offset_{k}_dn": Param(0.0, -1.0e4, 1.0e4, "DN", f"offset of tap {k} relative to tap 0",
                                   fit=(-500.0, 500.0), step=1.0)
           for k in TAP_INDICES},
    }

    def observable(self, param: str, n_taps: int) -> bool:
        """Tap k's parameters need a tap k."""
        return int(param.split("_")[1]) < n_taps

    def apply_taps(self, taps: np.ndarray, values: Mapping[str, Any], ctx: EffectContext) -> np.ndarray:
        k = taps.shape[1]
        gain = np.ones(k)
        offset = np.zeros(k)
        for j in TAP_INDICES:
            if j < k:
                gain[j], offset[j] = float(values[f"gain_{j}"]), float(values[f"offset_{j}_dn"])
        shape = (1, k) + (1,) * (taps.ndim - 2)
        out = taps * gain.reshape(shape).astype(taps.dtype) + offset.reshape(shape).astype(taps.dtype)
        return out.astype(taps.dtype, copy=False)
