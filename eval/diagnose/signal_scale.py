"""The device's signal scale: one factor from emitted light to DN, fitted where nothing states it.

A twin predicts DN through a radiometric chain: emitter power, optics, quantum efficiency,
modulation contrast, integration time and conversion gain. A capture from a device records
its modulation frequencies, tap phases and integration time, but not that chain; a scene
written for another camera, or whose emitter power is a guess, or built from a capture with a
sensor of its own (``scene-from-capture``), carries a chain that did not make the session.
For the modulated signal these unknowns act as one product, so the twin is fitted one factor
``g`` before anything else is: the median over the training pixels of ``|S_measured| /
|S_twin|``. The median of the ratio is unmoved by what the later search looks for (stray
light, multipath and defects move a minority of pixels; a gain moves all of them alike, and
that is this factor).

When the session records the sensor that made it and the scene's chain is that sensor's (a
twin session diagnosed against its own scene), nothing is fitted: a global gain is then a
finding, not a nuisance, and the search can name it. When it is fitted, a global gain of the
device cannot be told from it; the report says so.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from tofhil.errors import TofhilError

#: The sensor fields whose product with the emitter power scales the modulated signal in DN.
RADIOMETRIC_FIELDS = ("conversion_gain_dn_per_e", "quantum_efficiency", "modulation_contrast", "tap_fraction",
                      "integration_time_s")


@dataclass(frozen=True)
class SignalScale:
    """The factor the twin's signal was multiplied by, and where it came from."""

    factor: float = 1.0
    fitted: bool = False
    #: Why it was (or was not) fitted, in words for the report.
    reason: str = "the session records the sensor that made it, and the scene's radiometric chain is that sensor's"
    #: Training pixels the ratio was taken over, and the robust scatter of its log (MAD x 1.4826).
    pixels: int = 0
    log_scatter: float = 0.0

    @property
    def standard_error(self) -> float:
        """Relative standard error of the factor (the median of ``pixels`` log ratios; pixels of
        one block are correlated by the smooth effects, so this is a lower bound)."""
        return 1.2533 * self.log_scatter / math.sqrt(self.pixels) if self.pixels else float("nan")

    def text(self) -> str:
        if not self.fitted:
            return f"signal scale: the twin's, not fitted ({self.reason})"
        return (f"signal scale: the twin's signal x {self.factor:.4g} (+- {100 * self.standard_error:.2g} %), fitted as "
                f"the median measured / twin amplitude ratio over {self.pixels} training pixels ({self.reason}); "
                "a global gain of the device cannot be told from this factor")

    def to_json(self) -> dict[str, Any]:
        return {"factor": self.factor, "fitted": self.fitted, "reason": self.reason, "pixels": self.pixels,
                "log_scatter": round(self.log_scatter, 6),
                "relative_standard_error": None if not self.fitted else round(self.standard_error, 6)}


def needs_scale(scene_sensor: Any, recorded: dict | None) -> str | None:
    """Why the twin's signal scale must be fitted for a session, or None when the session
    states the chain that made it (a recorded sensor whose radiometric fields the scene shares)."""
    if recorded is None:
        return "the session records no sensor configuration, as a device capture does not"
    if scene_sensor is None:
        return None
    differ = [f for f in RADIOMETRIC_FIELDS
              if f in recorded and not math.isclose(float(recorded[f]), float(getattr(scene_sensor, f)), rel_tol=1e-9)]
    if differ:
        return ("the scene's sensor differs from the one the session recorded in " + ", ".join(differ)
                + ": its emitter power was not stated for this sensor")
    return None


def fit_signal_scale(data: Any, prediction: np.ndarray, reason: str) -> SignalScale:
    """The median measured / predicted amplitude over the training pixels where both carry
    signal (:class:`SignalScale`). Raises one line when the twin lights none of the pixels
    where the capture has signal: no factor can bring them together, the geometry differs."""
    nf = data.n_freq
    meas = np.abs(data.s_train[:nf]).mean(axis=0)
    pred = np.abs(prediction[:nf]).mean(axis=0)
    lit = pred > 0
    if lit.any():
        # a twin pixel with a millionth of the twin's typical light is a shadow, not a ratio
        lit &= pred > 1e-6 * float(np.median(pred[lit]))
    use = data.train_pixels & lit & (meas > 0)
    n = int(use.sum())
    if n < 20:
        raise TofhilError(f"the twin lights {n} of the {int(data.train_pixels.sum())} training pixels where the "
                          "capture has signal: no signal scale can bring them together (a camera, pose or scene "
                          "that does not see what the capture saw)", file=data.source, field="camera",
                          expected="a scene whose objects the capture's pixels see")
    log_ratio = np.log(meas[use] / pred[use])
    centre = float(np.median(log_ratio))
    scatter = 1.4826 * float(np.median(np.abs(log_ratio - centre)))
    return SignalScale(factor=float(np.exp(centre)), fitted=True, reason=reason, pixels=n, log_scatter=scatter)


def scaled_scene(scene: Any, scale: SignalScale) -> Any:
    """The scene with its sensor's conversion gain times the factor, and its ADC range widened
    by the same factor, so that the twin clips at the same charge as before (its full well)."""
    if not scale.fitted or scale.factor == 1.0:
        return scene
    s = scene.sensor
    bits = s.adc_bits + max(0, math.ceil(math.log2(scale.factor)))
    sensor = dataclasses.replace(s, conversion_gain_dn_per_e=s.conversion_gain_dn_per_e * scale.factor,
                                 adc_bits=min(bits, 32))
    return dataclasses.replace(scene, sensor=sensor)


def without_fixed_pattern(scene: Any) -> Any:
    """The scene with its sensor's seeded fixed pattern (DSNU, PRNU) at its expectation (none).

    The pattern a scene states is one random realisation in the electrons of the camera the
    scene was written for; a device's own pattern is another, which no scene knows. A twin that
    predicted the scene's realisation would add a pixel pattern the device does not have; at its
    expectation the device's pattern is left in the residual, for the search to find as one."""
    fp = scene.sensor.fixed_pattern
    if fp.dsnu_e == 0 and fp.prnu == 0:
        return scene
    sensor = dataclasses.replace(scene.sensor, fixed_pattern=dataclasses.replace(fp, dsnu_e=0.0, prnu=0.0))
    return dataclasses.replace(scene, sensor=sensor)
