"""What a capture can and cannot tell: unobservable effects and ambiguous causes.

Two statements a diagnosis owes its reader besides the cause it names:

- **unobservable**: effects left out of the candidates because the data or the scene cannot
  show them (an offset-only effect in depth data; a constant range offset on planes whose
  pose was fitted to the same depth, see :mod:`tofhil.sim.from_capture`);
- **ambiguous**: in a round of the selection, the best effect and the runner-up explain the
  held-out data equally well when their score difference is below its own standard error.
  The standard error comes from the held-out blocks (the checkerboard squares of the split):
  each block's share of the score difference is one sample, neighbouring pixels being
  correlated by the optics. Then the diagnosis says "A or B, this capture cannot tell them
  apart" and which capture would.

A post-step on :class:`tofhil.eval.diagnose.selection.Selection`; the selection itself is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tofhil.eval.diagnose.heldout import HeldOutData, huber
from tofhil.eval.diagnose.selection import Candidate, Selection

#: The capture that separates two effects (an unordered pair), for the ambiguity message.
SEPARATING_CAPTURE: dict[frozenset[str], str] = {
    frozenset({"range_offset", "pose"}): "a known target (its pose from the amplitude image, not from depth)",
    frozenset({"range_offset", "wiggling"}): "a second distance (wiggling changes with distance, an offset does not)",
    frozenset({"range_offset", "amplitude_dependent"}): "a darker and a brighter target at one distance",
    frozenset({"wiggling", "amplitude_dependent"}): "a second distance at the same brightness",
    frozenset({"lens_distortion", "pose"}): "a tilted plane or a known target filling the view",
    frozenset({"stray_light", "multipath"}): "a dark target in front of a bright background, then without the background",
    frozenset({"reflectance", "stray_light"}): "the same scene at a second distance",
}
DEFAULT_SEPARATING = "a second distance, a tilt of the surface, or a known target as independent truth"
#: Named causes that a surface shape can mimic when the scene's geometry was fitted to the
#: same depth (a scene from the capture without a known target): what each looks like.
MIMICKED_BY_SHAPE = {
    "range_offset_map": "a range pattern along rows or columns looks the same as a surface that bends along them",
    "field_angle": "a range error growing with the field angle looks the same as a surface curved about the "
                   "optical axis",
}
SHAPE_SEPARATING = ("the same scene with the camera rolled 90 degrees or moved sideways (a sensor pattern moves "
                    "with the sensor, a surface shape with the scene), or a known flat target (--target)")


@dataclass
class Observability:
    unobservable: dict[str, str] = field(default_factory=dict)
    ambiguous: list[dict[str, Any]] = field(default_factory=list)

    @property
    def lines(self) -> list[str]:
        out = [f"not a candidate: {e} -- {why}" for e, why in self.unobservable.items()]
        out += [a["text"] for a in self.ambiguous]
        return out

    def to_json(self) -> dict[str, Any]:
        return {"unobservable": self.unobservable, "ambiguous": self.ambiguous}


def _per_block_rho(data: HeldOutData, prediction: np.ndarray, block_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Held-out misfit (Huber rho summed over channels and components) per pixel, and its block label."""
    m = data.test_pixels
    r = data.whitened(prediction, "test")
    rho = (huber(r.real) + huber(r.imag)).sum(axis=0)
    v, u = np.nonzero(m)
    label = (v // block_px) * (data.usable.shape[1] // block_px + 1) + u // block_px
    return rho, label


def score_difference(model: Any, data: HeldOutData, a: Candidate, b: Candidate, block_px: int
                     ) -> tuple[float, float]:
    """``score(b) - score(a)`` on held-out data and its standard error over held-out blocks."""
    rho_a, label = _per_block_rho(data, model.predict(a.all_params), block_px)
    rho_b, _ = _per_block_rho(data, model.predict(b.all_params), block_px)
    _, inv = np.unique(label, return_inverse=True)
    per_block = np.bincount(inv, weights=rho_b - rho_a)
    nb = per_block.size
    se = float(np.sqrt(nb) * per_block.std(ddof=1)) if nb > 1 else float("inf")
    return float(b.score - a.score), se


def assess(selection: Selection, model: Any, data: HeldOutData, *, block_px: int = 8,
           unobservable: dict[str, str] | None = None) -> Observability:
    """The ambiguities of each selection round that chose an effect, and the unobservable ones."""
    obs = Observability(unobservable=dict(unobservable or {}))
    for i, rnd in enumerate(selection.rounds):
        if len(rnd) < 2 or not rnd[0].significant:
            continue
        best = rnd[0]
        for other in rnd[1:3]:
            diff, se = score_difference(model, data, best, other, block_px)
            if diff > se:  # told apart (equal predictions: diff = se = 0, not told apart)
                continue
            hint = SEPARATING_CAPTURE.get(frozenset({best.effect, other.effect}), DEFAULT_SEPARATING)
            obs.ambiguous.append({
                "round": i + 1, "effects": [best.effect, other.effect], "score_difference": diff,
                "standard_error": se,
                "text": (f"round {i + 1}: {best.effect} or {other.effect}, this capture cannot tell them apart "
                         f"(held-out score difference {diff:.1f} is below its standard error {se:.1f}); "
                         f"a capture that would: {hint}")})
    return obs


#: The capture that separates a pixel-fixed pattern from a surface shape, as data a program can
#: act on (the closed loop takes it): a bench change of the camera's pose.
SHAPE_SEPARATING_CAPTURE = {"kind": "bench_change", "change": "camera_pose",
                            "options": ["roll the camera 90 degrees", "move the camera sideways",
                                        "a known flat target (--target)"]}


def shape_ambiguities(causes: list[str], *, geometry_from_depth: bool = True) -> list[dict[str, Any]]:
    """Each named cause that is a pattern fixed to the pixels: from one pose a surface shape
    the twin lacks looks the same (the data hold no second view to tell); said for every
    session, since one view cannot separate a sensor pattern from a scene surface."""
    why = ("the planes were fitted to the same depth" if geometry_from_depth
           else "one view of the scene cannot tell a pattern of the pixels from a surface the twin places differently")
    return [{"round": None, "effects": [c, "surface shape"], "score_difference": None, "standard_error": None,
             "separating_capture": SHAPE_SEPARATING_CAPTURE,
             "text": (f"{c} or a surface shape the twin lacks, this capture cannot tell them apart: {why}, and "
                      f"{MIMICKED_BY_SHAPE[c]}; a capture that would: {SHAPE_SEPARATING}")}
            for c in causes if c in MIMICKED_BY_SHAPE]
