""""A or B": two readings of the data this capture cannot tell apart, and the capture that would.

One record (:class:`Ambiguity`) and one function (:func:`ambiguities`) for every way a
diagnosis finds two readings equal. Three tests find them, each kept as it was designed:

- :data:`SAME_RESIDUAL` (run by the selection when it names a cause,
  :func:`same_residual`): another family's candidate of the same round changes the held-out
  prediction mostly as the named one does, and their held-out scores differ by less than the
  larger of one degree of freedom's price and twice the noise of that difference;
- :data:`ROUND_SCORE` (:func:`round_ambiguities`): in a round that chose an effect, the best
  and a runner-up differ in held-out score by less than that difference's standard error
  over the held-out blocks (the checkerboard squares of the split: neighbouring pixels are
  correlated by the optics, so each block's share of the difference is one sample);
- :data:`SETS_ALIKE` (:func:`sets_alike`, run by the selection when its searches from several
  first choices end in different sets): another set of causes scores within the same margin
  as :data:`SAME_RESIDUAL`'s of the set chosen;
- :data:`ONE_VIEW` (:func:`shape_ambiguities`): a named cause that is a pattern fixed to the
  pixels looks, from one view, like a surface shape the scene lacks.

Every ambiguity carries the separating capture as data (:class:`tofhil.sim.effects.Separation`:
an acquisition setting or a bench change), declared on the effects
(``Effect.mimicked_by``, ``Effect.mimicked_by_shape``), never in a table here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from tofhil.eval.diagnose.heldout import HeldOutData, huber
from tofhil.sim.effects import EFFECTS, SHAPE_SEPARATION, Separation, separation

if TYPE_CHECKING:
    from tofhil.eval.diagnose.selection import Candidate, Selection

#: The tests that find an ambiguity (the name each record carries).
SAME_RESIDUAL = "same residual"
ROUND_SCORE = "score within its standard error"
ONE_VIEW = "one view"
SETS_ALIKE = "sets alike"
#: The reading a pattern fixed to the pixels is confused with, from one view.
SURFACE_SHAPE = "surface shape"
#: Squared cosine between two candidates' changes of the held-out prediction above which they
#: explain the same residual (more than half of each one's change is the other's).
SAME_RESIDUAL_OVERLAP = 0.5
#: Figures diagnosis.json gives rounded (digits).
_ROUNDED = {"score_gap": 2, "needed": 2, "overlap": 4}


@dataclass(frozen=True)
class Ambiguity:
    """Two readings of the data the capture cannot tell apart."""

    #: The two readings: the effect named (or the round's best) first, then the other.
    readings: tuple[str, str]
    #: The test that failed to separate them (:data:`SAME_RESIDUAL`, :data:`ROUND_SCORE`,
    #: :data:`ONE_VIEW`) and its figures.
    test: str
    figures: dict[str, float | None]
    #: The capture that would tell them apart.
    separating: Separation
    text: str
    #: Each reading's form ("" the simple form) and the selection round (1-based; None: not a
    #: round's comparison).
    forms: tuple[str, str] = ("", "")
    round: int | None = None

    @property
    def effect(self) -> str:
        return self.readings[0]

    @property
    def other(self) -> str:
        return self.readings[1]

    def to_json(self) -> dict[str, Any]:
        # the keys diagnosis.json has always had under `alternatives` and `observability.ambiguous`
        # (effect/other/forms, effects/round, the figures at the top level) beside the record's own
        figures = {k: (v if v is None or k not in _ROUNDED else round(v, _ROUNDED[k])) for k, v in self.figures.items()}
        return {"effects": list(self.readings), "effect": self.effect, "form": self.forms[0], "other": self.other,
                "other_form": self.forms[1], "round": self.round, "test": self.test, "figures": figures,
                **figures, "separating_capture": self.separating.to_json(), "text": self.text}


# ------------------------------------------------------------------ the three tests
def same_residual(model: Any, data: HeldOutData, chosen: Candidate, others: Sequence[Candidate],
                  current_pred: np.ndarray, penalty_per_dof: float) -> list[Ambiguity]:
    """The candidates of other families in the same round (``others``, each an effect's best
    form) that explain the same held-out residual as ``chosen`` about as well: significant
    themselves, a held-out score within the larger of one degree of freedom's price and twice
    the noise of the score difference (that noise is 2 |d|, d the whitened held-out difference
    of the two predictions), and their change of the prediction more than
    :data:`SAME_RESIDUAL_OVERLAP` the same as the chosen one's (the whitened held-out changes
    from ``current_pred``, the model before the round). A flexible form of one family can take
    up another's effect: an amplitude spline a wiggling's harmonics on a frontal wall."""
    out: list[Ambiguity] = []
    near = [c for c in others if c.effect != chosen.effect and c.significant]
    if not near:
        return out

    def residual(c: Any) -> np.ndarray:  # kept by the selection; else predicted again
        r = getattr(c, "test_residual", None)
        return data.whitened_residual(model.predict(c.all_params), "test") if r is None else r

    base = data.whitened_residual(current_pred, "test")
    named = residual(chosen)
    for c in near:
        needed, overlap = _likeness(base, named, residual(c), penalty_per_dof)
        gap = float(c.score - chosen.score)
        if overlap > SAME_RESIDUAL_OVERLAP and gap < needed:
            out.append(Ambiguity(
                readings=(chosen.effect, c.effect), forms=(chosen.form, c.form), test=SAME_RESIDUAL,
                figures={"score_gap": gap, "needed": needed, "overlap": overlap},
                separating=separation(chosen.effect, c.effect),
                text=_same_residual_text(chosen.effect, chosen.form, c.effect, c.form, gap, needed, overlap)))
    return out


def _likeness(base: np.ndarray, named: np.ndarray, other: np.ndarray, penalty_per_dof: float) -> tuple[float, float]:
    """Two explanations' whitened held-out residuals (``named``, ``other``) against the model
    before them (``base``): the score margin within which they cannot be told apart (the larger
    of one degree of freedom's price and twice the noise of their score difference, which is
    2 |d| for d the difference of the residuals) and the overlap of their changes (the squared
    cosine of the two changes of the prediction)."""
    diff = named - other
    needed = max(penalty_per_dof, 4.0 * float(np.sqrt(diff @ diff)))
    a, b = base - named, base - other
    denom = float(a @ a) * float(b @ b)
    overlap = float(a @ b) ** 2 / denom if denom > 0 else 0.0
    return needed, overlap


def _why_named(gap: float) -> str:
    """Why the named reading of an "A or B" is named: ``gap`` is the other's score less its own."""
    return "for its lower score" if gap >= 0 else "as the simpler reading (its score is the higher)"


def reading(effect: str, form: str = "") -> str:
    """An effect as a reading of the data: its name, its form, and for a generic form the
    channel it calibrates ("physical X or a calibration of channel Y")."""
    eff = EFFECTS.get(effect)
    what = [form] if form else []
    if eff is not None and eff.generic:
        what.append(f"a calibration of the {eff.calibrates} channel")
    return effect + (f" ({'; '.join(what)})" if what else "")


def _same_residual_text(effect: str, form: str, other: str, other_form: str, gap: float, needed: float,
                        overlap: float) -> str:
    return (f"{reading(effect, form)} or {reading(other, other_form)}: the held-out data cannot tell them apart (their "
            f"held-out scores differ by {gap:.1f}, less than {needed:.1f}: the larger of one degree of freedom's "
            f"price and twice the noise of that difference; {100 * overlap:.0f} % of what one changes the other "
            f"changes too); {effect} is named {_why_named(gap)}")


def sets_alike(model: Any, data: HeldOutData, causes: Sequence[str], params: dict, score: float,
               others: Sequence[tuple[float, Sequence[str], dict]], penalty_per_dof: float, *,
               said: set[str] = frozenset()) -> list[Ambiguity]:
    """The other sets of causes the search found (``(score, causes, params)``) that the held-out
    data cannot tell from the chosen set (``causes`` at ``params``, of held-out ``score``): by
    :func:`same_residual`'s margin, the larger of one degree of freedom's price and twice the
    noise of the score difference. A set already said as one cause's alternative (``said``) is
    not said again."""
    out: list[Ambiguity] = []
    base = data.whitened_residual(model.predict({}), "test")
    named = data.whitened_residual(model.predict(dict(params)), "test")
    label = " + ".join(causes)
    seen = {tuple(sorted(causes))} | {(o,) for o in said}
    for other_score, other_causes, other_params in others:
        key = tuple(sorted(other_causes))
        if not other_causes or key in seen:
            continue
        seen.add(key)
        fit_other = data.whitened_residual(model.predict(dict(other_params)), "test")
        needed, overlap = _likeness(base, named, fit_other, penalty_per_dof)
        gap = float(other_score - score)
        if gap >= needed:
            continue
        other = " + ".join(other_causes)
        said_as = " + ".join(reading(e) for e in causes), " + ".join(reading(e) for e in other_causes)
        differ = [e for e in causes if e not in other_causes] + [e for e in other_causes if e not in causes]
        sep = separation(differ[0], differ[-1]) if differ else separation(label, other)
        out.append(Ambiguity(
            readings=(label, other), test=SETS_ALIKE,
            figures={"score_gap": gap, "needed": needed, "overlap": overlap}, separating=sep,
            text=(f"{said_as[0]} or {said_as[1]}: the held-out data cannot tell these sets of causes apart (their held-out "
                  f"scores differ by {gap:.1f}, less than {needed:.1f}: the larger of one degree of freedom's price "
                  f"and twice the noise of that difference); {label} is named {_why_named(gap)}; a capture that "
                  f"would: {sep.text}")))
    return out


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


def round_ambiguities(selection: Selection, model: Any, data: HeldOutData, *, block_px: int = 8) -> list[Ambiguity]:
    """In each round that chose an effect, the best and the next two whose held-out score
    difference is not above its standard error over the held-out blocks."""
    out: list[Ambiguity] = []
    for i, rnd in enumerate(selection.rounds):
        if len(rnd) < 2 or not rnd[0].significant:
            continue
        best = rnd[0]
        for other in rnd[1:3]:
            diff, se = score_difference(model, data, best, other, block_px)
            if diff > se:  # told apart (equal predictions: diff = se = 0, not told apart)
                continue
            sep = separation(best.effect, other.effect)
            out.append(Ambiguity(
                readings=(best.effect, other.effect), forms=(best.form, other.form), test=ROUND_SCORE,
                figures={"score_difference": diff, "standard_error": se}, separating=sep, round=i + 1,
                text=(f"round {i + 1}: {best.effect} or {other.effect}, this capture cannot tell them apart "
                      f"(held-out score difference {diff:.1f} is below its standard error {se:.1f}); "
                      f"a capture that would: {sep.text}")))
    return out


def shape_ambiguities(causes: Sequence[str], *, geometry_from_depth: bool = True) -> list[Ambiguity]:
    """Each named cause that is a pattern fixed to the pixels (``Effect.mimicked_by_shape``):
    from one pose a surface shape the twin lacks looks the same (the data hold no second view
    to tell); said for every session, since one view cannot separate a sensor pattern from a
    scene surface."""
    why = ("the planes were fitted to the same depth" if geometry_from_depth
           else "one view of the scene cannot tell a pattern of the pixels from a surface the twin places differently")
    out = []
    for c in causes:
        looks = getattr(EFFECTS.get(c), "mimicked_by_shape", "")
        if looks:
            out.append(Ambiguity(
                readings=(c, SURFACE_SHAPE), test=ONE_VIEW, figures={"score_difference": None, "standard_error": None},
                separating=SHAPE_SEPARATION,
                text=(f"{c} or a surface shape the twin lacks, this capture cannot tell them apart: {why}, and "
                      f"{looks}; a capture that would: {SHAPE_SEPARATION.text}")))
    return out


# ------------------------------------------------------------------ all of them, once
@dataclass
class Ambiguities:
    """Every "A or B" of a diagnosis, in one list, and the views diagnosis.json keeps."""

    items: list[Ambiguity] = field(default_factory=list)

    def alternatives(self, causes: Sequence[str]) -> dict[str, list[Ambiguity]]:
        """Per named cause, the other families that explain the same residual (``alternatives``)."""
        out: dict[str, list[Ambiguity]] = {}
        for a in self.items:
            if a.test == SAME_RESIDUAL and a.effect in causes:
                out.setdefault(a.effect, []).append(a)
        return out

    @property
    def observed(self) -> list[Ambiguity]:
        """The rounds' and the one-view ambiguities (``observability.ambiguous``)."""
        return [a for a in self.items if a.test != SAME_RESIDUAL]


def ambiguities(selection: Selection, causes: Sequence[str], model: Any, data: HeldOutData, *, block_px: int = 8,
                geometry_from_depth: bool = True) -> Ambiguities:
    """Every "A or B" for a decision naming ``causes``: the other families the selection found
    explaining the same residual as each cause, the rounds' runners-up within their standard
    error, and the one-view shapes of the causes fixed to the pixels."""
    items = [a for e in causes for a in selection.alternatives.get(e, ())]
    items += round_ambiguities(selection, model, data, block_px=block_px)
    items += shape_ambiguities(causes, geometry_from_depth=geometry_from_depth)
    return Ambiguities(items)
