"""Priors of the flexible forms the optimiser fits, their strengths chosen on held-out data.

A flexible form (the wiggling harmonics up to the 7th, the monotone spline in log amplitude)
has more freedom than a small or noisy session supports. Its prior (``Effect.roughness``) is
a vector that is zero for the form's smoothest shape (no harmonic beyond the 3rd; an error
linear in log amplitude); the regularised fit minimises

    |r(x)|^2 + lam |rho(x)|^2

(``r`` the whitened training residual, ``rho`` the roughness). The strength ``lam`` is chosen
on held-out data by the rule the offset maps use (:func:`tofhil.eval.diagnose.linear_forms.held_out_strength`):
linearised about the unregularised fit ``x0`` (``r ~ r0 + J d``, ``rho ~ rho0 + R d``), the step

    d(lam) = -(J'J + lam R'R)^+ (J' r0 + lam R' rho0)

is fitted on the training blocks of the training frames (the fit's pixels) and scored on
their held-out blocks (``HeldOutData.part("tune")``); the strongest prior is tried first and
kept unless a weaker one does better; the regularised values are checked there with the model
itself (not its linearisation) and the unregularised form kept when they do worse. The held-out frames, on which the selection scores the
form, are never used here. The form's effective degrees of freedom are the trace of the hat
matrix, ``tr((J'J + lam R'R)^+ J'J)``: what the selection's penalty charges (a harmonic shrunk
to nothing costs nothing; an unregularised form costs its rank, not its parameter count).
The chosen strength stays with the form: every later fit of it (the joint refit) adds the
same prior (``EffectSpec.strength``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from tofhil.eval.diagnose.heldout import HeldOutData, huber
from tofhil.eval.diagnose.identifiability import form_jacobian
from tofhil.eval.diagnose.linear_forms import held_out_strength

#: Strengths tried, relative to the ratio of the data's and the prior's curvature (two per
#: decade, the strongest first; 0 is the unregularised form).
STRENGTH_GRID = tuple(10.0 ** np.arange(6.0, -4.01, -0.5)) + (0.0,)
#: Singular values below this share of the largest count as no direction (a harmonic's phase
#: at zero amplitude changes nothing).
RCOND = 1e-10


@dataclass
class PriorFit:
    """A flexible form's regularised values, strength and effective degrees of freedom."""

    values: dict[str, float]
    #: The prior's strength in the fit's whitened units (0: none).
    strength: float
    #: That strength relative to the data's curvature over the prior's (the grid's unit).
    relative: float
    #: Effective degrees of freedom: the trace of the hat matrix.
    dof: float
    n_params: int
    #: Linearised held-out-block misfit of the unregularised and the regularised form.
    tune_chi2: tuple[float, float]

    def summary(self) -> dict[str, Any]:
        return {"prior_strength": float(f"{self.relative:.3g}"), "dof": round(self.dof, 2),
                "params": self.n_params, "tune_chi2_unregularised": round(self.tune_chi2[0], 2),
                "tune_chi2": round(self.tune_chi2[1], 2)}


def regularise_form(model: Any, data: HeldOutData, fitted: Mapping[str, Mapping[str, float]], effect: str,
                    spec: Any) -> PriorFit | None:
    """The regularised values of ``effect`` fitted in ``spec``'s form (at ``fitted``, every
    active effect's values, the form's unregularised), the prior's strength chosen on the
    held-out blocks of the training frames, and the effective degrees of freedom. None when
    the form has no prior."""
    if spec.roughness is None or not spec.params:
        return None
    names = [p.name for p in spec.params]
    x0 = np.array([float(fitted[effect].get(p.name, p.off)) for p in spec.params])
    (r_fit, j_fit), (r_tune, j_tune) = form_jacobian(model, data, fitted, effect, spec, ("fit", "tune"))

    def rho(x: np.ndarray) -> np.ndarray:
        return np.asarray(spec.roughness(dict(zip(names, (float(v) for v in x)))), dtype=np.float64)

    rho0 = rho(x0)
    rough_cols = []
    for j, p in enumerate(spec.params):
        h = 0.05 * p.scale if x0[j] + 0.05 * p.scale <= p.hi else -0.05 * p.scale
        xj = x0.copy()
        xj[j] += h
        rough_cols.append((rho(xj) - rho0) / h)
    rough = np.stack(rough_cols, axis=1)
    m = j_fit.T @ j_fit
    pm, pg = rough.T @ rough, rough.T @ rho0
    if not (np.isfinite(pm).all() and np.isfinite(m).all()):
        raise ValueError(f"{effect} ({spec.form}): non-finite Jacobian at the fitted values")
    flat = not np.trace(pm) > 1e-12 * max(float(np.abs(rho0 @ rho0)), 1.0)
    # a prior that changes nothing to first order here (a spline of zero span has no
    # curvature to shrink): the form stays unregularised
    unit = 0.0 if flat else float(np.trace(m) / np.trace(pm))

    def step(rel: float) -> np.ndarray:
        # x0 is the (robust) fit's optimum: the data's gradient there is taken as zero, so the
        # step is the prior's pull alone and the unregularised form stays where it was fitted
        # (a Gauss-Newton step from x0 would move along near-null directions of J'J)
        if rel == 0.0:
            return np.zeros(x0.size)
        lam = rel * unit
        return -np.linalg.lstsq(m + lam * pm, lam * pg, rcond=RCOND)[0]

    def tune(rel: float) -> float:
        r = r_tune + j_tune @ step(rel)
        return float(r @ r)

    rel = 0.0 if flat else held_out_strength(STRENGTH_GRID, tune)
    lo, hi = np.array([p.lo for p in spec.params]), np.array([p.hi for p in spec.params])
    x = np.clip(x0 + step(rel), lo, hi)
    if rel > 0.0:
        # the step is linearised: checked on the same held-out blocks with the model itself,
        # and the unregularised form kept when the real prediction there is worse
        trial = {e: dict(v) for e, v in fitted.items()}
        trial[effect] = dict(zip(names, (float(v) for v in x)))
        if data.chi2(model.predict(trial), "tune") > float(huber(r_tune).sum()):
            rel, x = 0.0, x0
    lam = rel * unit
    dof = float(np.trace(np.linalg.lstsq(m + lam * pm, m, rcond=RCOND)[0]))
    return PriorFit(values=dict(zip(names, (float(v) for v in x))), strength=lam, relative=rel, dof=dof,
                    n_params=len(names), tune_chi2=(tune(0.0), tune(rel)))
