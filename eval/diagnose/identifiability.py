"""Whether the data tell a flexible form's extra parameters apart from the rest of the form.

A flexible form of an effect (``EffectSpec.forms``) adds parameters to its simple form. A
score margin on held-out data says the flexible form fits better; it does not say that
the data determine the added parameters. With K = 4 taps and single-path pixels the 3rd and
5th correlation harmonics alias onto the same 4-cycle error (``a3 e^{i 4 phi} + a5 e^{-i 4
phi}`` times the signal): on a scene whose phases span little of a cycle, any 5th harmonic
is reproduced by a changed 3rd, and a fit that reports both is reporting noise and the
optimiser's path.

The test, per group of extra parameters ``g`` (the parameters sharing a name prefix:
``h5_amplitude`` and ``h5_phase_rad`` are ``h5``), on the training pixels the fit used:

- ``r_g``, the whitened change of the prediction when ``g`` is switched off (its "off"
  values) with every other parameter at its fitted value: what ``g`` does;
- the part of ``r_g`` that the form's other parameters cannot reproduce to first order,
  ``|(I - P_rest) r_g|^2`` with ``P_rest`` the projection onto the span of their Jacobian
  columns (the profiled chi-square gain of ``g``, a likelihood-ratio statistic);
- ``g`` is **identified** when that unique part exceeds its degrees of freedom times the
  selection's penalty per degree of freedom (ln n, the same BIC price
  :func:`tofhil.eval.diagnose.selection.greedy_select` charges).

Whether ``g`` *could* be told apart does not depend on how large the fit happened to make
it (in a degenerate pair the optimiser splits the error arbitrarily, or leaves ``g`` near
its start): ``shared``, the largest squared canonical correlation between the span of
``g``'s Jacobian columns and the rest's, is the share of ``g``'s information in its least
distinguishable direction that the rest of the form also carries. At the size the data show
the effect (the chi-square of switching the whole form off), ``(1 - shared)`` of it is what
could tell ``g`` apart; below the price of ``g``'s parameters, ``g`` and the group it shares
most with **cannot be told apart** on this session.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from tofhil.eval.diagnose.heldout import HeldOutData, predict_fit

def param_group(name: str) -> str:
    """The group of a fitted parameter: its name up to the first underscore
    (``h5_phase_rad`` -> ``h5``, ``spline_q1`` -> ``spline``, ``b4`` -> ``b4``)."""
    return name.split("_", 1)[0]


@dataclass
class GroupTest:
    """The identifiability test of one group of extra parameters."""

    group: str
    params: list[str]
    #: chi2 of what the group changes at its fitted values (whitened, training pixels).
    change_chi2: float
    #: chi2 of the part of that change the form's other parameters cannot reproduce.
    unique_chi2: float
    #: The price: the group's degrees of freedom times the penalty per degree of freedom.
    needed_chi2: float
    #: Share of the group's least distinguishable direction the rest of the form carries.
    shared: float
    #: chi2 that could tell the group apart at the size the data show the effect.
    resolvable_chi2: float
    #: The other group sharing most with it.
    closest: str | None

    @property
    def identified(self) -> bool:
        return bool(self.unique_chi2 > self.needed_chi2)

    @property
    def confused(self) -> bool:
        """The data could not tell it from ``closest`` whatever its size up to the effect's."""
        return bool(self.closest is not None and self.resolvable_chi2 <= self.needed_chi2)

    def to_json(self) -> dict[str, Any]:
        return {"group": self.group, "params": self.params, "change_chi2": round(self.change_chi2, 2),
                "unique_chi2": round(self.unique_chi2, 2), "needed_chi2": round(self.needed_chi2, 2),
                "shared": round(self.shared, 6), "resolvable_chi2": round(self.resolvable_chi2, 2),
                "identified": self.identified, "cannot_tell_from": self.closest if self.confused else None}


@dataclass
class Identifiability:
    """The test of every extra group of one flexible form, and what to say about it."""

    effect: str
    form: str
    groups: list[GroupTest] = field(default_factory=list)
    #: The session's taps per frequency and number of frequencies (for the message).
    n_taps: int = 0
    n_freq: int = 1
    #: Tested again at the selection's final values (after the joint refit and any later
    #: effects), the form having been chosen earlier.
    after_later: bool = False
    #: Kept although not identified: the simpler form refitted was worse on held-out data.
    kept: bool = False
    #: The partial form fitted instead (this form without its unidentified groups), if any.
    partial: str = ""

    @property
    def identified(self) -> bool:
        return bool(all(g.identified for g in self.groups))

    @property
    def lines(self) -> list[str]:
        """One sentence per unidentified group."""
        where = f"with {self.n_taps} taps" + (f" and {self.n_freq} frequencies" if self.n_freq > 1 else "")
        out = []
        for g in self.groups:
            if g.identified:
                continue
            if g.confused:
                why = (f"{g.closest} and {g.group} cannot be told apart {where} on this scene "
                       f"({100 * g.shared:.1f} % of {g.group}'s information is {g.closest}'s too: at the size of "
                       f"the effect, chi2 {g.resolvable_chi2:.1f} could separate them, below the {g.needed_chi2:.1f} "
                       f"its {len(g.params)} parameters cost)")
            else:
                why = (f"{g.group} changes nothing the data can tell {where} (chi2 {g.change_chi2:.1f} of its own, "
                       f"{g.unique_chi2:.1f} that the rest of the form cannot reproduce, below the "
                       f"{g.needed_chi2:.1f} its {len(g.params)} parameters cost)")
            verb = ("kept although not identified at the final fit (the simpler form refitted is worse on "
                    "held-out data)" if self.kept else
                    "replaced by the simpler form at the final fit (after the joint refit and any later effects)"
                    if self.after_later else f"not chosen whole (fitted without {g.group}: {self.partial})"
                    if self.partial else "not chosen")
            out.append(f"{self.effect}: form {self.form} {verb}: {why}")
        return out

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "form": self.form, "identified": self.identified, "after_later": self.after_later,
                "kept": self.kept, "partial": self.partial,
                "groups": [g.to_json() for g in self.groups], "text": self.lines}


def _span(columns: np.ndarray, rtol: float = 1e-8) -> np.ndarray:
    """An orthonormal basis of the columns' span (near-zero directions dropped: a harmonic's
    phase at zero amplitude changes nothing)."""
    if columns.shape[1] == 0:
        return columns
    u, s, _ = np.linalg.svd(columns, full_matrices=False)
    keep = s > rtol * max(float(s[0]), 1e-300) if s.size else s.astype(bool)
    return u[:, keep]


def _projected_sq(basis: np.ndarray, r: np.ndarray) -> float:
    return float(np.sum((basis.T @ r) ** 2)) if basis.shape[1] else 0.0


def assess_form(model: Any, data: HeldOutData, fitted: Mapping[str, Mapping[str, float]], effect: str,
                spec: Any, simple: Any, penalty_per_dof: float) -> Identifiability:
    """Test each group of ``spec``'s parameters that ``simple`` (the effect's simple form)
    lacks, at the fitted values ``fitted`` (every active effect's; ``effect`` in ``spec``'s
    form). ``model.predict`` takes the fitted values; the Jacobian uses the same forward
    differences as the fit (a twentieth of each parameter's typical step)."""
    names = [p.name for p in spec.params]
    simple_names = {p.name for p in simple.params}
    extra = [n for n in names if n not in simple_names]
    out = Identifiability(effect=effect, form=spec.form, n_taps=len(data.theta_rad), n_freq=int(data.n_freq))
    if not extra:
        return out
    values = {n: float(fitted[effect].get(n, p.off)) for n, p in zip(names, spec.params)}

    def w(vals: Mapping[str, float]) -> np.ndarray:
        trial = {e: dict(v) for e, v in fitted.items()}
        trial[effect] = dict(vals)
        return data.whitened_residual(predict_fit(model, data, trial), "fit")

    (r0, jac), = form_jacobian(model, data, fitted, effect, spec, ("fit",))
    groups: dict[str, list[int]] = {}
    for i, n in enumerate(names):
        groups.setdefault(param_group(n), []).append(i)
    bases = {g: _span(jac[:, idx]) for g, idx in groups.items()}
    r_all = w({**values, **{p.name: p.off for p in spec.params}}) - r0
    effect_chi2 = float(r_all @ r_all)  # the size the data show the effect
    for g in dict.fromkeys(param_group(n) for n in extra):
        idx = groups[g]
        r_g = w({**values, **{names[i]: spec.params[i].off for i in idx}}) - r0  # what the group changes
        change = float(r_g @ r_g)
        rest = [i for i in range(len(names)) if i not in idx]
        unique = change - _projected_sq(_span(jac[:, rest]), r_g)
        shared_with = {o: _shared(bases[g], b) for o, b in bases.items() if o != g}
        closest = max(shared_with, key=lambda o: (shared_with[o], o)) if shared_with else None
        shared = _shared(bases[g], _span(jac[:, rest])) if rest else 0.0
        out.groups.append(GroupTest(group=g, params=[names[i] for i in idx], change_chi2=change,
                                    unique_chi2=max(unique, 0.0), needed_chi2=float(len(idx) * penalty_per_dof),
                                    shared=shared, resolvable_chi2=(1.0 - shared) * max(effect_chi2, change),
                                    closest=closest))
    return out


def form_jacobian(model: Any, data: HeldOutData, fitted: Mapping[str, Mapping[str, float]], effect: str,
                  spec: Any, parts: tuple[str, ...] = ("fit",)) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per data part: the whitened residual at the fitted values and its Jacobian in
    ``spec``'s parameters of ``effect`` (every other effect held). Forward differences of a
    twentieth of each parameter's typical step, as the fit's own; one prediction per
    parameter serves every part."""
    values = {p.name: float(fitted[effect].get(p.name, p.off)) for p in spec.params}

    def w(vals: Mapping[str, float]) -> list[np.ndarray]:
        trial = {e: dict(v) for e, v in fitted.items()}
        trial[effect] = dict(vals)
        # the fit pixels alone are rendered when they are all that is read
        pred = predict_fit(model, data, trial) if set(parts) <= {"fit"} else model.predict(trial)
        return [data.whitened_residual(pred, part) for part in parts]

    r0 = w(values)
    cols: list[list[np.ndarray]] = [[] for _ in parts]
    for p in spec.params:
        h = 0.05 * p.scale
        if values[p.name] + h > p.hi:
            h = -h
        for i, r in enumerate(w({**values, p.name: values[p.name] + h})):
            cols[i].append((r - r0[i]) / h)
    return [(r0[i], np.stack(cols[i], axis=1) if cols[i] else np.zeros((r0[i].size, 0))) for i in range(len(parts))]


def _shared(a: np.ndarray, b: np.ndarray) -> float:
    """The largest squared canonical correlation between two spans (orthonormal bases): 1
    when a direction of one is also in the other; 1 for a group whose columns are all zero
    (it has no direction of its own)."""
    if a.shape[1] == 0:
        return 1.0
    if b.shape[1] == 0:
        return 0.0
    return float(min(np.linalg.svd(a.T @ b, compute_uv=False)[0] ** 2, 1.0))
