"""Non-sinusoidal modulation ("wiggling"): odd harmonics of the correlation waveform, and
which of them a session's taps can see (:func:`harmonic_aliases`)."""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from tofhil.sim.effects.base import BENCH_CHANGE, Effect, EffectContext, Param, Separation
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal


def harmonic_aliases(h: int, n_taps: int) -> bool:
    """Whether harmonic ``h`` of the correlation waveform reaches the estimate
    ``S = (2/K) sum_k c_k exp(i theta_k)`` of ``K = n_taps`` equally spaced taps: the sum over
    the taps keeps exactly the orders ``h = +-1 (mod K)``, each folded onto the fundamental
    (K = 4: every odd order, 3 and 7 as ``exp(-i(h-1) phi)``, 5 as ``exp(+i 4 phi)``; K = 3:
    2, 4, 5, 7 but not 3). Other orders cancel and cannot be seen in the data."""
    return h % n_taps in (1, n_taps - 1)


#: The harmonics the effect carries: the odd ones of a symmetric waveform, and the even ones a
#: duty cycle off 50 % adds (seen by 3- and 5-tap sensors only: with 4 taps they cancel).
_WIGGLE_ORDERS = (2, 3, 4, 5, 6, 7)
_AMP: dict[str, Any] = {"fit": (0.0, 0.5), "step": 0.01}
_PHASE: dict[str, Any] = {"fit": (-math.pi, math.pi), "step": 0.3, "periodic": True}
_ALL = ("harmonics",)


def _harmonic_params(h: int, forms: tuple[str, ...], *, start: float,
                     default: float | None = None) -> dict[str, Param]:
    """Harmonic ``h``'s amplitude (relative to the fundamental's) and phase."""
    nth = {2: "2nd", 3: "3rd"}.get(h, f"{h}th")
    return {f"h{h}_amplitude": Param(0.0, 0.0, 0.5, "", f"{nth}-harmonic correlation amplitude / fundamental's",
                                     default=default, start=start, forms=forms, **_AMP),
            f"h{h}_phase_rad": Param(0.0, -math.pi, math.pi, "rad", f"{nth}-harmonic phase", start=0.0,
                                     starts=(-2.0, 2.0), forms=forms, **_PHASE)}


@register
class WigglingEffect(Effect):
    name = "wiggling"
    mimicked_by = {"amplitude_dependent": Separation(BENCH_CHANGE, "distance", "a second distance at the same brightness")}
    stage = "signal"
    rank = 140
    summary = ('harmonics 2 to 7 of the correlation waveform (odd ones of a symmetric waveform, even ones of a duty '
               'cycle off 50 %); harmonic h reaches K taps only if h = +-1 mod K (K = 4: the odd ones, phase error '
               'about `-a3 sin(4 phi + psi3) + a5 sin(4 phi + psi5) - a7 sin(8 phi + psi7)`; K = 3: 2, 4, 5, 7)')
    doc = ("Non-sinusoidal modulation: harmonics of the correlation waveform, added to the emitter's: the odd "
           "ones of a symmetric (50 % duty) waveform, and the even ones a duty cycle off 50 % adds. With K taps "
           "harmonic h aliases onto the fundamental when h = +-1 mod K and gives a cyclic distance error (K = 4: "
           "the 3rd and 5th give 4 cycles per ambiguity range, the 7th 8, the even orders cancel; K = 3: the 2nd "
           "and 5th give 3 and 6 cycles, the 4th and 7th 3 and 6, the 3rd cancels); other orders cancel. "
           "Harmonics the render did not compute are synthesised from the fundamental (exact for single-path "
           "pixels). Diagnosis fits the 3rd harmonic (simple form) or every visible order up to the 7th (form "
           "`harmonics`; on a sensor that cannot see the 3rd, that form alone).")
    forms = {"harmonics": "every harmonic up to the 7th that the session's taps see (amplitude and phase each)"}
    # the 3rd harmonic is the simple form's too (its default and start: a typical LED's); the
    # others only the flexible form's, starting small. (Their order is the fit's parameter order.)
    params = {**_harmonic_params(3, ("",) + _ALL, default=0.05, start=0.03),
              **{k: v for h in (2, 4, 6, 5, 7) for k, v in _harmonic_params(h, _ALL, start=0.01).items()}}

    def is_off(self, values: Mapping[str, Any]) -> bool:
        return not self.harmonics(values)

    @staticmethod
    def harmonics(values: Mapping[str, Any]) -> tuple[int, ...]:
        return tuple(h for h in _WIGGLE_ORDERS if float(values.get(f"h{h}_amplitude", 0.0)) != 0.0)

    def observable(self, param: str, n_taps: int) -> bool:
        return harmonic_aliases(int(param[1:param.index("_")]), n_taps)

    def roughness(self, form: str, values: Mapping[str, Any]) -> np.ndarray | None:
        # the harmonics other than the 3rd shrink to zero: a ridge on their complex amplitudes (in
        # units of their typical size 0.01; amplitude and phase alike, so that the phase of a
        # small harmonic is not a free parameter); only the simple form's 3rd is smoothest
        if form != "harmonics":
            return None
        out = []
        for h in (h for h in _WIGGLE_ORDERS if h != 3):
            a, psi = float(values.get(f"h{h}_amplitude", 0.0)), float(values.get(f"h{h}_phase_rad", 0.0))
            out += [a * math.cos(psi) / 0.01, a * math.sin(psi) / 0.01]
        return np.array(out)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        out = signal.copy()
        for h in self.harmonics(values):
            a = float(values[f"h{h}_amplitude"])
            out.waveform[h] = out.waveform.get(h, 0.0) + a * np.exp(1j * float(values[f"h{h}_phase_rad"]))
        return out
