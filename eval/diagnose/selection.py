"""Greedy, held-out model selection over a library of parametric effects.

The forward model predicts the complex signal ``S[F, H, W]`` (DN) for a set of active effects
and their parameters. An effect's parameters are fitted by weighted least squares on the
training data; the fit is scored on held-out data with a BIC-like penalty:

    score = chi2_heldout + k * ln(n_heldout)

(k the number of fitted parameters, n the number of held-out real values). Effects are added
one at a time, the best first, while the held-out score improves by more than the penalty
and by a stated fraction of the current misfit. The change of every channel (depth,
amplitude, offset: ``verdict.channel_chi2``) is accounted and reported; a channel that rises
means the explanation is partial, never that a form which lowers the total is rejected. ``k`` is an effect's effective number of degrees of freedom
(``EffectSpec.dof``; its parameter count unless a regularised flexible form says less).
An effect with a ``closed_form`` fit (a map: many values, linear in the residual) is fitted
by it instead of the optimiser, and its ``k`` is the effective degrees of freedom that fit
reports (the trace of its hat matrix). A flexible form of an effect is chosen over its simple
form only when it earns its freedom on held-out data and the data identify its extra
parameters (:mod:`tofhil.eval.diagnose.identifiability`); chosen forms are tested again at the final
values. Nothing here knows what an effect does.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Protocol, Sequence

import numpy as np
from scipy.optimize import least_squares

from tofhil.content_cache import LRUCache, content_digest
from tofhil.eval.diagnose.heldout import HUBER_SIGMA, HeldOutData, huber, predict_fit
from tofhil.eval.diagnose.form_prior import regularise_form
from tofhil.eval.diagnose.ambiguity import Ambiguity, same_residual, sets_alike
from tofhil.eval.diagnose.identifiability import Identifiability, assess_form, param_group
from tofhil.eval.diagnose.verdict import ChannelGain, EffectSize, channel_chi2, worse_channels
from tofhil.sim.effects import EFFECTS
from tofhil.sim.memory import release_free_memory

EffectParams = dict[str, dict[str, float]]
#: How many branches the search also follows (:func:`greedy_select`): the runners-up of its
#: rounds closest in score to the cause chosen; two more searches at most, each over its
#: round's significant effects only.
EXTRA_STARTS = 2
#: Refits of a chosen set without one cause kept for reuse (:meth:`_GreedySearch._refit_without`;
#: each holds a prediction, a few MB at 170 x 170 bins).
MAX_KEPT_REFITS = 48
#: A fit ends when a step lowers its training misfit (sum of Huber's rho) by less than this
#: (scipy's relative ``ftol`` scaled by the misfit where the fit starts, at least 1e-6): a two-hundredth of
#: the smallest price a cause pays (one degree of freedom, log of the held-out values: 7 at
#: 1000 values), so no decision moves by it.
FIT_TOLERANCE = 0.05
#: How a partial form is named: its flexible form, this, and the parameter groups left out.
PARTIAL = " without "


@dataclass(frozen=True)
class FitParam:
    """One fitted parameter: its "off" value, bounds, and a typical step for the optimiser."""

    name: str
    off: float
    lo: float
    hi: float
    scale: float
    #: An angle whose range is one period: its bounds are the same value, never a limit.
    periodic: bool = False


@dataclass(frozen=True)
class EffectSpec:
    """The fitted parameters of one effect and extra starting points for a multi-start fit.

    Starting points matter where "off" sits on a flat spot of the misfit: at zero weight a
    stray-light lobe's width is irrelevant, at zero amplitude a harmonic's phase is.
    """

    params: tuple[FitParam, ...]
    starts: tuple[dict[str, float], ...] = ()
    #: Effective degrees of freedom for the penalty (None: the number of parameters).
    dof: float | None = None
    #: The form this spec fits ("" the effect's simple form).
    form: str = ""
    #: Flexible forms of the same effect, from the least to the most flexible: each is fitted
    #: beside this (simple) form and replaces it only when it earns its extra degrees of
    #: freedom on held-out data (:func:`choose_form`).
    forms: tuple["EffectSpec", ...] = ()
    #: A closed-form fit on the training data instead of the optimiser (flexible map forms):
    #: ``(model, data, current effects, penalty per dof) -> (values, effective dof, details)``.
    closed_form: Callable[..., tuple[dict[str, Any], float, dict[str, Any]]] | None = None
    #: The form's prior (``Effect.roughness``): fitted values -> a vector zero for its
    #: smoothest shape; None for none.
    roughness: Callable[[Mapping[str, float]], np.ndarray] | None = None
    #: The prior's strength chosen on held-out data (:mod:`tofhil.eval.diagnose.form_prior`): every fit
    #: of this spec adds ``strength * |roughness|^2`` to its misfit (0: no prior).
    strength: float = 0.0
    #: A calibration form of a channel rather than a physical cause (``Effect.generic``): being
    #: flexible, it can take alone in one round what physical causes explain together, so where
    #: the search takes one it also searches from the best physical cause of that round.
    generic: bool = False

    @property
    def k(self) -> float:
        return float(len(self.params) if self.dof is None else self.dof)

    def variant(self, form: str) -> "EffectSpec":
        """The spec of ``form`` (this one or one of its flexible forms, or a partial form of
        one: ``"harmonics without h5"``, :meth:`without`)."""
        base, _, dropped = form.partition(PARTIAL)
        spec = next(s for s in (self,) + tuple(self.forms) if s.form == base)
        return spec.without(dropped.split(", ")) if dropped else spec

    def without(self, groups: Sequence[str]) -> "EffectSpec":
        """A partial form: this form with the parameter groups ``groups`` left out (held at
        their off values; groups as :func:`tofhil.eval.diagnose.identifiability.param_group`)."""
        base, _, before = self.form.partition(PARTIAL)
        dropped = sorted(set(groups) | set(before.split(", ") if before else ()))
        return dataclasses.replace(
            self, params=tuple(p for p in self.params if param_group(p.name) not in dropped),
            starts=tuple({k: v for k, v in s.items() if param_group(k) not in dropped} for s in self.starts),
            form=base + PARTIAL + ", ".join(dropped), forms=())


class ForwardModel(Protocol):
    def library(self) -> Mapping[str, EffectSpec]: ...

    def predict(self, active: EffectParams) -> np.ndarray: ...


@dataclass
class Candidate:
    effect: str
    params: dict[str, float]
    chi2_train: float
    chi2_test: float
    score: float
    delta_score: float  # improvement of the held-out score over the current model (> 0: better)
    relative_gain: float  # (chi2_test(current) - chi2_test(with it)) / chi2_test(current)
    significant: bool
    n_params: int
    #: Every active effect's parameters in this trial (the earlier ones and this one).
    all_params: EffectParams = field(default_factory=dict, repr=False)
    #: Channels whose held-out misfit grew beyond their noise with this effect added.
    worse_channels: list[str] = field(default_factory=list)
    #: Fitted parameters pinned at a bound of their range (a bound that is not "off").
    at_bounds: list[str] = field(default_factory=list)
    #: Held-out misfit per channel with this effect: {channel: (chi2, n values)}.
    channels: dict[str, tuple[float, int]] = field(default_factory=dict, repr=False)
    #: The effect's form ("" its simple form, else the name of a flexible one).
    form: str = ""
    #: Effective degrees of freedom of that form (the penalty's k; a closed-form fit's own).
    dof: float = 0.0
    #: Every form tried: {form: {"chi2_test", "score", "dof", "significant"}}.
    forms: dict[str, dict[str, float | bool]] = field(default_factory=dict)
    #: What a closed-form fit reports about itself (form, strengths, parts).
    details: dict[str, Any] = field(default_factory=dict)
    #: Held-out RMSE per channel in its own units against the current model
    #: (:class:`tofhil.eval.diagnose.verdict.EffectSize`; empty when the selection checks no effect size).
    rmse: dict[str, ChannelGain] = field(default_factory=dict, repr=False)
    #: False when its gain, though significant in misfit, is too small to name or makes a
    #: channel's RMSE worse (against the current model or the base twin).
    worth_naming: bool = True
    #: Flexible forms that beat the chosen one on score but whose extra parameters the data
    #: do not identify (:mod:`tofhil.eval.diagnose.identifiability`): why each was not chosen.
    unidentified: list[Identifiability] = field(default_factory=list)
    #: A regularised form's prior strength (``EffectSpec.strength``) and what its choice on
    #: held-out data reports (:class:`tofhil.eval.diagnose.form_prior.PriorFit`); 0 and empty otherwise.
    strength: float = 0.0
    prior: dict[str, Any] = field(default_factory=dict)
    #: The whitened held-out residual with this candidate (kept to compare candidates of
    #: different families without predicting again: "A or B").
    test_residual: np.ndarray | None = field(default=None, repr=False)


@dataclass
class Selection:
    causes: list[str]
    params: EffectParams
    baseline_chi2_test: float
    final_chi2_test: float
    rounds: list[list[Candidate]] = field(default_factory=list)
    n_test: int = 0
    #: False when nothing was searched (``max_effects`` 0).
    searched: bool = True
    #: Effects whose held-out score gain was significant but that made a channel worse.
    rejected_for_channels: list[str] = field(default_factory=list)
    #: Per cause, its fitted parameters pinned at a bound of the range searched.
    at_bounds: dict[str, list[str]] = field(default_factory=dict)
    #: Per cause, the form chosen ("" the simple form).
    forms: dict[str, str] = field(default_factory=dict)
    #: Held-out misfit per channel of the base twin and of the final fit.
    channels_before: dict[str, tuple[float, int]] = field(default_factory=dict)
    channels_after: dict[str, tuple[float, int]] = field(default_factory=dict)
    #: Per cause fitted in closed form, what its fit reports (form, dof, strengths).
    details: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Effects whose misfit gain was significant but whose RMSE gain was too small to name
    #: (or made a channel's RMSE worse), with their figures.
    too_small: dict[str, str] = field(default_factory=dict)
    #: Forms not fitted in a round because the score test of the residual on their signature
    #: could not reach what naming needs (:mod:`tofhil.eval.diagnose.signature`), with figures.
    not_tried: dict[str, str] = field(default_factory=dict)
    #: The sets found by searching again without a chosen cause that replaced it (:meth:`_GreedySearch.exchange`).
    exchanges: list[str] = field(default_factory=list)
    #: Per cause, the flexible forms refused because the data do not identify their extra
    #: parameters (which ones cannot be told apart).
    unidentified: dict[str, list[Identifiability]] = field(default_factory=dict)
    #: Per cause fitted in a regularised form, its prior's strength and effective dof.
    priors: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Per cause, the other families' candidates of its round that the held-out data cannot
    #: tell from it ("A or B", :func:`tofhil.eval.diagnose.ambiguity.same_residual`).
    alternatives: dict[str, list[Ambiguity]] = field(default_factory=dict)
    #: Every set the search found (from the greedy first choice and the next significant ones)
    #: and its held-out score; the lowest score is chosen.
    searches: list[dict[str, Any]] = field(default_factory=list)

    @property
    def first_round(self) -> list[Candidate]:
        return self.rounds[0] if self.rounds else []


def _pack(active: Sequence[str], lib: Mapping[str, EffectSpec], values: EffectParams) -> np.ndarray:
    return np.array([values.get(e, {}).get(p.name, p.off) for e in active for p in lib[e].params], dtype=float)


def _unpack(active: Sequence[str], lib: Mapping[str, EffectSpec], x: np.ndarray) -> EffectParams:
    out: EffectParams = {}
    i = 0
    for e in active:
        out[e] = {}
        for p in lib[e].params:
            out[e][p.name] = float(x[i])
            i += 1
    return out


def fit(model: ForwardModel, data: HeldOutData, active: Sequence[str], start: EffectParams,
        new_effect: str | None = None, max_nfev: int = 60,
        free: Sequence[str] | None = None, lib: Mapping[str, EffectSpec] | None = None) -> tuple[EffectParams, float]:
    """Least-squares fit of the active effects' parameters on the training data (its
    evaluated pixels, :attr:`HeldOutData.fit_pixels`).

    Only the effects in ``free`` (default: all active ones) move; the others keep their
    values in ``start``. Starts from ``start`` ("off" where it is silent) and, for
    ``new_effect``, also from its extra starting points; keeps the best training fit.
    ``lib`` (default the model's library) says which parameters each effect fits: the
    form chosen for it.
    """
    lib = model.library() if lib is None else lib
    # effects without optimiser parameters (closed-form maps) keep their values
    free = [e for e in (active if free is None else free) if lib[e].params]
    fixed = {e: dict(start.get(e, {})) for e in active if e not in free}
    for e in fixed:
        for p in lib[e].params:
            fixed[e].setdefault(p.name, p.off)
    params = [p for e in free for p in lib[e].params]

    def full(x: np.ndarray) -> EffectParams:
        return {e: fixed[e] if e in fixed else _unpack(free, lib, x)[e] for e in active}

    if not params:
        return full(np.zeros(0)), data.chi2(predict_fit(model, data, full(np.zeros(0))), "fit")
    lo = np.array([p.lo for p in params])
    hi = np.array([p.hi for p in params])
    scale = np.array([p.scale for p in params])
    x0 = np.clip(_pack(free, lib, start), lo, hi)

    last: dict[str, np.ndarray] = {}

    # a regularised form's prior enters its fit as extra residuals sqrt(strength) * roughness
    priors = [(e, lib[e]) for e in free if lib[e].roughness is not None and lib[e].strength > 0.0]

    def penalty(x: np.ndarray) -> np.ndarray:
        if not priors:
            return np.zeros(0)
        values = _unpack(free, lib, x)
        return np.concatenate([np.sqrt(spec.strength) * spec.roughness(values[e]) for e, spec in priors])

    # Effects that move light between pixels (stray light) need whole frames rendered for
    # every evaluation; when they are held and the effects fitted are pixel-local, their part
    # is nearly constant over the fit (it moves by their weight times the small change the fit
    # makes): the fit pixels alone are predicted without them, plus their part at the start,
    # and each optimisation ends with the whole prediction (which the result is judged on).
    held_part: dict[str, np.ndarray] = {}
    local = getattr(model, "predict_local", None) if all(
        getattr(EFFECTS.get(e), "pixel_local", False) for e in free) else None

    def hold_at(x: np.ndarray) -> bool:
        if local is None:
            return False
        p_local = local(full(x), data.fit_pixels)
        if p_local is None:
            return False
        held_part["value"] = predict_fit(model, data, full(x)) - p_local
        return True

    def predict_x(x: np.ndarray) -> np.ndarray:
        if "value" in held_part:
            return local(full(x), data.fit_pixels) + held_part["value"]
        return predict_fit(model, data, full(x))

    def stacked(x: np.ndarray) -> np.ndarray:
        """The fit pixels' whitened residual and the priors' penalty residuals at ``x``."""
        return np.concatenate([data.whitened_residual(predict_x(x), "fit"), penalty(x)])

    def residual(x: np.ndarray) -> np.ndarray:
        r = stacked(x)
        last["x"], last["r"] = x.copy(), r
        return r

    # Forward differences with steps of a twentieth of each parameter's typical scale: scipy's
    # relative steps collapse to ~1e-8 absolute at a parameter's "off" value of zero, far too
    # small to see a rendered pose change or a picosecond delay move.
    steps = 0.05 * scale

    def jacobian(x: np.ndarray) -> np.ndarray:
        r0 = last["r"] if "x" in last and np.array_equal(last["x"], x) else residual(x)
        x0_ = x.copy()
        cols = []
        for j in range(x.size):
            h = steps[j] if x[j] + steps[j] <= hi[j] else -steps[j]
            xj = x0_.copy()
            xj[j] += h
            cols.append((stacked(xj) - r0) / h)   # (not residual(): the last point stays x's)
        return np.stack(cols, axis=1)

    starts = [x0]
    if new_effect is not None and new_effect in free:
        for extra in lib[new_effect].starts:
            trial = {e: dict(start.get(e, {})) for e in free}
            trial[new_effect].update(extra)
            starts.append(np.clip(_pack(free, lib, trial), lo, hi))
    # Screen every starting point with one evaluation; optimise from the best two.
    inner = [np.clip(x, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo)) for x in starts]
    holding = hold_at(x0)
    if len(inner) > 2:
        costs = [float(np.sum(huber(residual(x)))) for x in inner]
        inner = [inner[i] for i in np.argsort(costs)[:2]]
    best_x, best_cost = x0, np.inf
    for x_start in inner:
        for _pass in range(2 if holding else 1):
            if holding:
                last.clear()
                hold_at(x_start)  # the held part where this pass starts
            # (scipy stops when a step lowers its cost, half the misfit, by less than ftol times
            # the cost: at most FIT_TOLERANCE of misfit once the cost is below the start's; never
            # tighter than scipy's 1e-6 of it, which a misfit of 10^8 units, a twin far from the
            # data, would ask for)
            ftol = max(FIT_TOLERANCE / max(float(np.sum(huber(residual(x_start)))), 1.0), 1e-6)
            res = least_squares(residual, x_start, jac=jacobian, bounds=(lo, hi), x_scale=scale, method="trf",
                                max_nfev=max_nfev, ftol=ftol, xtol=1e-7, loss="huber", f_scale=HUBER_SIGMA)
            cost = res.cost
            if holding:
                # judged on the whole prediction; a second pass holds the part where the first ended
                held_part.clear()
                cost = 0.5 * float(np.sum(huber(stacked(res.x))))
            if cost < best_cost:
                best_x, best_cost = res.x, cost
            if not holding or np.allclose(res.x, x_start, rtol=0, atol=1e-3 * float(np.min(scale))):
                break
            # A second pass corrects for what the held part drifted by over the first (the gap
            # between the whole prediction's cost and the held one's at the end point), and wins
            # back a part of it (in the 512 x 512 benchmark 360 of a drift of 6172): a start that
            # ended worse than the best by more than twice its drift is not refined again.
            if cost - best_cost > 2.0 * abs(cost - res.cost):
                break
            x_start = res.x
    return full(best_x), 2.0 * best_cost


def pinned(spec: EffectSpec, values: Mapping[str, float], rel: float = 1e-3) -> list[str]:
    """Parameters fitted to within ``rel`` of their range from a bound that is not "off"
    (an angle over one period has no such bound)."""
    out = []
    for p in spec.params:
        if p.periodic:
            continue
        v, tol = values.get(p.name, p.off), rel * (p.hi - p.lo)
        if (abs(v - p.lo) <= tol and p.lo != p.off) or (abs(v - p.hi) <= tol and p.hi != p.off):
            out.append(p.name)
    return out


def choose_form(tried: Sequence[Candidate], min_extra_gain: float,
                identify: Callable[[Candidate], Identifiability] | None = None,
                partial: Callable[[Candidate, list[str]], Candidate] | None = None) -> Candidate:
    """The form of one effect to offer in a round, from its fits in each form (the simple
    form first, then the flexible ones from least to most flexible).

    A more flexible form replaces the current choice only when it is significant itself
    and earns its extra freedom on held-out data: its score (held-out misfit plus the
    penalty for its effective degrees of freedom) beats the current choice's, and it removes
    more than ``min_extra_gain`` more held-out misfit (the same margin an effect needs to be
    significant), and ``identify`` (when given) finds every one of its extra parameters
    determined by the data: a score margin can come from the optimiser's path or from
    parameters that another one of the form reproduces (:mod:`tofhil.eval.diagnose.identifiability`).
    A form whose extra groups are identified only in part (h3 and h7 but not h5) is tried
    again without the groups the data do not identify (``partial(candidate, groups)`` fits
    that partial form), under the same rule, until every group left is identified.
    Otherwise the simpler form stays: a flexible form that adds nothing on held-out data is
    not chosen. The chosen candidate lists every form tried in ``forms`` and the refused
    unidentified ones in ``unidentified``.
    """
    chosen = tried[0]
    refused: list[Identifiability] = []
    checked: dict[str, bool] = {}
    every = list(tried)
    for c in tried[1:]:
        while c.significant and c.score < chosen.score and chosen.chi2_test - c.chi2_test > min_extra_gain:
            if identify is not None and c.n_params:
                test = identify(c)
                checked[c.form] = test.identified
                if not test.identified:
                    refused.append(test)
                    drop = [g.group for g in test.groups if not g.identified]
                    if partial is None or len(drop) == len(test.groups):
                        break
                    c = partial(c, drop)
                    every.append(c)
                    continue
            chosen = c
            break
    for test in refused:
        if chosen.form.startswith(test.form.partition(PARTIAL)[0] + PARTIAL):
            test.partial = chosen.form
    chosen.forms = {c.form: {"chi2_test": c.chi2_test, "score": c.score, "dof": c.dof, "significant": c.significant}
                    | ({"identified": checked[c.form]} if c.form in checked else {}) for c in every}
    chosen.unidentified = refused
    return chosen


def _release_residuals(candidates: Sequence[Candidate]) -> None:
    """Drop the held-out residuals a round kept for "A or B" once it is decided: the ranking
    keeps every round's candidates, and at camera resolution each residual is megabytes."""
    for c in candidates:
        c.test_residual = None


def greedy_select(model: ForwardModel, data: HeldOutData, *, candidates: Sequence[str] | None = None,
                  max_effects: int = 3, min_relative_gain: float = 0.02,
                  progress: Callable[[str], None] | None = None, effect_size: EffectSize | None = None) -> Selection:
    """Add effects one by one while each brings a significant held-out gain.

    An effect is significant when its held-out score beats the current model's (the penalty
    for its effective degrees of freedom included), it removes at least ``min_relative_gain``
    of the current held-out misfit in excess of noise (chi2 - n): a margin against naming a
    small model difference while a large excess is unexplained. Practical significance is the
    effect size's (``effect_size``), in the channels' own units; a margin per held-out value
    (it was 0.02) hid weak but real effects on large captures, a drift of z 30 among them. The best-scoring significant effect of a round is added. A channel
    that gets worse beyond its noise is recorded on the candidate (``worse_channels``) and
    reported: it means the explanation is partial, not that the form is wrong.

    With ``effect_size`` an effect must also be worth naming in the channels' own units: its
    held-out RMSE gain reaches the minimum of some channel
    (:meth:`tofhil.eval.diagnose.verdict.EffectSize.worth_naming`).
    """
    refits = LRUCache(MAX_KEPT_REFITS)  # shared: the searches refit the same sets

    def new_search() -> _GreedySearch:
        return _GreedySearch(model, data, max_effects=max_effects, min_relative_gain=min_relative_gain,
                             progress=progress, effect_size=effect_size, refits=refits)

    search = new_search()
    names = list(candidates if candidates is not None else search.lib)
    search.run(names, max_effects)
    best = search.finish()
    # Forward selection takes each round's best cause for good, and a flexible cause that
    # mimics a pair alone (an unseen reflector standing in for a cyclic range error plus a clock
    # skew) keeps the pair out. The search therefore also branches where the chosen path was
    # closest to another choice: the significant runners-up of its rounds, the smallest score
    # gap first, EXTRA_STARTS of them; each branch keeps the causes chosen before its round and
    # continues over that round's significant effects (an effect that gains nothing there
    # rarely gains later). The set with the best held-out score is chosen: the same score, over
    # more of the sets.
    found = [(search.score(), search.dof(), best)]
    # Only from the rounds on the final path: a round whose state holds a cause the exchange or
    # the prune took out starts from a set the search has already found worse than the one
    # without it, and a branch from there explores what it rejected.
    on_path = [set(search.before[r]["active"]) <= set(best.causes) for r in range(len(search.path))]
    branches = sorted(((c.score - chosen.score, r, c) for r, (chosen, rnd) in enumerate(search.path)
                       for c in rnd if on_path[r] and c.significant and c is not chosen
                       and c.effect not in best.causes),
                      key=lambda t: (t[0], t[1], t[2].effect))[:EXTRA_STARTS]
    # A generic form chosen for what physical causes explain together (a gain field for an
    # emitter beside the lens and a beam of another exponent) keeps them out when each alone
    # gains less in its round: the search also starts from the best physical cause of the
    # round where the first generic form was taken (parsimony then chooses between the sets).
    first = next((r for r, (chosen, _) in enumerate(search.path) if on_path[r] and search.lib[chosen.effect].generic),
                 None)
    if first is not None:
        physical = next((c for c in search.path[first][1] if c.significant and not search.lib[c.effect].generic
                         and c.effect not in best.causes), None)
        if physical is not None and all(c is not physical for _, _, c in branches):
            branches.append((physical.score - search.path[first][0].score, first, physical))
    settled = search.settled()
    for _, r, c in branches:
        if progress:
            progress(f"searching again from round {r + 1}'s {c.effect}")
        other = new_search()
        other.restore(search.before[r])
        other.add(c, [c], {c.effect: [c]})
        other.run([x.effect for x in search.path[r][1] if x.significant], max_effects, premise=c.effect,
                  settled=settled)
        alt = other.finish()
        alt.rounds = best.rounds[:r + 1] + alt.rounds
        for key in ("too_small", "not_tried"):
            getattr(alt, key).update({k: v for k, v in getattr(best, key).items() if k not in alt.causes})
        found.append((other.score(), other.dof(), alt))
    return _choose_set(model, data, found, search.penalty)


def _choose_set(model: ForwardModel, data: HeldOutData, found: Sequence[tuple[float, float, Selection]],
                penalty: float) -> Selection:
    """The set the search names among those it found: the lowest held-out score, unless another
    set the data cannot tell from it (:func:`~tofhil.eval.diagnose.ambiguity.sets_alike`) has
    fewer degrees of freedom; then the simpler one (parsimony among readings the data cannot
    separate; the other is said, "A or B")."""
    best_score, _, best = min(found, key=lambda f: f[0])
    chosen_score, chosen = best_score, best
    if len(found) > 1 and best.causes:
        others = [(score, sel.causes, sel.params) for score, _, sel in found if sel is not best]
        alike = {a.other for a in sets_alike(model, data, best.causes, best.params, best_score, others, penalty)}
        simpler = [(k, score, sel) for score, k, sel in found
                   if sel is best or (sel.causes and " + ".join(sel.causes) in alike)]
        _, chosen_score, chosen = min(simpler, key=lambda t: (t[0], t[1]))
    sets: dict[tuple[str, ...], dict[str, Any]] = {}
    for score, _, sel in found:  # one entry per set found (two starts can end in the same set)
        key = tuple(sorted(sel.causes))
        if key not in sets or sel is chosen:
            sets[key] = {"causes": list(sel.causes), "score": round(score, 2), "chosen": sel is chosen}
    chosen.searches = list(sets.values())
    if len(found) > 1 and chosen.causes:
        others = [(score, sel.causes, sel.params) for score, _, sel in found if sel is not chosen]
        said = {a.other for alts in chosen.alternatives.values() for a in alts}
        found_alike = sets_alike(model, data, chosen.causes, chosen.params, chosen_score, others, penalty,
                                 said=said)
        if found_alike:
            chosen.alternatives.setdefault(chosen.causes[0], []).extend(found_alike)
    return chosen


class _GreedySearch:
    """The state of :func:`greedy_select`: the effects chosen so far, their parameters, and the
    current model's held-out misfit, per channel and in total."""

    def __init__(self, model: ForwardModel, data: HeldOutData, *, max_effects: int, min_relative_gain: float,
                 progress: Callable[[str], None] | None,
                 effect_size: EffectSize | None,
                 refits: LRUCache | None = None) -> None:
        self.model, self.data, self.progress, self.effect_size = model, data, progress, effect_size
        #: The chosen set without one cause, refitted, by the state it was refitted from: the
        #: prune tests each cause against the others refitted, and the exchange then drops each
        #: from the same state (and the branches reach the same states): one fit, not two.
        self.refits = LRUCache(MAX_KEPT_REFITS) if refits is None else refits
        self.min_relative_gain = min_relative_gain
        self.lib = model.library()
        self.n_test = data.n_values("test")
        self.penalty = np.log(self.n_test)
        self.active: list[str] = []
        self.params: EffectParams = {}
        self.dofs: dict[str, float] = {}  # effective dof of the closed-form fits chosen
        self.base_pred = model.predict({})
        self.current_pred = self.base_pred
        self.current_chi2 = data.chi2(self.base_pred, "test")
        self.current_channels = channel_chi2(data, self.base_pred)
        self.selection = Selection(causes=[], params={}, baseline_chi2_test=self.current_chi2,
                                   final_chi2_test=self.current_chi2, n_test=self.n_test, searched=max_effects > 0,
                                   channels_before=self.current_channels, channels_after=self.current_channels)
        self.work = dict(self.lib)  # each chosen effect's spec is that of its chosen form
        #: Per round that chose a cause: the state before it, and (the cause, the round ranked).
        self.before: list[dict[str, Any]] = []
        self.path: list[tuple[Candidate, list[Candidate]]] = []

    def k_of(self, e: str) -> float:
        return self.dofs.get(e, self.work[e].k)

    def snapshot(self) -> dict[str, Any]:
        """The search's state before a round (what a branch from that round starts from)."""
        sel = self.selection
        return {"active": list(self.active), "params": dict(self.params), "dofs": dict(self.dofs),
                "work": dict(self.work), "chi2": self.current_chi2, "pred": self.current_pred,
                "channels": self.current_channels,
                "selection": {k: dict(getattr(sel, k)) for k in ("forms", "details", "priors", "unidentified",
                                                                 "alternatives")}}

    def restore(self, snap: dict[str, Any]) -> None:
        self.active, self.params, self.dofs = list(snap["active"]), dict(snap["params"]), dict(snap["dofs"])
        self.work = dict(snap["work"])
        self.current_chi2, self.current_pred, self.current_channels = snap["chi2"], snap["pred"], snap["channels"]
        for k, v in snap["selection"].items():
            setattr(self.selection, k, dict(v))

    def dof(self) -> float:
        """The chosen set's degrees of freedom (effective, for a regularised or closed-form fit)."""
        return float(sum(self.k_of(e) for e in self.active))

    def score(self) -> float:
        """The chosen set's held-out score: misfit plus the penalty of its degrees of freedom."""
        return float(self.current_chi2 + sum(self.k_of(e) for e in self.active) * self.penalty)

    def run(self, names: Sequence[str], max_effects: int, premise: str | None = None, settled: bool = False) -> None:
        """Rounds until nothing significant is left or ``max_effects`` are chosen, every cause
        tested again against the others (:meth:`prune`) and the search run again without each
        (:meth:`exchange`); then the chosen forms are tested again at the final values.

        A branch's ``premise`` (the runner-up it starts from) is not searched again without: the
        search without it is the one the branch was taken from. A branch whose main search is
        ``settled`` (its set leaves nothing beyond noise) runs no exchange: an exchange looks for
        a set that explains more, and there is nothing more to explain; what a branch can still
        give there is a set the data cannot tell from the main one, which its rounds find.

        There, too, a branch ends once its premise fails the prune's test against the causes
        chosen after it: the set without it is one the main search held, and went on from,
        before (the branch would repeat that search)."""
        rejoined = self.forward(names, max_effects, premise=premise if settled else None)
        if not rejoined:
            self.prune()
            if not settled:
                self.exchange(names, max_effects, premise)
        self.simplify_forms()

    def settled(self) -> bool:
        """The chosen set leaves nothing beyond noise (the verdict's test at ALPHA)."""
        from tofhil.eval.diagnose.verdict import noise_dof, noise_threshold

        return self.current_chi2 <= noise_threshold(self.n_test, noise_dof(self.data)) * self.n_test

    def forward(self, names: Sequence[str], max_effects: int, premise: str | None = None) -> bool:
        """Rounds until nothing significant is left or ``max_effects`` are chosen. With a
        ``premise``: until it fails the prune's test against the causes chosen after it (then
        it is dropped, and True returned)."""
        while len(self.active) < max_effects:
            before = self.snapshot()
            round_, tried_of = self.round(names)
            chosen = next((c for c in round_ if c.significant), None)
            if chosen is None:
                _release_residuals(round_)
                break
            self.before.append(before)
            self.path.append((chosen, round_))
            self.add(chosen, round_, tried_of)
            if premise is not None and premise in self.active and len(self.active) > 1 \
                    and not self._kept_against_rest(premise):
                return True
        return False

    def exchange(self, names: Sequence[str], max_effects: int, premise: str | None = None) -> None:
        """Every chosen cause must survive the search run without it (forward selection with
        exchanges): the others refitted, the rounds run again over every other effect, the set
        pruned. A cause taken first for parts of two others' light (a readout's offset for a
        stray-light veil and a harmonic together) kept the others out; the set found without it
        replaces the chosen one when its held-out score is lower, and is said. Not where the set
        leaves nothing beyond noise (the verdict's test at ALPHA): no set explains more there,
        and the sets it cannot tell apart are the branches' "A or B"."""
        if self.settled():
            return  # the set leaves nothing beyond noise (the verdict's test): no other set explains more
        sel = self.selection
        for cause in list(self.active):
            if cause not in self.active or cause == premise:
                continue
            saved, score = self.snapshot(), self.score()
            saved_small, n_rounds, n_path = dict(sel.too_small), len(sel.rounds), len(self.path)
            before = " + ".join(self.active)
            if self.progress:
                self.progress(f"searching again without {cause}")
            kept = set(self.active) - {cause}
            self._drop(cause)
            self.forward([n for n in names if n != cause], max_effects)
            self.prune()
            for new in [e for e in self.active if e not in kept]:
                self._restart_jointly(new)
            if self.score() < score:
                sel.exchanges.append(f"{before} (held-out score {score:.1f}) searched again without {cause}: "
                                     f"{' + '.join(self.active) or 'nothing'} ({self.score():.1f}), kept")
                continue
            self.restore(saved)
            sel.too_small, sel.rounds = saved_small, sel.rounds[:n_rounds]
            del self.path[n_path:], self.before[n_path:]

    def _restart_jointly(self, e: str) -> None:
        """Refit the chosen set jointly from each of ``e``'s starting points: ``e`` was fitted
        with the others held at values they took without it (a stray light fitted beside a
        harmonic and a clock skew that had taken part of its light found a lobe twice as wide).
        Kept when the held-out misfit falls."""
        if self.progress:
            self.progress("refitting " + " + ".join(self.active) + f" jointly from the starts of {e}")
        joint, _ = fit(self.model, self.data, self.active, self.params, new_effect=e, lib=self.work)
        pred = self.model.predict(joint)
        chi2 = self.data.chi2(pred, "test")
        if chi2 < self.current_chi2:
            self.params, self.current_chi2, self.current_pred = joint, chi2, pred
            self.current_channels = channel_chi2(self.data, pred)

    def _refit_without(self, e: str) -> tuple[EffectParams, float, np.ndarray]:
        """The chosen set without ``e``, the others refitted: their values, held-out misfit, prediction."""
        rest = [a for a in self.active if a != e]
        key = content_digest(rest, {a: self.params[a] for a in rest},
                             {a: (self.work[a].form, self.work[a].strength) for a in rest})
        kept = self.refits.get(key)
        if kept is None:
            refit, _ = fit(self.model, self.data, rest, {a: self.params[a] for a in rest}, lib=self.work)
            pred = self.model.predict(refit)
            kept = (refit, self.data.chi2(pred, "test"), pred)
            self.refits.put(key, kept)
        return kept

    def _drop(self, e: str, without: tuple[EffectParams, float, np.ndarray] | None = None) -> None:
        """``e`` out of the chosen set, the others at their values without it (refitted if not given)."""
        refit, chi2, pred = self._refit_without(e) if without is None else without
        self.active.remove(e)
        for table in (self.selection.forms, self.selection.details, self.selection.priors,
                      self.selection.unidentified, self.selection.alternatives, self.dofs):
            table.pop(e, None)
        self.params = {a: refit[a] for a in self.active}
        self.current_chi2, self.current_pred = chi2, pred
        self.current_channels = channel_chi2(self.data, pred)

    def prune(self) -> None:
        """Every chosen cause must pass the round's significance test against the chosen set
        without it, the others refitted: a cause taken early can be made redundant by later
        ones (an illumination change taken first for the mean of an unseen panel's light, the
        panel itself taken after). A cause that fails is dropped, and the test runs again."""
        dropped = True
        while dropped and len(self.active) > 1:
            dropped = False
            for e in list(self.active):
                if not self._kept_against_rest(e):
                    dropped = True
                    break

    def _kept_against_rest(self, e: str) -> bool:
        """The prune's test of one cause: ``e`` against the chosen set without it, the others
        refitted; a cause that fails is dropped (and said too small)."""
        if self.progress:
            self.progress(f"testing {e} against " + " + ".join(a for a in self.active if a != e))
        without = self._refit_without(e)
        _, chi2, pred = without
        gains, worth, _ = self._significant(chi2, self.current_chi2, self.k_of(e), pred, self.current_pred)
        if gains and worth:
            return True
        self.selection.too_small[e] = (f"{e}: dropped, the other causes refitted without it explain the "
                                       f"held-out data as well (its gain over them {chi2 - self.current_chi2:.1f} "
                                       f"in misfit, {self.k_of(e):g} degrees of freedom)")
        self._drop(e, without)
        return False

    def _significant(self, chi2_without: float, chi2_with: float, k: float, pred_without: np.ndarray,
                     pred_with: np.ndarray) -> tuple[bool, bool, dict[str, ChannelGain]]:
        """The one test of a cause, in a round and in the prune: whether it gains (the held-out
        misfit falls by more than its ``k`` degrees of freedom's penalty, which sets the
        false-alarm rate, and by a share of the excess over noise that is left), whether it is
        worth naming (its effect size where it acts), and the effect size per channel."""
        from tofhil.eval.diagnose.signature import needed_gain

        gain = chi2_without - chi2_with
        excess = max(chi2_without - self.n_test, 0.0)
        gains = bool(excess > 0 and gain > needed_gain(k, self.penalty, excess, self.min_relative_gain))
        rmse: dict[str, ChannelGain] = {}
        worth = True
        if gains and self.effect_size is not None:
            rmse, worth = self.effect_size.names(pred_without, pred_with)
        return gains, worth, rmse

    def identify(self, c: Candidate) -> Identifiability:
        return assess_form(self.model, self.data, c.all_params, c.effect, self.lib[c.effect].variant(c.form),
                           self.lib[c.effect], self.penalty)

    def round(self, names: Sequence[str]) -> tuple[list[Candidate], dict[str, list[Candidate]]]:
        """Every effect not chosen yet, each in its best form, ranked; and every form tried."""
        current_k = sum(self.k_of(e) for e in self.active)
        current_score = self.current_chi2 + current_k * self.penalty
        excess = max(self.current_chi2 - self.n_test, 0.0)
        round_: list[Candidate] = []
        tried_of: dict[str, list[Candidate]] = {}
        for name in names:
            if name in self.active or name not in self.lib:
                continue  # chosen already, or nothing of it acts on these data
            tried = self._try_effect(name, current_k, current_score, excess)
            if not tried:
                continue  # no form's signature could be named (selection.not_tried says why)
            tried_of[name] = tried
            round_.append(self._best_form(name, tried, current_k, current_score, excess))
        # ties broken by name: the ranking does not depend on the library's order
        round_.sort(key=lambda c: (c.score, c.effect))
        self.selection.rounds.append(round_)
        return round_, tried_of

    def _signature_absent(self, name: str, spec: EffectSpec, excess: float) -> bool:
        """True when no value of ``spec``'s form near its starts could be named: the score test
        of the residual on the form's signature (:mod:`tofhil.eval.diagnose.signature`) is below
        what the selection's test needs. The reason goes to ``selection.not_tried``."""
        from tofhil.eval.diagnose.signature import needed_gain, signature_test

        needed = needed_gain(spec.k, self.penalty, excess, self.min_relative_gain)
        test = signature_test(self.model, self.data, name, spec, self.params, self.current_pred, needed)

        if test is None or not test.absent:
            return False
        self.selection.not_tried[name] = test.text()
        return True

    def _try_effect(self, name: str, current_k: float, current_score: float, excess: float) -> list[Candidate]:
        """``name`` fitted in each of its forms, the flexible ones starting where the simple one ended."""
        tried: list[Candidate] = []
        traded = False  # a form gained only by making a channel worse
        simple = self.lib[name]
        # an effect of one form is screened; the forms of an effect with flexible ones are all
        # fitted, since a flexible form is chosen only against the simple one's fit (choose_form)
        if not simple.forms and self._signature_absent(name, simple, excess):
            return tried
        for spec in (simple,) + tuple(simple.forms):
            cand, traded_ = self._try_form(name, spec, tried[0] if tried else None, current_k, current_score, excess)
            tried.append(cand)
            traded |= traded_
        if traded and name not in self.selection.rejected_for_channels:
            self.selection.rejected_for_channels.append(name)
        return tried

    def _best_form(self, name: str, tried: list[Candidate], current_k: float, current_score: float,
                   excess: float) -> Candidate:
        """The form of ``name`` the round compares (:func:`choose_form`), and why it is too
        small to name when no form is worth it."""

        def partial(c: Candidate, drop: list[str]) -> Candidate:
            # a partial form starts from the fuller form's values
            return self._try_form(c.effect, self.lib[c.effect].variant(c.form).without(drop), c, current_k,
                                  current_score, excess)[0]
        best_form = choose_form(tried, self.min_relative_gain * excess, self.identify, partial)
        small = [c for c in tried if not c.worth_naming]
        if small and not best_form.significant and name not in self.selection.too_small:
            c = min(small, key=lambda c: c.score)
            self.selection.too_small[name] = (f"{name}" + (f" ({c.form})" if c.form else "") + ": "
                                              + EffectSize.why_not(c.rmse) + ": " + EffectSize.describe(c.rmse))
        return best_form

    def _try_form(self, name: str, spec: EffectSpec, start_from: Candidate | None, current_k: float,
                  current_score: float, excess: float) -> tuple[Candidate, bool]:
        """Fit ``name`` in ``spec``'s form and score it; and whether it gained only by making a
        channel worse."""
        model, data, params, penalty = self.model, self.data, self.params, self.penalty
        if start_from is not None and spec.params:
            # a flexible form also starts where a simpler one ended (its phases found)
            names_ = {p.name for p in spec.params}
            simple = {k: v for k, v in start_from.params.items() if k in names_}
            spec = dataclasses.replace(spec, starts=(simple,) + tuple(spec.starts))
        release_free_memory()  # (the last fit's frame-sized temporaries)
        if self.progress:
            self.progress(f"fitting {name}" + (f" ({spec.form})" if spec.form else ""))
        trial_lib = {**self.work, name: spec}
        trial = self.active + [name]
        k_new, details = spec.k, {}
        # forward stagewise: the new effect is fitted with the earlier ones held; the chosen
        # set is refitted jointly after
        if spec.closed_form is not None:
            values, k_new, details = spec.closed_form(model, data, params, penalty)
            fitted = {e: params[e] for e in self.active} | {name: values}
            chi2_train = data.chi2(model.predict(fitted), "train")
        else:
            fitted, chi2_train = fit(model, data, trial, params, new_effect=name, free=[name], lib=trial_lib)
        prior = regularise_form(model, data, fitted, name, spec)
        if prior is not None:
            # the form's prior, its strength chosen on held-out blocks of the training frames;
            # the penalty charges the regularised form's effective dof
            fitted = {**fitted, name: prior.values}
            k_new = prior.dof
        pred = model.predict(fitted)
        if prior is not None:
            chi2_train = data.chi2(pred, "fit")
        chi2_test = data.chi2(pred, "test")
        channels = channel_chi2(data, pred)
        # worse than the current model or, summed over rounds, than the base twin
        worse = sorted(set(worse_channels(self.current_channels, channels))
                       | set(worse_channels(self.selection.channels_before, channels)))
        score = chi2_test + (current_k + k_new) * penalty
        gain = self.current_chi2 - chi2_test
        gains, worth, rmse = self._significant(self.current_chi2, chi2_test, k_new, self.current_pred, pred)
        # a channel that rose is accounted (the explanation is partial there), never a veto:
        # the total held-out score decides
        significant = gains and worth
        cand = Candidate(effect=name, params=fitted[name], chi2_train=chi2_train, chi2_test=chi2_test,
                         score=score, delta_score=current_score - score,
                         relative_gain=gain / self.current_chi2 if self.current_chi2 > 0 else 0.0,
                         significant=significant, n_params=len(spec.params),
                         all_params=fitted, worse_channels=worse, at_bounds=pinned(spec, fitted[name]),
                         channels=channels, form=spec.form, dof=float(k_new), details=details,
                         rmse=rmse, worth_naming=worth,
                         strength=prior.strength if prior is not None else 0.0,
                         prior=prior.summary() if prior is not None else {},
                         # kept for "A or B" and a flexible form's identifiability, which read
                         # significant candidates only (megabytes each at camera resolution)
                         test_residual=data.whitened_residual(pred, "test") if significant else None)
        return cand, gains and bool(worse)

    def add(self, chosen: Candidate, round_: list[Candidate], tried_of: dict[str, list[Candidate]]) -> None:
        """Take the round's cause into the model, with what the data say of its form and of
        other families that explain the same residual; then refit the chosen set jointly."""
        selection, model, data = self.selection, self.model, self.data
        # A flexible form the score rule refused is not tested in choose_form; its extra
        # parameters may still be indistinguishable from the simple form's on this session
        # (then the simple form holds them all): say so for the effect named.
        for c in tried_of[chosen.effect]:
            if c.form and c.form != chosen.form and c.n_params and "identified" not in chosen.forms[c.form]:
                test = self.identify(c)
                chosen.forms[c.form]["identified"] = test.identified
                if any(g.confused for g in test.groups):
                    chosen.unidentified.append(test)
        # another family that explains the same residual as well: said, "A or B"
        alt = same_residual(model, data, chosen, round_, self.current_pred, self.penalty)
        if alt:
            selection.alternatives[chosen.effect] = alt
        _release_residuals(round_)
        self.active.append(chosen.effect)
        self.work[chosen.effect] = dataclasses.replace(self.lib[chosen.effect].variant(chosen.form),
                                                       strength=chosen.strength)
        if chosen.prior:
            selection.priors[chosen.effect] = chosen.prior
        selection.forms[chosen.effect] = chosen.form
        self.dofs[chosen.effect] = chosen.dof
        if chosen.details:
            selection.details[chosen.effect] = chosen.details
        if chosen.unidentified:
            selection.unidentified[chosen.effect] = chosen.unidentified
        self.params = chosen.all_params
        self.current_chi2 = chosen.chi2_test
        before_round = self.current_channels
        before_pred = self.current_pred
        self.current_channels = chosen.channels
        self.current_pred = model.predict(self.params)
        self._joint_refit(before_round, before_pred)

    def _joint_refit(self, before_round: dict, before_pred: np.ndarray) -> None:
        """Refit the chosen set jointly (for one effect: more iterations from its best start;
        geometric effects often need them); kept only if better and no channel worse."""
        model, data = self.model, self.data
        if self.progress:
            self.progress("refitting " + " + ".join(self.active) + " jointly")
        joint, _ = fit(model, data, self.active, self.params, lib=self.work)
        joint_pred = model.predict(joint)
        joint_chi2 = data.chi2(joint_pred, "test")
        joint_channels = channel_chi2(data, joint_pred)
        joint_ok = True
        if self.effect_size is not None:
            # the joint refit keeps what made the round's cause worth naming
            _, joint_ok = self.effect_size.names(before_pred, joint_pred)
        if joint_chi2 < self.current_chi2 and joint_ok:
            self.params, self.current_chi2, self.current_channels, self.current_pred = (
                joint, joint_chi2, joint_channels, joint_pred)

    def simplify_forms(self) -> None:
        """A flexible form must earn its extra degrees of freedom at the final values, as it had
        to when it was chosen (:func:`choose_form`): one chosen in an early round may have stood in
        for an effect added later (in the demo the 5th and 7th harmonics took up part of a
        clock-skew pattern until fixed_pattern was fitted; on the TOFcam635 they took part of a
        readout imbalance that the exchange then dropped). The simple form is refitted with the
        set, jointly, and replaces the flexible one when its held-out score is as low; a
        flexible form kept whose extra parameters are no longer identified is said."""
        model, data, lib, work, penalty, selection = (self.model, self.data, self.lib, self.work, self.penalty,
                                                      self.selection)
        for e in list(self.active):
            spec = work[e]
            if not spec.form or spec.closed_form is not None or not spec.params:
                continue
            params = self.params
            test = assess_form(model, data, params, e, spec, lib[e], penalty)
            test.after_later = True
            start = {k: dict(v) for k, v in params.items()}
            start[e] = {p.name: params[e][p.name] for p in lib[e].params if p.name in params[e]}
            simple_work = {**work, e: lib[e]}
            refit, _ = fit(model, data, self.active, start, lib=simple_work)
            pred = model.predict(refit)
            chi2 = data.chi2(pred, "test")
            channels = channel_chi2(data, pred)
            k_others = sum(self.k_of(a) for a in self.active if a != e)
            if chi2 + (k_others + lib[e].k) * penalty <= self.current_chi2 + (k_others + self.k_of(e)) * penalty:
                work[e], self.dofs[e] = lib[e], lib[e].k
                selection.forms[e] = ""
                selection.priors.pop(e, None)
                self.params, self.current_chi2, self.current_channels, self.current_pred = refit, chi2, channels, pred
            elif test.identified:
                continue
            else:
                test.kept = True  # the simpler form is worse on held-out data: said, not hidden
            if not test.identified:
                selection.unidentified.setdefault(e, []).append(test)

    def finish(self) -> Selection:
        selection = self.selection
        # a cause named is not also "too small" or "not fitted": such a record is from a set the
        # search left (a prune that dropped it before an exchange took it back)
        for table in (selection.too_small, selection.not_tried):
            for e in self.active:
                table.pop(e, None)
        selection.causes = self.active
        selection.params = {e: self.params[e] for e in self.active}
        selection.final_chi2_test = self.current_chi2
        selection.channels_after = self.current_channels
        selection.at_bounds = {e: pinned(self.work[e], self.params[e]) for e in self.active}
        return selection
