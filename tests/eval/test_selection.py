"""Held-out model selection (eval/diagnose/selection.py) on a small fake forward model.

The fake stands in for the twin through the ``ForwardModel`` protocol: a complex image with
three candidate effects of known form -- a gain (linear), a phase shift (non-linear) and a
Gaussian bump whose width needs a multi-start (non-linear, flat at zero amplitude). Data are
the model at hidden parameters plus Gaussian noise of known sigma, split like a session
(training/held-out frames, checkerboard pixel blocks). Selection must name the hidden effect,
fit its parameters to within the noise, name nothing when nothing is hidden, and give the
same answer twice.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.eval.fake_heldout import heldout_from_signal
from tofhil.eval.diagnose.heldout import HeldOutData
from tofhil.eval.diagnose.selection import EffectParams, EffectSpec, FitParam, greedy_select

H = W = 24
SIGMA = 0.02


class FakeModel:
    """S = (1 + ramp) * g * exp(i phi) + a * exp(-r^2 / (2 w^2)), a pure function of its parameters."""

    def __init__(self) -> None:
        v, u = np.mgrid[0:H, 0:W].astype(float)
        self.ramp = 0.5 * u / W + 0.3 * v / H
        self.r2 = (u - 0.6 * W) ** 2 + (v - 0.4 * H) ** 2
        self.calls = 0

    def library(self) -> dict[str, EffectSpec]:
        return {
            "gain": EffectSpec((FitParam("g", 1.0, 0.2, 5.0, 0.05),)),
            "shift": EffectSpec((FitParam("phi", 0.0, -1.0, 1.0, 0.05),)),
            "bump": EffectSpec((FitParam("a", 0.0, 0.0, 2.0, 0.05), FitParam("w", 3.0, 0.5, 20.0, 0.5)),
                               starts=({"a": 0.2, "w": 2.0}, {"a": 0.2, "w": 8.0})),
        }

    def predict(self, active: EffectParams) -> np.ndarray:
        self.calls += 1
        g = active.get("gain", {}).get("g", 1.0)
        phi = active.get("shift", {}).get("phi", 0.0)
        bump = active.get("bump", {})
        a, w = bump.get("a", 0.0), bump.get("w", 3.0)
        s = (1.0 + self.ramp) * g * np.exp(1j * phi) + a * np.exp(-self.r2 / (2 * w * w))
        return s[None]


def _data(truth: EffectParams, seed: int) -> HeldOutData:
    return heldout_from_signal(FakeModel().predict(truth), SIGMA, seed)


@pytest.mark.parametrize("effect, truth, tol", [
    ("gain", {"g": 1.2}, {"g": 0.01}),
    ("shift", {"phi": -0.3}, {"phi": 0.01}),
    ("bump", {"a": 0.4, "w": 6.0}, {"a": 0.02, "w": 0.3}),
])
def test_names_and_fits_the_hidden_effect(effect, truth, tol):
    sel = greedy_select(FakeModel(), _data({effect: truth}, seed=1), max_effects=3)
    assert sel.causes == [effect]
    for k, t in tol.items():
        assert abs(sel.params[effect][k] - truth[k]) <= t, (k, sel.params[effect][k], truth[k])
    n = sel.n_test
    assert sel.baseline_chi2_test > 3 * n  # visible above the noise
    assert sel.final_chi2_test < 1.2 * n   # and explained down to it


def test_two_hidden_effects_are_both_named():
    sel = greedy_select(FakeModel(), _data({"shift": {"phi": 0.25}, "bump": {"a": 0.5, "w": 4.0}}, seed=2))
    assert sorted(sel.causes) == ["bump", "shift"]
    assert abs(sel.params["shift"]["phi"] - 0.25) < 0.01


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_refuses_a_null(seed):
    sel = greedy_select(FakeModel(), _data({}, seed=seed))
    assert sel.causes == [] and sel.params == {}
    assert sel.rounds and not any(c.significant for c in sel.rounds[0])


def test_deterministic():
    data = _data({"bump": {"a": 0.3, "w": 5.0}}, seed=6)
    a, b = greedy_select(FakeModel(), data), greedy_select(FakeModel(), data)
    assert a.causes == b.causes and a.params == b.params
    assert a.final_chi2_test == b.final_chi2_test
    assert [[(c.effect, c.chi2_test) for c in r] for r in a.rounds] == [[(c.effect, c.chi2_test) for c in r]
                                                                         for r in b.rounds]


def test_candidates_limit_the_search():
    model = FakeModel()
    sel = greedy_select(model, _data({"shift": {"phi": 0.3}}, seed=7), candidates=["gain"])
    assert "shift" not in sel.causes
    assert all(c.effect == "gain" for r in sel.rounds for c in r)


def test_a_named_cause_is_not_also_said_too_small_or_not_fitted():
    """A prune can drop a cause that an exchange takes back: its "dropped, too small" record is
    from a set the search left, and the selection it finishes with does not carry it."""
    from tofhil.eval.diagnose.selection import _GreedySearch

    search = _GreedySearch(FakeModel(), _data({"gain": {"g": 1.2}}, seed=1), max_effects=3, min_relative_gain=0.02,
                           progress=None, effect_size=None)
    search.run(list(search.lib), 3)
    assert search.active == ["gain"]
    search.selection.too_small["gain"] = "gain: dropped (a record of a set left)"
    search.selection.not_tried["gain"] = "gain at most 0 of 1"
    search.selection.too_small["bump"] = "bump: too small"
    sel = search.finish()
    assert sel.causes == ["gain"]
    assert "gain" not in sel.too_small and "gain" not in sel.not_tried
    assert sel.too_small["bump"] == "bump: too small"     # the others' records are kept
