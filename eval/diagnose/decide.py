"""How a diagnosis decides, after the selection: ordered pure rules over the selection's record,
with a ledger of what is named and what is not, and why.

:func:`decide` takes the selection's result (read, never changed) and applies :data:`RULES`,
each a function ``State -> State``, in this order:

1. :func:`extended_scene_keeps_gain`: the extended scene, as it will be written and read
   back, must keep the gain that named its causes; else they are rejected ("fitted but not
   named") and the extended scene is the base;
2. :func:`scene_does_not_match`: a residual organised by the scene's objects and edges that
   what was found cannot explain (:class:`Judge`, the geometry test) names nothing; the
   verdict stays the reading of the set that was fitted;
3. :func:`search_limit`: a partial explanation at ``max_effects`` says the search stopped there;
4. :func:`accounted_channels`: a cause that puts a part into a channel the base twin had
   clean is accounted (a note: the explanation is partial there), never unnamed;
5. :func:`drift_test`: the per-frame drift fitted on top of the causes (when searched);
6. :func:`drift_alone`: the drift fitted alone explains the frames as well: the static causes
   only took up its mean and are rejected;
7. :func:`drift_verdict`: a named drift is the verdict where nothing else was, a note otherwise;
8. :func:`a_or_b`: every "A or B" of the causes (:func:`tofhil.eval.diagnose.ambiguity.ambiguities`);
9. :func:`fitted_too_small`: with nothing named, what the selection fitted but found too small.

The verdict is made once, from the final state (:func:`finish`); the notes that need the
held-out measurement of the final set (an unweighted RMSE made worse, unwrapping errors,
defects) are added by :func:`with_measurement`. Every test the rules use is
:mod:`tofhil.eval.diagnose.verdict`'s (one false-alarm rate, ALPHA). Changing how a verdict is
decided is this module, with the tests in that one (docs/diagnose.md, "How a diagnosis decides").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from tofhil.eval.diagnose import verdict as V
from tofhil.eval.diagnose.ambiguity import Ambiguities, ambiguities
from tofhil.eval.diagnose.channels import prediction_readings
from tofhil.eval.diagnose.geometry import GeometryEvidence, geometry_evidence
from tofhil.eval.diagnose.heldout import HeldOutData, depth_from_signal
from tofhil.eval.diagnose.linear_forms import MAP_EFFECT, fit_frame_drift
from tofhil.eval.diagnose.selection import Selection
from tofhil.eval.diagnose.structure import edge_mask
from tofhil.eval.metrics import core as M

#: The name of the per-frame drift form among the candidates (it is not a scene effect).
DRIFT = "drift"
distance_defined = V.distance_defined


# =============================================================================================
# the judge: the reading of a candidate set on the held-out data
# =============================================================================================
@dataclass(frozen=True)
class Reading:
    """What the held-out data say of one prediction: the verdict's reading of it, each
    channel's and object's misfit, the channels made worse and the geometry test."""

    verdict: V.Verdict
    channels: dict[str, tuple[float, int]]
    objects: dict[str, dict[str, Any]]
    worse: list[str]
    geometry: GeometryEvidence | None


class Judge:
    """The reading of a prediction of the held-out data, with its per-channel and per-object misfits."""

    def __init__(self, data: HeldOutData, selection: Selection, base_pred: np.ndarray, object_id: np.ndarray,
                 object_names: dict[int, str], sizes: V.EffectSize | None = None) -> None:
        self.data, self.selection, self.object_id, self.object_names = data, selection, object_id, object_names
        self.base_pred, self.sizes = base_pred, sizes
        self.nu = V.noise_dof(data)
        self.n = max(data.n_values("test"), 1)
        self.objects_before = V.object_misfits(data, base_pred, self.nu, object_id, object_names)
        # what every geometry test of this diagnosis shares: the measured depth, its noise, the edges
        self._d_meas = depth_from_signal(data.s_test[:data.n_freq], data.freq_hz)
        self._sigma_depth, _ = V.channel_sigmas(data)
        self._edges = edge_mask(self._d_meas, data.usable, object_id)
        self.geometry_base = self.organised_by_geometry(base_pred)

    def organised_by_geometry(self, prediction: np.ndarray) -> GeometryEvidence | None:
        """Whether the held-out depth residual left by ``prediction`` is organised by the scene's
        objects and edges (:mod:`tofhil.eval.diagnose.geometry`)."""
        data = self.data
        residual = M.wrapped_difference(self._d_meas, depth_from_signal(prediction[:data.n_freq], data.freq_hz),
                                        data.unambiguous_range_m)
        pixels = data.test_pixels & distance_defined(data, prediction)
        limit = V.unwrap_limit_m(data)
        if limit is not None:
            # pixels unwrapped to another interval carry no comparable depth (as in every figure)
            with np.errstate(invalid="ignore"):
                pixels &= np.abs(residual) <= limit
        return geometry_evidence(residual, self._sigma_depth, pixels, self.object_id, self.object_names, self._edges,
                                 V.ALPHA)

    def read(self, after_pred: np.ndarray, causes: Sequence[str]) -> Reading:
        data, selection = self.data, self.selection
        ch_after = V.channel_chi2(data, after_pred)
        worse = V.worse_channels(selection.channels_before, ch_after)
        if self.sizes is not None and causes:
            # a channel whose RMSE gains a systematic part is worse in its own units too
            worse = sorted(set(worse) | {c for c, g in self.sizes.compare(self.base_pred, after_pred).items()
                                         if g.worse})
        objects_after = V.object_misfits(data, after_pred, self.nu, self.object_id, self.object_names)
        after = self.organised_by_geometry(after_pred) if causes else self.geometry_base
        # the geometry is wrong where the base twin's residual is organised by objects and edges
        # and the fitted set leaves it so; a pattern the fitted set alone puts there is its own
        if after is not None and not (self.geometry_base and self.geometry_base.organised):
            after = dataclasses.replace(after, organised=False, base_organised=False)
        v = V.verdict(searched=selection.searched, causes=list(causes), n_values=self.n, nu=self.nu,
                      before_per_value=selection.baseline_chi2_test / self.n,
                      after_per_value=data.chi2(after_pred, "test") / self.n, worse=worse,
                      objects_before=self.objects_before, objects_after=objects_after, pinned=selection.at_bounds,
                      rejected_for_channels=selection.rejected_for_channels, geometry=after)
        return Reading(v, ch_after, objects_after, worse, after)


# =============================================================================================
# the ledger and the state the rules pass on
# =============================================================================================
@dataclass(frozen=True)
class Cause:
    """An effect named: its form, its fitted values (as diagnosis.json gives them) and the
    figures of the round that chose it."""

    effect: str
    form: str
    params: dict[str, Any]
    figures: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "form": self.form, "params": self.params, "figures": self.figures}


@dataclass(frozen=True)
class Rejected:
    """Effects fitted but not named: the rule that rejected them, what it says, its figures."""

    effects: tuple[str, ...]
    rule: str
    reason: str
    figures: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {"effects": list(self.effects), "rule": self.rule, "reason": self.reason, "figures": self.figures}


@dataclass(frozen=True)
class Context:
    """What the rules read: the selection (never changed), the data, the twin, the judge, and
    the extended scene's prediction of a set of fitted effects (in memory: nothing is written
    before the decision is made)."""

    selection: Selection
    data: HeldOutData
    model: Any
    judge: Judge
    sizes: V.EffectSize
    base_pred: np.ndarray
    #: fitted values -> (the extended scene's twin, its prediction), as the file will read back
    extended: Callable[[dict[str, dict[str, Any]]], tuple[Any, np.ndarray]]
    max_effects: int
    want_drift: bool = False
    block_px: int = 8
    geometry_from_depth: bool = False

    @property
    def penalty(self) -> float:
        return float(np.log(self.judge.n))


@dataclass(frozen=True)
class State:
    """The decision so far. ``causes``/``params`` and ``model``/``prediction`` are the set the
    extended scene holds and its prediction, ``reading`` the held-out reading of it; ``draft``
    is the reading the verdict will be made from (the set fitted, for a scene that does not
    match; the drift, where it is the verdict); ``notes`` are the rules' own, in order."""

    ctx: Context = field(repr=False, compare=False)
    causes: tuple[str, ...]
    params: dict[str, dict[str, Any]]
    model: Any
    prediction: np.ndarray
    reading: Reading
    draft: V.Verdict
    rejected: tuple[Rejected, ...] = ()
    notes: tuple[str, ...] = ()
    drift: Any = None
    #: The named drift is the verdict (nothing else was).
    drift_is_verdict: bool = False
    ambiguities: Ambiguities = field(default_factory=Ambiguities)

    def with_notes(self, *lines: str) -> State:
        return dataclasses.replace(self, notes=self.notes + tuple(lines))

    def named(self, causes: Sequence[str], params: dict[str, dict[str, Any]], *, keep_draft: bool = False,
              **changes: Any) -> State:
        """The state naming another set: predicted and read again (the draft too, unless kept)."""
        model, pred = self.ctx.extended(params)
        reading = self.ctx.judge.read(pred, causes)
        draft = self.draft if keep_draft else reading.verdict
        return dataclasses.replace(self, causes=tuple(causes), params=params, model=model, prediction=pred,
                                   reading=reading, draft=draft, **changes)


Rule = Callable[[State], State]


# =============================================================================================
# the rules, in order
# =============================================================================================
def extended_scene_keeps_gain(s: State) -> State:
    """The extended scene as written and read back must keep the gain the selection saw."""
    if not s.causes:
        return s
    sizes = s.ctx.sizes.compare(s.ctx.base_pred, s.prediction)
    if V.EffectSize.worth_naming(sizes):
        return s
    reason = ("fitted but not named: " + ", ".join(s.causes) + " (as the extended scene: "
              + V.EffectSize.describe(sizes) + "; " + V.effect_size_rule() + ")")
    gone = Rejected(s.causes, "extended scene loses the gain", reason, {c: g.to_json() for c, g in sizes.items()})
    return s.named([], {}, rejected=s.rejected + (gone,), notes=s.notes + (reason,))


def scene_does_not_match(s: State) -> State:
    """No effect is named on a scene that does not match: the extended scene is the base, the
    verdict the reading of the set fitted (what it would have done, on the held-out pixels: a
    lower misfit can come with a worse depth RMSE, the misfit weighs each pixel by its noise)."""
    if not s.causes or s.reading.verdict.kind is not V.Kind.SCENE_MISMATCH:
        return s
    ctx = s.ctx
    n = ctx.judge.n
    before, after = ctx.data.chi2(ctx.base_pred, "test") / n, ctx.data.chi2(s.prediction, "test") / n
    sizes = ctx.sizes.compare(ctx.base_pred, s.prediction)
    reason = ("fitted but not named: " + ", ".join(s.causes)
              + f" (with them, held-out misfit {before:.2f} -> {after:.2f} per value; "
              + V.EffectSize.describe(sizes) + ")")
    gone = Rejected(s.causes, "scene does not match", reason,
                    {"misfit_before_per_value": before, "misfit_after_per_value": after}
                    | {c: g.to_json() for c, g in sizes.items()})
    return s.named([], {}, keep_draft=True, rejected=s.rejected + (gone,), notes=s.notes + (reason,))


def search_limit(s: State) -> State:
    """The search stopped at its limit, not because nothing significant was left: the rest may
    be a further effect (the emulated TOFcam635 hides three; with max_effects 2 its clock-skew
    pattern was left out)."""
    m = s.ctx.max_effects
    if s.draft.kind is V.Kind.PARTLY_EXPLAINED and len(s.causes) >= m:
        return s.with_notes(f"the search stopped at max_effects = {m}: the excess left may hold a further effect "
                            "(diagnose again with a larger --max-effects)")
    return s


def accounted_channels(s: State) -> State:
    """A cause that puts a part into a channel the base twin had clean is accounted, not unnamed."""
    if not s.causes:
        return s
    moved = moved_clean_channels(s.ctx.model, s.ctx.data, s.ctx.selection, s.ctx.base_pred)
    return s.with_notes(*(f"{c} moves a channel where the base twin's residual had nothing beyond noise ("
                          + "; ".join(texts) + "): the explanation is partial there"
                          for c, texts in moved.items() if c in s.causes))


def drift_test(s: State) -> State:
    """The per-frame drift fitted on top of the causes named (when it is searched)."""
    if not s.ctx.want_drift:
        return s
    return dataclasses.replace(s, drift=fit_frame_drift(s.ctx.model, s.ctx.data, s.params, s.ctx.penalty))


def drift_alone(s: State) -> State:
    """The drift fitted on the base twin explains the frames as well as the causes with the
    drift on top (their parameters charged at ln n each): the static causes only took up the
    drift's mean. A new set: the notes said of the old one go."""
    drift, ctx = s.drift, s.ctx
    if drift is None or not drift.named or not s.causes:
        return s
    alone = fit_frame_drift(ctx.model, ctx.data, {}, ctx.penalty)
    if alone is None or not alone.named:
        return s
    k = sum(len(v) for e, v in s.params.items() if e != MAP_EFFECT)
    k += float(ctx.selection.details.get(MAP_EFFECT, {}).get("dof", 0.0)) if MAP_EFFECT in s.params else 0.0
    if alone.chi2_drift > drift.chi2_drift + ctx.penalty * max(k, 1.0):
        return s
    a, w = alone.chi2_drift / alone.n_values, drift.chi2_drift / drift.n_values
    reason = ("fitted but not named: " + " + ".join(s.causes) + " (the per-frame drift alone explains the frames "
              f"as well: held-out misfit {a:.3f} per value against {w:.3f} with them; a static effect fitted to "
              "frames that drift takes up the drift's mean)")
    gone = Rejected(s.causes, "drift alone explains", reason,
                    {"misfit_drift_alone_per_value": a, "misfit_with_causes_per_value": w})
    return s.named([], {}, rejected=s.rejected + (gone,), notes=(reason,), drift=alone)


def drift_verdict(s: State) -> State:
    """The frames' mean hides a drift (it inflates the frame-to-frame noise instead): a named
    drift is the verdict where nothing else was, on the held-out pixels of every frame."""
    drift, judge = s.drift, s.ctx.judge
    if drift is None or not drift.named:
        return s
    if s.draft.kind in (V.Kind.WITHIN_NOISE, V.Kind.UNEXPLAINED):
        draft = V.verdict(searched=True, causes=[DRIFT], n_values=drift.n_values, nu=judge.nu,
                          before_per_value=drift.chi2_static / drift.n_values,
                          after_per_value=drift.chi2_drift / drift.n_values, worse=[],
                          objects_before=judge.objects_before, objects_after=judge.objects_before, pinned={},
                          rejected_for_channels=[])
        s = dataclasses.replace(s, draft=draft, drift_is_verdict=True)
    return s.with_notes(drift.text)


def channel_beyond_noise(s: State) -> State:
    """The verdict's misfit test is over every held-out value at once; a part confined to one
    channel (a frequency's gain, the taps' alternating part, the offset) is tested on its own by
    the channel table at the same false-alarm rate (family-wise). A reading beyond its noise
    there is a residual: the base twin is not "within noise" (the verdict is "unexplained", the
    reading said), nor is a set "explained" that leaves it ("partly explained"). The frame
    readings are the drift's when it is named; the noise reading compares the scatter with the
    sensor's model and is no residual."""
    from tofhil.eval.diagnose.channels import residual_by_channel, sensor_noise_variance

    if s.draft.kind not in (V.Kind.WITHIN_NOISE, V.Kind.EXPLAINED) or s.drift_is_verdict:
        return s
    data = s.ctx.data
    taps = getattr(s.model, "taps", None)
    measured = getattr(data, "taps_test", None)
    try:
        table = residual_by_channel(data, s.prediction, taps_measured=measured,
                                    taps_predicted=taps({}) if callable(taps) and measured is not None else None,
                                    model_variance=sensor_noise_variance(data))
    except (AttributeError, ValueError):
        return s
    skip = {"noise"} | ({"frame"} if s.drift is not None and s.drift.named else set())
    beyond = [r for r in table.readings if r.significant and r.channel not in skip]
    if not beyond:
        return s
    kind = V.Kind.UNEXPLAINED if s.draft.kind is V.Kind.WITHIN_NOISE else V.Kind.PARTLY_EXPLAINED
    said = "; ".join(f"{r.text} (z {r.z:+.1f})" for r in beyond)
    text = (s.draft.text + f"; but a part confined to one channel is beyond its noise (|z| > "
            f"{beyond[0].z_threshold:.2f}, the channel table's family-wise test at the same false-alarm rate): "
            + said)
    draft = dataclasses.replace(s.draft, kind=kind, text=text,
                                worse_channels=sorted(set(s.draft.worse_channels) | {r.channel for r in beyond}))
    return dataclasses.replace(s, draft=draft)


def a_or_b(s: State) -> State:
    """Every "A or B" of the causes named: each is said, with the capture that separates them."""
    ctx = s.ctx
    amb = ambiguities(ctx.selection, s.causes, ctx.model, ctx.data, block_px=ctx.block_px,
                      geometry_from_depth=ctx.geometry_from_depth)
    said = [a.text for e in s.causes for a in amb.alternatives(s.causes).get(e, ())]
    said += [a.text for a in amb.observed if a.round is None]  # a pattern of the pixels or a surface
    return dataclasses.replace(s, ambiguities=amb).with_notes(*said)


def fitted_too_small(s: State) -> State:
    """With nothing named, what the selection found significant but too small is said."""
    too_small = s.ctx.selection.too_small
    if not s.causes and too_small and s.draft.kind in (V.Kind.UNEXPLAINED, V.Kind.SCENE_MISMATCH):
        return s.with_notes("fitted but not named: " + "; ".join(too_small.values()))
    return s


#: The rules, in the order :func:`decide` applies them.
RULES: tuple[Rule, ...] = (extended_scene_keeps_gain, scene_does_not_match, search_limit, accounted_channels,
                           drift_test, drift_alone, drift_verdict, channel_beyond_noise, a_or_b, fitted_too_small)


# =============================================================================================
# the decision
# =============================================================================================
@dataclass(frozen=True)
class Decision:
    """What the diagnosis names, what it fitted but does not name and why, and the verdict."""

    causes: list[Cause]
    rejected: list[Rejected]
    verdict: V.Verdict
    #: The fitted values of the causes, as the extended scene holds them.
    params: dict[str, dict[str, Any]]
    #: The extended scene's twin and its held-out prediction, and the reading of it.
    model: Any
    prediction: np.ndarray
    reading: Reading
    drift: Any
    drift_is_verdict: bool
    ambiguities: Ambiguities

    @property
    def names(self) -> list[str]:
        return [c.effect for c in self.causes]

    def ledger(self) -> dict[str, Any]:
        return {"rules": [r.__name__ for r in RULES], "causes": [c.to_json() for c in self.causes],
                "rejected": [r.to_json() for r in self.rejected],
                "drift": None if self.drift is None else {"named": bool(self.drift.named),
                                                           "is_verdict": self.drift_is_verdict}}


def fitted_values_json(effect: str, values: Mapping[str, Any], details: Mapping[str, Any] | None = None
                       ) -> dict[str, Any]:
    """An effect's fitted values as diagnosis.json gives them: a closed-form map's figures (the
    map is in its .npy file), else the parameters."""
    from tofhil.eval.diagnose.twin_model import to_effect_values

    return dict(details) if details else to_effect_values(effect, dict(values))


def _cause(selection: Selection, effect: str, params: Mapping[str, Any]) -> Cause:
    figures: dict[str, Any] = {}
    for i, rnd in enumerate(selection.rounds):
        c = next((c for c in rnd if c.effect == effect and c.significant), None)
        if c is not None and i < len(selection.causes) and selection.causes[i] == effect:
            figures = {"round": i + 1, "delta_score": c.delta_score, "relative_gain": c.relative_gain,
                       "dof": round(c.dof, 2)}
    return Cause(effect, selection.forms.get(effect, ""),
                 fitted_values_json(effect, params, selection.details.get(effect)), figures)


#: The rule of the selection that fitted an effect but did not name it (in the ledger beside
#: the decision's own rules).
TOO_SMALL = "selection: too small to name"


def _too_small(selection: Selection) -> list[Rejected]:
    """The selection's own rejections: significant in misfit, too small (or a channel worse) in
    the channels' own units (the words say so at the first round that found it), with the figures
    of its candidate in the rounds."""
    out = []
    for e, why in selection.too_small.items():
        tried = [c for rnd in selection.rounds for c in rnd if c.effect == e]
        c = next((c for c in tried if c.rmse), tried[0] if tried else None)
        figures = {} if c is None else {"delta_score": c.delta_score, "relative_gain": c.relative_gain,
                                        "rmse": {ch: g.to_json() for ch, g in c.rmse.items()}}
        out.append(Rejected((e,), TOO_SMALL, why, figures))
    return out


def finish(s: State) -> Decision:
    """The decision from the final state: the verdict made once, its reading's notes then the rules'."""
    verdict = dataclasses.replace(s.draft, notes=list(s.draft.notes) + list(s.notes))
    sel = s.ctx.selection
    return Decision(causes=[_cause(sel, e, s.params[e]) for e in s.causes],
                    rejected=_too_small(sel) + list(s.rejected),
                    verdict=verdict, params=s.params, model=s.model, prediction=s.prediction, reading=s.reading,
                    drift=s.drift, drift_is_verdict=s.drift_is_verdict, ambiguities=s.ambiguities)


def decide(ctx: Context, rules: Sequence[Rule] = RULES) -> Decision:
    """Apply ``rules`` in order to the selection's record (read, never changed) and make the verdict."""
    sel = ctx.selection
    model, pred = ctx.extended(sel.params)
    reading = ctx.judge.read(pred, sel.causes)
    s = State(ctx=ctx, causes=tuple(sel.causes), params=dict(sel.params), model=model, prediction=pred,
              reading=reading, draft=reading.verdict)
    for rule in rules:
        s = rule(s)
    return finish(s)


def with_measurement(decision: Decision, gain: Mapping[str, Mapping[str, float]], defects: str | None) -> Decision:
    """The notes that need the held-out measurement of the extended scene: an unweighted RMSE a
    named cause leaves worse (the misfit weighs each pixel by its noise and caps outliers; the
    RMSE does neither), pixels unwrapped to the wrong interval, and the defects (first)."""
    notes = list(decision.verdict.notes)
    if decision.causes:
        for k, label, scale, unit in (("depth_rmse_m", "depth RMSE", 1e3, " mm"),
                                      ("amplitude_rmse", "amplitude RMSE", 1.0, "")):
            b, a = gain[k]["before"], gain[k]["after"]
            if np.isfinite(a) and np.isfinite(b) and a > 1.005 * b:  # (0.5 %: not a rounding)
                notes.append(f"held-out {label} {b * scale:.4g} -> {a * scale:.4g}{unit} is worse after the fit: "
                             "the misfit that chose the cause weighs pixels by their noise and caps outliers, "
                             "the RMSE does not")
    for key, label in (("before", "with the base twin"), ("after", "with the extended twin")):
        n_wrong = int(gain["unwrap_error_pixels"][key])
        if n_wrong:
            notes.append(f"{n_wrong} held-out pixels unwrapped to the wrong interval {label} (a phase "
                         "inconsistency between the frequencies, or noise in them): mapped, not in the depth "
                         f"figures ({int(gain['depth_compared_pixels'][key])} pixels compared)")
    if defects:
        notes.insert(0, defects)
    return dataclasses.replace(decision, verdict=dataclasses.replace(decision.verdict, notes=notes))


# =============================================================================================
# a figure the rules read
# =============================================================================================
def moved_clean_channels(model: Any, data: HeldOutData, selection: Selection,
                          base_pred: np.ndarray) -> dict[str, list[str]]:
    """The causes that put a part into a channel where the base twin's residual has none: a
    reading within noise with the base twin and beyond it with every cause, that comes back
    within noise without that cause (each effect's signature read off its fitted change,
    against the residual's). Judged on the final model: one cause may move a channel that a
    later one takes back (stray light alone moves the demo's gain by -0.9 %, the final model
    by 0.0 %)."""
    if not selection.causes or not hasattr(data, "freq_hz"):
        return {}
    before = prediction_readings(data, base_pred)
    clean = {n for n, r in before.items() if not r.significant}
    after = prediction_readings(data, model.predict(selection.params))
    moved = [n for n in clean if after[n].significant]
    out: dict[str, list[str]] = {}
    if not moved:
        return out
    for c in selection.causes:
        without = prediction_readings(data, model.predict({e: v for e, v in selection.params.items() if e != c}))
        back = [after[n].text for n in moved if not without[n].significant]
        if back:
            out[c] = back
    return out
