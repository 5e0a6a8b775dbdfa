"""The prior of a flexible form, its strength chosen on held-out data (issue 10, point 1).

A forward model linear in its parameters (a signal times ``1 + sum_k c_k cos(k u)``), so
that the linearisation :mod:`tofhil.eval.diagnose.form_prior` makes is exact and its answer can be
checked against the penalised least-squares solution and the hat-matrix trace computed here
from the design matrix, independently of the module's Jacobian.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.eval.fake_heldout import heldout_from_signal
from tofhil.eval.diagnose.form_prior import regularise_form
from tofhil.eval.diagnose.selection import EffectParams, EffectSpec, FitParam, greedy_select

H = W = 24
SIGMA = 0.02
K = 8  # terms of the flexible form; the simple form has the first only


def _rough(values) -> np.ndarray:
    # a ridge on every term beyond the first, in units of 0.01
    return np.array([values.get(f"c{k}", 0.0) / 0.01 for k in range(2, K + 1)])


class CosineModel:
    def __init__(self) -> None:
        v, u = np.mgrid[0:H, 0:W].astype(float)
        self.s0 = (1.0 + 0.3 * v / H) * np.exp(0.5j)
        self.basis = np.stack([np.cos(k * 2 * np.pi * u / W + 0.3 * k) for k in range(1, K + 1)])  # [K, H, W]

    def library(self) -> dict[str, EffectSpec]:
        ps = tuple(FitParam(f"c{k}", 0.0, -1.0, 1.0, 0.02) for k in range(1, K + 1))
        flex = EffectSpec(ps, form="cosines", roughness=_rough)
        return {"ripple": EffectSpec(ps[:1], forms=(flex,))}

    def predict(self, active: EffectParams) -> np.ndarray:
        r = active.get("ripple", {})
        c = np.array([r.get(f"c{k}", 0.0) for k in range(1, K + 1)])
        return (self.s0 * (1.0 + np.tensordot(c, self.basis, axes=(0, 0))))[None]

    def design(self, mask: np.ndarray) -> np.ndarray:
        """Whitened prediction change per unit of each parameter over ``mask`` (real, imag)."""
        cols = (self.s0 * self.basis)[:, mask] / SIGMA  # [K, N]
        return np.concatenate([cols.real, cols.imag], axis=1).T


def _least_squares(model: CosineModel, data, mask: np.ndarray) -> np.ndarray:
    x = model.design(mask)
    z = (data.s_train[0] - model.s0)[mask] / SIGMA
    return np.linalg.lstsq(x, np.concatenate([z.real, z.imag]), rcond=None)[0]


def _prior_fit(truth: dict[str, float], seed: int):
    model = CosineModel()
    data = heldout_from_signal(model.predict({"ripple": truth}), SIGMA, seed)
    spec = model.library()["ripple"].forms[0]
    c0 = _least_squares(model, data, data.fit_pixels)
    fitted = {"ripple": {f"c{k}": float(c0[k - 1]) for k in range(1, K + 1)}}
    return model, data, c0, regularise_form(model, data, fitted, "ripple", spec)


@pytest.mark.parametrize("seed", [1, 2])
def test_the_prior_is_the_penalised_least_squares_fit_and_its_dof_the_hat_trace(seed):
    model, data, c0, prior = _prior_fit({"c1": 0.1}, seed)
    x = model.design(data.fit_pixels)
    pen = np.diag([0.0] + [1.0 / 0.01 ** 2] * (K - 1))
    z = (data.s_train[0] - model.s0)[data.fit_pixels] / SIGMA
    y = np.concatenate([z.real, z.imag])
    expect = np.linalg.solve(x.T @ x + prior.strength * pen, x.T @ y)
    got = np.array([prior.values[f"c{k}"] for k in range(1, K + 1)])
    assert np.allclose(got, expect, atol=2e-4 * SIGMA), (got, expect)
    hat = x @ np.linalg.solve(x.T @ x + prior.strength * pen, x.T)
    assert prior.dof == pytest.approx(float(np.trace(hat)), rel=1e-6)


def test_noise_only_terms_are_shrunk_and_real_terms_kept():
    """Seven terms that are pure noise: the held-out blocks ask for a prior, and the form
    costs less than its eight parameters; the same form with real terms (50 x the noise of a
    coefficient) keeps them, and its dof is its parameter count."""
    shrunk = [_prior_fit({"c1": 0.1}, seed)[3] for seed in range(4)]
    assert sum(p.strength > 0 for p in shrunk) >= 3, [p.summary() for p in shrunk]
    assert np.median([p.dof for p in shrunk]) < K - 1.5, [p.summary() for p in shrunk]
    truth = {"c1": 0.1, "c3": 0.05, "c6": -0.04}
    _, _, c0, kept = _prior_fit(truth, 7)
    assert kept.dof > K - 0.1, kept.summary()
    for k, t in truth.items():
        assert abs(kept.values[k] - t) < 0.005, (kept.values, truth)


def test_a_partly_identified_form_is_fitted_without_what_the_data_do_not_identify():
    """Issue 10, point 2: c1 and c3 real, c2 and c4..c8 noise. The whole form is refused
    (six of its groups unidentified); the partial form without them is chosen, charged its
    regularised effective dof, and recovers c3."""
    model = CosineModel()
    data = heldout_from_signal(model.predict({"ripple": {"c1": 0.1, "c3": 0.05}}), SIGMA, 3)
    sel = greedy_select(model, data)
    assert sel.causes == ["ripple"] and sel.forms == {"ripple": "cosines without c2, c4, c5, c6, c7, c8"}
    cand = sel.rounds[0][0]
    assert cand.forms["cosines"]["identified"] is False and cand.forms[sel.forms["ripple"]]["identified"] is True
    assert cand.score < min(cand.forms[f]["score"] for f in ("", "cosines"))
    assert cand.dof == pytest.approx(sel.priors["ripple"]["dof"], abs=0.01) and cand.dof <= 2.0
    assert set(sel.params["ripple"]) == {"c1", "c3"}
    assert abs(sel.params["ripple"]["c3"] - 0.05) < 0.005 and abs(sel.params["ripple"]["c1"] - 0.1) < 0.005
    lines = [t for t in sel.unidentified["ripple"] for t in t.lines]
    assert lines and all("fitted without" in t for t in lines), lines


@pytest.mark.parametrize("b4, b6", [(0.8, 0.0), (0.0, -3.0), (1.5, 2.0)])
def test_the_radial_illumination_prior_is_what_b4_and_b6_change_at_the_field_edge(b4, b6):
    # the prior shrinks the radial form toward its simple cos^dn: it measures, in units of 1 %
    # of the light, the change the radial terms make at t = tan(field angle) = 0.5, the same
    # as the effect's own factor there
    from tofhil.camera import CameraModel
    from tofhil.sim.effects import EFFECTS

    eff = EFFECTS["illumination"]
    assert eff.roughness("", {"dn": 2.0}) is None
    assert np.all(eff.roughness("radial", {"dn": 1.3, "b4": 0.0, "b6": 0.0}) == 0.0)
    cam = CameraModel(3, 1, 2.0, 2.0, 1.0, 0.0)  # the pixel at u = 2, v = 0 looks at t = (2 - 1) / 2
    assert (2 - cam.cx) / cam.fx == pytest.approx(0.5)
    change = eff.factor({"dn": 0.0, "b4": b4, "b6": b6}, cam, (1, 3))[0, 2] - 1.0
    assert eff.roughness("radial", {"dn": 0.0, "b4": b4, "b6": b6}).sum() * 0.01 == pytest.approx(change, rel=1e-6)
