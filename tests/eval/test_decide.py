"""The decision (``eval/diagnose/decide.py``): ordered pure rules over the selection's record,
with a ledger; the selection is read, never changed; the verdict is made once at the end."""

from __future__ import annotations

import copy

import numpy as np

from tofhil.eval.diagnose import decide as D
from tofhil.eval.diagnose import verdict as V
from tofhil.eval.diagnose.selection import Selection

N = 100


class _Judge:
    """Reads a prediction whose value is its held-out misfit per value (the base twin's is 5)."""

    n, nu, objects_before = N, 50.0, {}

    def read(self, pred, causes):
        v = V.verdict(searched=True, causes=list(causes), n_values=N, nu=self.nu, before_per_value=5.0,
                      after_per_value=float(pred.mean()), worse=[], objects_before={}, objects_after={}, pinned={},
                      rejected_for_channels=[])
        return D.Reading(v, {}, {}, [], None)


class _Sizes:
    """Every candidate set removes ``removed`` of a depth RMSE of 1 (the minimum is 0.1)."""

    def __init__(self, removed: float) -> None:
        self.removed = removed

    def compare(self, before, after):
        return {"depth": V.ChannelGain("depth", 1.0, float(np.sqrt(1.0 - self.removed ** 2)), 0.5, 0.1, N)}


def _context(removed: float) -> D.Context:
    sel = Selection(causes=["a"], params={"a": {"g": 1.0}}, baseline_chi2_test=5.0 * N, final_chi2_test=0.9 * N,
                    n_test=N)
    return D.Context(selection=sel, data=object(), model=None, judge=_Judge(), sizes=_Sizes(removed),
                     base_pred=np.full(1, 5.0), extended=lambda p: ("twin", np.full(1, 0.9 if p else 5.0)),
                     max_effects=3)


def test_a_set_that_keeps_its_gain_is_named_and_the_selection_is_not_changed():
    ctx = _context(removed=0.5)
    before = copy.deepcopy(ctx.selection)
    d = D.decide(ctx)
    assert d.names == ["a"] and d.verdict.kind is V.Kind.EXPLAINED and not d.rejected
    assert d.params == {"a": {"g": 1.0}} and d.prediction.mean() == 0.9
    assert ctx.selection == before  # read, never changed
    ledger = d.ledger()
    assert ledger["rules"] == [r.__name__ for r in D.RULES] and ledger["causes"][0]["effect"] == "a"


def test_a_set_that_loses_its_gain_is_rejected_with_its_rule_and_figures():
    ctx = _context(removed=0.01)
    d = D.decide(ctx)
    assert d.names == [] and d.params == {} and d.prediction.mean() == 5.0
    (r,) = d.rejected
    assert r.effects == ("a",) and r.rule == "extended scene loses the gain" and "depth" in r.figures
    assert d.verdict.kind is V.Kind.UNEXPLAINED  # made from the final state: nothing named
    assert any(n.startswith("fitted but not named: a") for n in d.verdict.notes)
    assert ctx.selection.causes == ["a"] and ctx.selection.params == {"a": {"g": 1.0}}


def test_the_rules_are_applied_in_the_order_given():
    seen = []

    def rule(name):
        def apply(s):
            seen.append(name)
            return s.with_notes(name)
        return apply

    d = D.decide(_context(removed=0.5), rules=[rule("first"), rule("second")])
    assert seen == ["first", "second"] and d.verdict.notes[-2:] == ["first", "second"]
