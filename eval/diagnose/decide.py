"""How a diagnosis decides, after the selection: the verdict on the extended scene as written,
what is accounted rather than vetoed, the scene-mismatch rule's geometry test, and the per-frame
drift against the static causes.

The rules, in the order :func:`tofhil.eval.diagnose.run.diagnose` applies them:

1. :func:`moved_clean_channels`: a cause that puts a part into a channel the base twin had
   clean is accounted (a note: the explanation is partial there), never unnamed;
2. :func:`settle`: the extended scene as written must keep the gain that named its causes
   (else they are "fitted but not named"); a verdict of "the scene does not match" (only for a
   residual organised by objects and edges, :class:`Judge`) names nothing; a search stopped at
   its limit says so;
3. :func:`drift_alone` and :func:`with_drift`: the per-frame drift replaces static causes that
   only took up its mean, and is the verdict where nothing else was;
4. :func:`rmse_worse_notes`: an unweighted figure a named cause leaves worse is said.

Every test they use is :mod:`tofhil.eval.diagnose.verdict`'s (one false-alarm rate, ALPHA), and
the verdict itself is built there, once per judgement, by :func:`~tofhil.eval.diagnose.verdict.verdict`.
Changing how a verdict is decided is this module and that one (docs/diagnose.md, "How a
diagnosis decides").
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from tofhil.eval.diagnose import verdict as V
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


class Judge:
    """The verdict on a prediction of the held-out data, with its per-channel and per-object misfits."""

    def __init__(self, data: HeldOutData, selection: Selection, base_pred: np.ndarray, object_id: np.ndarray,
                 object_names: dict[int, str], sizes: V.EffectSize | None = None) -> None:
        self.data, self.selection, self.object_id, self.object_names = data, selection, object_id, object_names
        self.base_pred, self.sizes = base_pred, sizes
        self.nu = V.noise_dof(data)
        self.n = max(data.n_values("test"), 1)
        self.objects_before = V.object_misfits(data, base_pred, self.nu, object_id, object_names)
        self.geometry: GeometryEvidence | None = None
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

    def __call__(self, after_pred: np.ndarray, causes: list[str]) -> tuple[V.Verdict, dict, dict, list[str]]:
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
        self.geometry = after
        v = V.verdict(searched=selection.searched, causes=causes, n_values=self.n, nu=self.nu,
                      before_per_value=selection.baseline_chi2_test / self.n,
                      after_per_value=data.chi2(after_pred, "test") / self.n, worse=worse,
                      objects_before=self.objects_before, objects_after=objects_after, pinned=selection.at_bounds,
                      rejected_for_channels=selection.rejected_for_channels, geometry=self.geometry)
        return v, ch_after, objects_after, worse


def settle(selection: Selection, data: HeldOutData, sizes: V.EffectSize, judge: Judge, extend: Callable[[dict], tuple[Any, np.ndarray]],
            base_pred: np.ndarray, after_pred: np.ndarray, after_model: Any, max_effects: int) -> tuple:
    """The verdict on the extended scene as written: a set that loses its gain there, or that
    was fitted to a scene that does not match, is "fitted but not named" and the extended
    scene is the base again."""
    verdict, ch_after, objects_after, worse = judge(after_pred, list(selection.causes))
    size_after = sizes.compare(base_pred, after_pred)
    if selection.causes and not V.EffectSize.worth_naming(size_after):
        # the extended scene as written and read back must keep the gain the selection saw
        verdict.notes.append("fitted but not named: " + ", ".join(selection.causes) + " (as the extended scene: "
                             + V.EffectSize.describe(size_after) + "; " + V.effect_size_rule() + ")")
        selection.causes, selection.params = [], {}
        after_model, after_pred = extend({})
        verdict, ch_after, objects_after, worse = judge(after_pred, [])
    elif verdict.kind is V.Kind.SCENE_MISMATCH and selection.causes:
        # No effect is named on a scene that does not match: the extended scene is the base.
        # what the fitted set would have done, on the held-out pixels (a lower misfit can come
        # with a worse depth RMSE: the misfit weighs each pixel by its noise, the RMSE does not)
        n = judge.n
        before, after = data.chi2(base_pred, "test") / n, data.chi2(after_pred, "test") / n
        verdict.notes.append("fitted but not named: " + ", ".join(selection.causes)
                             + f" (with them, held-out misfit {before:.2f} -> {after:.2f} per value; "
                             + V.EffectSize.describe(size_after) + ")")
        selection.causes, selection.params = [], {}
        after_model, after_pred = extend({})
        _, ch_after, objects_after, worse = judge(after_pred, [])
    if verdict.kind is V.Kind.PARTLY_EXPLAINED and len(selection.causes) >= max_effects:
        # The search stopped at its limit, not because nothing significant was left: the rest
        # may be a further effect (the emulated TOFcam635 hides three; with max_effects 2 its
        # clock-skew pattern was left out, or taken up by lens_distortion in older code).
        verdict.notes.append(f"the search stopped at max_effects = {max_effects}: the excess left may hold a "
                             "further effect (diagnose again with a larger --max-effects)")
    return verdict, ch_after, objects_after, worse, after_model, after_pred


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


def drift_alone(model: Any, data: HeldOutData, selection: Selection, drift: Any, penalty: float) -> Any:
    """The drift fitted on the base twin, when it explains the frames as well as the selected
    causes with the drift on top (their parameters charged at ``penalty`` each): then the causes
    only took up the drift's mean. None when the causes are needed."""
    alone = fit_frame_drift(model, data, {}, penalty)
    if alone is None or not alone.named:
        return None
    k = sum(len(v) for e, v in selection.params.items() if e != MAP_EFFECT)
    k += float(selection.details.get(MAP_EFFECT, {}).get("dof", 0.0)) if MAP_EFFECT in selection.params else 0.0
    return alone if alone.chi2_drift <= drift.chi2_drift + penalty * max(k, 1.0) else None


def with_drift(verdict: V.Verdict, drift: Any, judge: Judge, evidence: list[str]) -> V.Verdict:
    """The frames' mean hides a drift (it inflates the frame-to-frame noise instead): a named
    drift is the verdict where nothing else was, on the held-out pixels of every frame."""
    if drift is None:
        return verdict
    evidence.append(drift.text)
    if drift.named and verdict.kind in (V.Kind.WITHIN_NOISE, V.Kind.UNEXPLAINED):
        verdict = V.verdict(searched=True, causes=[DRIFT], n_values=drift.n_values, nu=judge.nu,
                            before_per_value=drift.chi2_static / drift.n_values,
                            after_per_value=drift.chi2_drift / drift.n_values, worse=[],
                            objects_before=judge.objects_before, objects_after=judge.objects_before, pinned={},
                            rejected_for_channels=[])
        verdict.notes.append(drift.text)
    elif drift.named:
        verdict.notes.append(drift.text)
    return verdict


def rmse_worse_notes(verdict: V.Verdict, gain: dict[str, dict[str, float]]) -> None:
    """The misfit weighs each pixel by its noise and caps outliers; the RMSE does neither. A
    named cause that leaves an unweighted figure worse is said, not hidden."""
    for k, label, scale, unit in (("depth_rmse_m", "depth RMSE", 1e3, " mm"), ("amplitude_rmse", "amplitude RMSE", 1.0, "")):
        b, a = gain[k]["before"], gain[k]["after"]
        if np.isfinite(a) and np.isfinite(b) and a > 1.005 * b:  # (0.5 %: not a rounding)
            verdict.notes.append(f"held-out {label} {b * scale:.4g} -> {a * scale:.4g}{unit} is worse after the fit: "
                                 "the misfit that chose the cause weighs pixels by their noise and caps outliers, "
                                 "the RMSE does not")
