"""An effect's signature, derived from the effect itself: the directions in which its parameters
move the twin's held-out prediction, read by perturbing them in the twin where its fit starts;
and the score test of the current residual on them.

The selection names a cause when its fit lowers the held-out misfit by more than its price
(``k`` degrees of freedom times the penalty per degree: the false-alarm rate of every test of
the selection). To first order in the effect's parameters, no value of them can lower the
held-out misfit by more than the residual's projection on the effect's signature: for
Huber's misfit ``sum rho(r)`` (``rho = r^2`` within ``HUBER_SIGMA``) and a change ``J b`` of
the whitened residual, the most it falls is ``sum rho(r) - min_b sum rho(r - J b)``, a
Huber regression on the signature's directions (in least squares ``|P_J r|^2``: Rao's score
statistic, chi^2 with ``k`` degrees of freedom where the effect is absent). A form whose
statistic is below the same price would not be named whatever its fit found near its
starts, so it is not fitted: the test that skips a form is the test that names one, and the
signature is computed, not declared.

First order is exact for parameters the prediction is linear in (a gain, an offset, a
harmonic's quadrature parts) and a bound near the starting points for the others; the
signature is the span of the directions at every starting point the fit would take (at
zero weight a stray-light lobe's width moves nothing, at its other starts it does), which
only makes the statistic larger than one start's (a form is skipped less often, never more).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from tofhil.eval.diagnose.heldout import HUBER_SIGMA, HeldOutData, huber

#: A form with more parameters than this is fitted without its signature's test: the test
#: predicts once per parameter and starting point, which for a flexible field costs what its
#: fit does. (A cost limit; it decides nothing: every form is still judged by the one test.)
MAX_SIGNATURE_PARAMS = 12
#: A large image's test reads a subsample of the held-out pixels (unless its predictions are
#: whole frames anyway: :func:`signature_part`) and bounds the whole part's
#: statistic from above (:func:`whole_part_bound`) this many standard deviations above its
#: estimate: a form whose whole-part statistic would be named is skipped with probability
#: below 0.13 % (a normal tail).
SUBSAMPLE_Z = 3.0


@dataclass(frozen=True)
class SignatureTest:
    """The score test of the held-out residual on one form's signature."""

    effect: str
    form: str
    #: The most the held-out misfit can fall, to first order (Rao's score statistic).
    statistic: float
    #: The rank of the signature: the directions its parameters move the prediction.
    rank: int
    #: What a cause must gain to be named (its price, and its share of the excess over noise).
    needed: float

    @property
    def absent(self) -> bool:
        """True when no value of the form's parameters near its starts could be named."""
        return self.statistic <= self.needed

    def text(self) -> str:
        """One entry of the evidence's line of forms not fitted (:data:`NOT_FITTED`)."""
        form = f" ({self.form})" if self.form else ""
        return f"{self.effect}{form} at most {self.statistic:.1f} of {self.needed:.1f}"


#: The evidence line's head for the forms their signature's test skipped.
NOT_FITTED = ("not fitted, the residual's projection on their signature (the directions their parameters move "
              "the held-out prediction, read by perturbing them in the twin) could not lower the held-out misfit "
              "by what a cause must gain to be named")


def signature(model: Any, data: HeldOutData, effect: str, spec: Any, current: Mapping[str, Mapping[str, float]],
              base_residual: np.ndarray, part: str = "screen") -> np.ndarray:
    """The whitened held-out directions ``[values, directions]`` in which ``spec``'s parameters
    move the prediction (every channel of the likelihood: S and the offset), at each of the
    fit's starting points (off, and the form's ``starts``), by the fit's own forward-difference
    step (a twentieth of each parameter's scale), on the screen pixels
    (:attr:`HeldOutData.screen_pixels`; ``base_residual`` is read there), or on the whole
    held-out part (``part="test"``, see :func:`signature_part`)."""
    base_values = {p.name: p.off for p in spec.params}
    columns: list[np.ndarray] = []
    # (on the screen pixels: a model that can predicts only them, exact there)
    pixels = data.screen_pixels if part == "screen" and getattr(model, "predicts_pixels", False) else None

    def residual(values: Mapping[str, Any]) -> np.ndarray:
        pred = model.predict(values) if pixels is None else model.predict(values, pixels=pixels)
        return data.whitened_residual(pred, part)

    for start in ({},) + tuple(spec.starts):
        x0 = {**base_values, **{k: v for k, v in start.items() if k in base_values}}
        r0 = base_residual if not start else residual(dict(current) | {effect: x0})
        for p in spec.params:
            h = _step(p, x0[p.name])
            columns.append((r0 - residual(dict(current) | {effect: {**x0, p.name: x0[p.name] + h}})) / h)
    return np.stack(columns, axis=1) if columns else np.zeros((0, 0))


def _step(p: Any, x: float) -> float:
    """The forward-difference step of parameter ``p`` at ``x``: a twentieth of its scale, back
    from the upper bound."""
    h = 0.05 * p.scale
    return -h if x + h > p.hi else h


def score_statistic(residual: np.ndarray, directions: np.ndarray, c: float = HUBER_SIGMA,
                    iterations: int = 30) -> tuple[float, int]:
    """The most Huber's misfit of ``residual`` falls for a change along ``directions`` (the
    linearised fit: ``sum rho(r) - min_b sum rho(r - J b)``, a convex problem solved by
    iteratively reweighted least squares), and the rank of the directions. Within Huber's
    corner this is Rao's score statistic ``g^T H^+ g``; beyond it (a strong effect whose
    residuals are all in the linear tail) it still counts, where a quadratic model of the
    misfit on its inliers alone would see nothing."""
    if directions.size == 0:
        return 0.0, 0
    # the directions can be dependent (a width that moves nothing at zero weight, the same
    # direction at two starts): solved on the directions the data resolve
    w_all, v_all = np.linalg.eigh(directions.T @ directions)
    keep = w_all > max(float(w_all.max()), 0.0) * 1e-10
    if not np.any(keep):
        return 0.0, 0
    basis = directions @ (v_all[:, keep] / np.sqrt(w_all[keep]))  # orthonormal columns
    b = basis.T @ residual                                         # least squares: the start
    for _ in range(iterations):
        e = residual - basis @ b
        a = np.abs(e)
        weight = np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))
        h = basis.T @ (basis * weight[:, None])
        b_new = np.linalg.lstsq(h, basis.T @ (weight * residual), rcond=None)[0]
        if np.allclose(b_new, b, rtol=1e-8, atol=1e-10):
            b = b_new
            break
        b = b_new
    before = float(huber(residual, c).sum())
    after = float(huber(residual - basis @ b, c).sum())
    return max(before - min(after, before), 0.0), int(keep.sum())


def signature_test(model: Any, data: HeldOutData, effect: str, spec: Any, current: Mapping[str, Mapping[str, float]],
                   base_prediction: np.ndarray, needed: float) -> SignatureTest | None:
    """The score test of ``spec``'s form of ``effect`` at the current model (``current``
    params, predicting ``base_prediction``); None for a form it does not apply to (a
    closed-form map, a form with a prior, no parameters, more than :data:`MAX_SIGNATURE_PARAMS`)."""
    if (getattr(spec, "closed_form", None) is not None or getattr(spec, "roughness", None) is not None
            or not spec.params or len(spec.params) > MAX_SIGNATURE_PARAMS):
        return None  # (a form with a prior: its price, its effective dof, is known after its fit)
    part = signature_part(model, effect, spec, current)
    base = data.whitened_residual(base_prediction, part)
    directions = signature(model, data, effect, spec, current, base, part)
    stat, rank = score_statistic(base, directions)
    return SignatureTest(effect=effect, form=spec.form,
                         statistic=stat if part == "test" else whole_part_bound(stat, data, rank), rank=rank,
                         needed=needed)


def signature_part(model: Any, effect: str, spec: Any, current: Mapping[str, Mapping[str, float]]) -> str:
    """Where the signature is read: the screen pixels (``"screen"``) where the model predicts
    them without the rest of the frame; else the whole held-out part (``"test"``): when a
    perturbed prediction is a whole frame anyway (an effect that moves light between pixels
    is on), the screen would save no render, and its statistic is only a bound on the whole
    part's, loose by the noise of a subsample (a form would be fitted that the whole part's
    statistic skips)."""
    alone = getattr(model, "predicts_alone", None)
    if alone is None:
        return "screen"
    moved = {p.name: p.off + _step(p, p.off) for p in spec.params}
    return "screen" if alone(dict(current)) and alone(dict(current) | {effect: moved}) else "test"


def whole_part_bound(statistic: float, data: HeldOutData, rank: int = 0) -> float:
    """The held-out part's statistic bounded from the screen pixels' (a fraction ``f`` of the
    part), the statistic itself when the screen is the whole part. The screen's statistic is
    the effect's energy on the screen plus noise (chi^2 of ``rank``): the whole part's is
    estimated as ``(S - rank) / f + rank``, and bounded :data:`SUBSAMPLE_Z` standard deviations
    above (the energy's, ``2 sqrt(E (1/f - 1))``, and the noise's, ``sqrt(2 rank (1/f^2 - 1))``)."""
    f = float(data.screen_pixels.sum()) / max(float(data.test_pixels.sum()), 1.0)
    if f >= 1.0:
        return statistic
    estimate = max((statistic - rank) / f + rank, 0.0)
    sd = float(np.sqrt(4.0 * estimate * (1.0 / f - 1.0) + 2.0 * rank * (1.0 / f ** 2 - 1.0)))
    return estimate + SUBSAMPLE_Z * sd


def needed_gain(k: float, penalty_per_dof: float, excess: float, min_relative_gain: float) -> float:
    """What a cause of ``k`` degrees of freedom must gain to be named (the selection's test)."""
    return max(k * penalty_per_dof, min_relative_gain * excess)


__all__: Sequence[str] = ("SignatureTest", "signature", "score_statistic", "signature_test", "needed_gain",
                          "MAX_SIGNATURE_PARAMS", "NOT_FITTED", "whole_part_bound", "signature_part", "SUBSAMPLE_Z")
