"""Hidden changes for the flexible scalar forms (issue 10): wiggling with harmonics up to the
7th, a monotone range error in log amplitude that is neither exponential nor piecewise
linear, and an emitter profile of another form than the library's polynomial.

Each acts on the light on the sensor between the render and the sensor model (as
tests/eval/hidden_forms.py does), written here with the sensor's own mechanisms (waveform
coefficients, a phase rotation, a scale of the emitter's light), not with the effect code.
Shared by tests/eval/test_scalar_forms.py and benchmarks/diagnose_sweep.py.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from tests.eval.hidden_forms import Change, rotate_radial
from tofhil.sim.sensor import OpticalSignal


def odd_harmonics(rng: np.random.Generator, orders: tuple[int, ...] = (3, 5, 7),
                  amplitude: tuple[float, float] = (0.02, 0.05)) -> Change:
    """Correlation harmonics of random amplitude and phase added to the waveform."""
    coef = {h: rng.uniform(*amplitude) * np.exp(1j * rng.uniform(-math.pi, math.pi)) for h in orders}

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        out = signal.copy()
        for h, c in coef.items():
            out.waveform[h] = out.waveform.get(h, 0.0) + c
        return out

    change.coef = coef  # type: ignore[attr-defined]
    return change


def amplitude_sigmoid(rng: np.random.Generator) -> Change:
    """A monotone range error in log10 of the modulation amplitude (electrons per tap):
    ``k * tanh((log10 A - x0) / w)``, rising or falling, centred in the image's range."""
    k = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.02, 0.04))
    w = float(rng.uniform(0.4, 0.8))
    shift = float(rng.uniform(-0.2, 0.2))

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        c = sensor.config
        amp_e = c.tap_fraction * c.modulation_contrast * c.electrons_per_watt \
            * np.abs(signal.phasor_w[:, signal.harmonics.index(1)])
        x = np.log10(np.maximum(amp_e, 1e-3))
        x0 = float(np.median(x[amp_e > 0])) + shift
        return rotate_radial(signal, k * np.tanh((x - x0) / w))

    return change


def cos_beam(rng: np.random.Generator) -> Change:
    """The emitter's beam narrower or wider than the scene's by a factor cos^dn of the field
    angle (on the emitter's light only; ambient unchanged)."""
    dn = float(rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 3.0))

    def change(signal: OpticalSignal, sensor: Any) -> OpticalSignal:
        cam = sensor.camera
        v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
        # the pixel ray (x, y, 1) in camera coordinates; cos of its angle to the optical axis
        x, y = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
        g = (1.0 / np.sqrt(1.0 + x * x + y * y)) ** dn
        out = signal.copy()
        out.phasor_w = signal.phasor_w * g
        out.dc_w = np.asarray(signal.dc_w) * g
        return out

    change.dn = dn  # type: ignore[attr-defined]
    return change
