"""The pixel-stage delay pattern of the demodulation clock: row and column gradients plus a
seeded random part per pixel."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil import C_M_PER_S
from tofhil.errors import InputFileError
from tofhil.sim.effects.base import Effect, EffectContext, Param, _rotate_phase
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal


@register
class FixedPatternEffect(Effect):
    name = "fixed_pattern"
    stage = "pixel"
    rank = 110
    summary = 'per-pixel demodulation delay: row/column gradients about the image centre (clock distribution) plus a seeded random part (option `seed`); a delay tau reads `c tau / 2` farther'
    doc = ("Per-pixel demodulation delay pattern: linear row and column gradients (the modulation "
           "clock reaching rows/columns at different times) about the image centre, plus a seeded "
           "random per-pixel part. tau > 0 reads farther by c tau / 2.")
    params = {
        "row_delay_s": Param(0.0, -2e-11, 2e-11, "s/row", "delay per row from the image centre",
                             fit=(-2e-11, 2e-11), step=1e-13),
        "col_delay_s": Param(0.0, -2e-11, 2e-11, "s/column", "delay per column from the image centre",
                             fit=(-2e-11, 2e-11), step=1e-13),
        "random_delay_s": Param(0.0, 0.0, 1e-10, "s", "standard deviation of the random per-pixel delay",
                                default=5e-12),
    }
    options = {"seed": "seed of the random part (integer >= 0, default 0)"}

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        s = values.get("seed", 0)
        if isinstance(s, bool) or not isinstance(s, int) or s < 0:
            raise InputFileError(f"got {s!r}", file=source, field=f"{prefix}.seed", expected="an integer >= 0")

    @staticmethod
    def delay_s(values: Mapping[str, Any], shape: tuple[int, int], ctx: EffectContext | None = None) -> np.ndarray:
        """Each pixel's delay (s) on a frame of ``shape``; with ``ctx``, at the pixels its
        signal holds (:attr:`EffectContext.pixels`)."""
        h, w = shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float64) if ctx is None else ctx.pixel_grid(shape)
        tau = float(values["row_delay_s"]) * (v - (h - 1) / 2) + float(values["col_delay_s"]) * (u - (w - 1) / 2)
        sd = float(values["random_delay_s"])
        if sd:
            rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(values.get("seed", 0)), 0xF1])))
            draw = rng.standard_normal(shape)  # the whole frame's draw, whichever pixels are asked for
            tau = tau + sd * (draw if ctx is None else ctx.at_pixels(draw))
        return tau

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        return _rotate_phase(signal, C_M_PER_S * self.delay_s(values, ctx.frame_shape(signal.shape), ctx))
