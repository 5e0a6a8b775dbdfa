"""Corrections know their limits: source pixels whose taps clipped.

A stray-light correction removes ``h * S`` computed from the measured signal. A source
pixel whose taps clipped (the bright card beside the lens) has no valid ``S``: its light,
scattered over the sensor, is not known from the capture, and a correction that spreads
the light it does know removes the wrong share -- the dark square beside the card comes
out worse than before. :func:`clipped_sources` either restores the clipped pixels' signal
from a stated model (the twin's prediction, ``twin=SCENE``) or marks the pixels whose
correction cannot be trusted (``FLAG_UNTRUSTED``) and says so.

Without a model the clipped pixels' light is estimated at its smallest plausible level: a
clipped pixel is at least as bright as the brightest pixels that did not clip (the 99th
percentile of ``|S|`` over them, per frequency), or its clipped ``|S|`` when larger. A
pixel is untrusted where that light, scattered by the correction's own operator, exceeds
:data:`TRUST` of its signal (a phase error of that many radians: 0.01 rad is 12 mm at
20 MHz).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.eval.corrections.context import FLAG_RESTORED, FLAG_UNTRUSTED, CorrectionContext

#: Light from clipped sources above this fraction of a pixel's |S| makes it untrusted.
TRUST = 0.01


def clipped_sources(s: np.ndarray, ctx: CorrectionContext | None, scatter: Callable[[np.ndarray], np.ndarray],
                    twin: str | Path | Any = "") -> np.ndarray:
    """The signal to correct: with ``twin`` the clipped pixels' ``S`` is the twin's prediction
    (in the device's scale), else ``s`` unchanged and the pixels it cannot correct flagged.
    ``scatter`` is the correction's stray-light operator (``h * S`` without the direct part).
    ``s`` of rank 4 holds frames' deviations from a mean: a restored pixel has none."""
    sat = None if ctx is None else ctx.saturated
    if sat is None or not sat.any():
        return s
    s = np.asarray(s)
    if s.ndim == 4:
        return np.where(sat, 0, s) if twin else s
    n_sat = int(sat.sum())
    if twin:
        from tofhil.eval.corrections.twin import device_scale, predict

        pred = predict(twin, ctx)
        scale = device_scale(s, pred, ctx)
        a = scale.factor
        out = s.astype(np.complex128, copy=True)
        out[..., sat] = a * pred.full[..., sat]
        ctx.flag(sat, FLAG_RESTORED)
        ctx.info["restored_from_twin"] = {"scene": pred.scene, "pixels": n_sat, "signal_scale": a,
                                          "signal_scale_fit": {**scale.to_json(), "text": scale.text(),
                                                               "fitted_on": ctx.fitted_on() if scale.fitted else None}}
        ctx.note(f"the light of the clipped source pixels restored from the twin {pred.scene} before correcting "
                 f"(flag restored_from_twin); twin {scale.text()}"
                 + (f"; fitted on {ctx.fitted_on()}" if scale.fitted else ""))
        return out
    amp = np.abs(s)
    floor = np.percentile(amp[..., ~sat], 99, axis=-1) if (~sat).any() else np.zeros(amp.shape[:-2])
    src = np.where(sat, np.maximum(amp, floor[..., None, None]), 0.0)
    stray = np.abs(scatter(src))
    with np.errstate(invalid="ignore"):
        untrusted = ~sat & np.any(stray > TRUST * amp, axis=tuple(range(s.ndim - 2)))
    ctx.flag(untrusted, FLAG_UNTRUSTED)
    k = int(untrusted.sum())
    ctx.info["clipped_sources"] = {"pixels": n_sat, "untrusted_pixels": k, "trust_fraction": TRUST}
    ctx.note(f"source pixels clipped: their light is unknown to the correction; where the stray light it would "
             f"leave exceeds {100 * TRUST:g} % of the signal the correction cannot be trusted (flag untrusted; "
             "twin=SCENE restores the clipped light from the twin)")
    return s
