"""The render-stage effect: the indirect (multi-bounce) light recombined with the direct."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from tofhil.errors import InputFileError
from tofhil.sim.effects.base import Effect, Param
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal


@register
class MultipathEffect(Effect):
    name = "multipath"
    stage = "render"
    beyond_direct = "multipath"
    rank = 50
    summary = '`S = S_direct + scale * S_indirect` (0 = direct only, 1 = physical); option `bounces` (default max(2, render.bounces))'
    doc = ("Scale of the indirect (multi-bounce) light: S = S_direct + scale * S_indirect. 0 = direct "
           "only, 1 = physical. Needs a render with separate direct/indirect phasors and bounces > 0 "
           "(`bounces` option; default the scene's render.bounces, at least 2). A scene without this "
           "effect uses whatever the renderer computed.")
    params = {"scale": Param(0.0, 0.0, 3.0, "", "factor on the indirect light", default=1.0,
                             fit=(0.0, 3.0), step=0.1, start=1.0)}
    options = {"bounces": "number of indirect bounces to render (integer >= 1)"}

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        b = values.get("bounces")
        if b is not None and (isinstance(b, bool) or not isinstance(b, int) or b < 1):
            raise InputFileError(f"got {b!r}", file=source, field=f"{prefix}.bounces",
                                 expected="an integer >= 1")

    def render_requirements(self, values: Mapping[str, Any], scene: Any) -> dict[str, Any]:
        b = values.get("bounces") or max(2, int(scene.render.bounces))
        return {"separate_direct": True, "bounces": int(b)}

    def apply_render(self, result: Any, values: Mapping[str, Any],
                     waveform: Mapping[int, complex] | None = None) -> OpticalSignal:
        return OpticalSignal.from_render(result, waveform, multipath_scale=float(values["scale"]))
