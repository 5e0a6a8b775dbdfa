"""Diagnose: what the twin gets wrong, why, the extended model, and the held-out gain.

1. Split the measured session into training and held-out data (``heldout``).
2. Set the twin to the session's camera and sensor settings and render it (``twin_model``).
3. Map the residuals (complex signal per frequency, depth, amplitude).
4. Fit every effect of the library on the training data, score it on held-out data with a
   parameter penalty, and add effects greedily while the gain is significant (``selection``).
5. Write the extended scene (base scene + fitted effects), load it back, re-render, and
   report the gain on held-out data: residual RMSE, ICP inlier RMSE, NDT scores, per region.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.outputs import prepare_output_dir, refuse_existing
from tofhil.demod import bad_tap_pixels
from tofhil.errors import TofhilError
from tofhil.eval.metrics import core as M
from tofhil.eval.diagnose.channels import residual_by_channel, sensor_noise_variance
from tofhil.eval.diagnose.leftover import what_is_left
from tofhil.eval.diagnose.depth_heldout import observable_candidates, split_for_diagnosis
from tofhil.eval.diagnose.geometry import GeometryEvidence
from tofhil.eval.diagnose.heldout import HeldOutData, depth_from_signal
from tofhil.eval.diagnose.linear_forms import MAP_EFFECT
from tofhil.eval.diagnose.observability import Observability
from tofhil.eval.diagnose.selection import Selection, greedy_select
from tofhil.eval.diagnose.signal_scale import (SignalScale, fit_signal_scale, needs_scale, scaled_scene,
                                               without_fixed_pattern)
from tofhil.eval.diagnose.twin_model import TwinModel
from tofhil.eval.diagnose import decide as D
from tofhil.eval.diagnose import verdict as V
from tofhil.eval.diagnose.decide import DRIFT
from tofhil.frames import DepthFrame
from tofhil.session import open_session
from tofhil.sim.effects import ORDER, PoseEffect, StrayLightEffect


@dataclass
class DiagnosisResult:
    cause: str | None
    causes: list[str]
    ranked: list[dict[str, Any]]
    rounds: list[list[dict[str, Any]]]
    gain: dict[str, dict[str, float]]
    regions: dict[str, dict[str, dict[str, Any]]]
    extended_scene: str
    params: dict[str, dict[str, float]]
    evidence: list[str]
    chi2_per_value: dict[str, float]
    data: HeldOutData = field(repr=False)
    maps: dict[str, np.ndarray] = field(repr=False, default_factory=dict)
    evaluations: dict[str, M.Evaluation] = field(repr=False, default_factory=dict)
    seconds: float = 0.0
    #: What the diagnosis claims (``eval/diagnose/verdict.py``), and the figures behind it.
    verdict: V.Verdict | None = None
    #: Held-out misfit per channel before and after, with its noise margin and a "worse" flag.
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Connected regions left above noise after the fit (before it when nothing was named).
    residual_regions: list[dict[str, Any]] = field(default_factory=list)
    #: Each object's held-out misfit per value before and after, and whether it is above noise.
    objects: dict[str, dict[str, Any]] = field(default_factory=dict)
    observability: Observability = field(default_factory=Observability)
    #: What the residual left looks like: edges, smooth field errors, fixed patterns, spots
    #: (``eval/diagnose/structure.py``), each above its noise.
    structure: list[dict[str, Any]] = field(default_factory=list)
    #: Per cause, the form fitted ("" the effect's simple form, else a flexible form's name).
    forms: dict[str, str] = field(default_factory=dict)
    #: The per-frame drift test (``eval/diagnose/linear_forms.py``): None when not searched.
    drift: dict[str, Any] | None = None
    #: The minimum effect size for naming (``verdict.EffectSize``): the rule, each channel's
    #: held-out RMSE base twin -> extended twin with its noise and minimum gain, and the
    #: effects that were fitted but too small to name.
    effect_size: dict[str, Any] = field(default_factory=dict)
    #: Per cause, the flexible forms not chosen because the data do not identify their extra
    #: parameters (``eval/diagnose/identifiability.py``): which parameters cannot be told apart.
    identifiability: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    #: Per cause, the other families the held-out data cannot tell from it ("A or B").
    alternatives: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    #: The defective pixels found before any fit (``eval/diagnose/defects.py``), excluded.
    defects: dict[str, Any] = field(default_factory=dict)
    #: The held-out residual by channel (``eval/diagnose/channels.py``), base twin and extended.
    channel_table: dict[str, Any] = field(default_factory=dict)
    #: What the fit leaves, said as a signature (``eval/diagnose/leftover.py``); None when
    #: the verdict leaves nothing to say.
    left: str | None = None
    #: The twin's signal scale: fitted where the session does not state the chain that made it
    #: (``eval/diagnose/signal_scale.py``).
    signal_scale: SignalScale = field(default_factory=SignalScale)
    #: Where the twin's camera and sensor settings came from (``sim/session_setup.py``).
    setup_note: str = ""
    #: Whether the residual left is organised by the scene's objects and edges, the test behind
    #: "the scene does not match" (``eval/diagnose/geometry.py``); None: too few pixels.
    geometry: GeometryEvidence | None = None
    #: The decision's ledger (``eval/diagnose/decide.py``): the rules in order, the causes
    #: named and the effects fitted but not named, each with the rule and its figures; and the
    #: sets the search found from its first choices (``searches``: causes, held-out score, chosen).
    ledger: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"verdict": self.verdict.to_json() if self.verdict else None, "channels": self.channels,
                "residual_regions": self.residual_regions, "objects": self.objects,
                "cause": self.cause, "causes": self.causes, "forms": self.forms, "ranked": self.ranked, "gain": self.gain,
                "regions": self.regions, "extended_scene": self.extended_scene, "params": self.params,
                "evidence": self.evidence, "chi2_per_value": self.chi2_per_value, "rounds": self.rounds,
                "depth_rmse_definition": f"{M.DEPTH_RMSE}, held-out pixels and frames",
                "split": {"train_frames": self.data.n_train_frames, "test_frames": self.data.n_test_frames,
                          "train_pixels": int(self.data.train_pixels.sum()),
                          "test_pixels": int(self.data.test_pixels.sum()),
                          "offset_channel": self.data.offset_channel,
                          # the data are means of binned x binned sensor pixels (1: the sensor's own)
                          "binned": self.data.binned_by},
                "data_path": self.data.channels, "noise": self.data.noise,
                "observability": self.observability.to_json(), "residual_structure": self.structure,
                "drift": self.drift, "effect_size": self.effect_size, "identifiability": self.identifiability,
                "alternatives": self.alternatives, "defects": self.defects, "residual_by_channel": self.channel_table,
                "left": self.left, "signal_scale": self.signal_scale.to_json(),
                "geometry": self.geometry.to_json() if self.geometry is not None else None,
                "twin_setup": self.setup_note, "ledger": self.ledger}
        # (the run time is in the report, not here: the same inputs give the same file, bit for bit)


#: (kept here too: callers import it from diagnose)
distance_defined = V.distance_defined


#: The region of the held-out pixels (the gain is measured there).
HELD_OUT = "held-out"
#: The pixels the held-out figures use, written next to the report: ``tofhil compare
#: --mask`` with it gives the same figures for the capture against the twin.
HELD_OUT_MASK = "heldout_pixels.npy"
#: The fitted range offset map [H, W] (m), beside the extended scene that loads it.
OFFSET_MAP_FILE = "range_offset_map.npy"


def heldout_frames(data: HeldOutData, prediction: np.ndarray, defined: np.ndarray) -> tuple[DepthFrame, DepthFrame]:
    """The held-out measurement and a prediction as depth frames (radial distance and mean
    amplitude from the complex signal): measured pixels are valid where usable (signal above
    noise, no clipped tap), predicted ones where ``defined``; both only where lit
    (:func:`tofhil.eval.metrics.core.lit_pixels`)."""
    nf = data.n_freq
    cam = data.camera
    s_meas, s_pred = data.s_test[:nf], prediction[:nf]
    frames = []
    for s, valid in ((s_meas, data.usable), (s_pred, defined)):
        amp = np.abs(s).mean(axis=0)
        lit = M.lit_pixels(amp)  # the rule compare applies: unlit pixels have no phase to compare
        frames.append(DepthFrame(distance_m=depth_from_signal(s, data.freq_hz), kind="radial", camera=cam,
                                 amplitude=amp, valid=valid if lit is None else valid & lit))
    return frames[0], frames[1]


def heldout_metrics(data: HeldOutData, prediction: np.ndarray, defined: np.ndarray,
                    object_regions: list[M.Region] = (), *, ndt_cell_m: float = 0.05,
                    icp_max_distance_m: float = 0.05) -> tuple[dict[str, float], dict[str, np.ndarray], M.Evaluation]:
    """Residual, point-cloud and NDT figures of a prediction against the held-out data, from
    the evaluation core: the region :data:`HELD_OUT` (held-out pixels) and each object's
    held-out pixels; a pixel counts where it is valid in both (usable, and ``defined`` for
    the prediction -- the same for every prediction compared)."""
    measured, twin = heldout_frames(data, prediction, defined)
    held = M.Region(HELD_OUT, data.test_pixels, "held-out")
    objs = [M.Region(r.name, r.mask & data.test_pixels, r.kind) for r in object_regions]
    ev = M.evaluate(measured, twin, [held] + [r for r in objs if r.mask.sum() >= 5],
                    wrap_m=M.wrap_period(data.freq_hz), cloud_regions=[HELD_OUT], cell_size=ndt_cell_m,
                    threshold=icp_max_distance_m, icp_max_distance=icp_max_distance_m, include_all=False,
                    source="held-out data", freq_hz=data.freq_hz)
    h = ev.regions[HELD_OUT]
    metrics = {"depth_rmse_m": h.depth_rmse_m, "depth_median_m": h.depth_residual_m.median,
               "depth_mad_m": h.depth_residual_m.mad, "amplitude_rmse": h.amplitude_difference.rmse,
               "chi2_per_value": data.chi2(prediction, "test") / max(data.n_values("test"), 1),
               "unwrap_error_pixels": h.unwrap_error_pixels or 0, "depth_compared_pixels": h.depth_residual_m.n}
    if h.cloud is not None and h.ndt is not None:
        metrics["icp_inlier_rmse_m"] = h.cloud.icp_inlier_rmse
        metrics["icp_fitness"] = h.cloud.icp_fitness
        metrics["ndt_score_per_point"] = h.ndt.score_per_point
        metrics["ndt_nvtl"] = h.ndt.nvtl
        metrics["ndt_mean_likelihood_trilinear"] = h.ndt.mean_likelihood_trilinear
    # unwrapping errors are counted and mapped apart: no surface of the twin is that wrong
    unwrapped = ev.maps.unwrap_error if ev.maps.unwrap_error is not None else np.zeros(data.camera.shape, bool)
    maps = {"depth_measured": np.asarray(measured.radial_m), "depth_twin": np.asarray(twin.radial_m),
            "depth_residual": np.where(unwrapped, np.nan, ev.maps.depth_residual_m),
            "unwrap_error": unwrapped.astype(float), "amplitude_residual": ev.maps.amplitude_difference,
            "ndt_likelihood": ev.ndt_map if ev.ndt_map is not None else np.full(data.camera.shape, np.nan)}
    return metrics, maps, ev


def residual_structure(data: HeldOutData, prediction: np.ndarray, maps: dict[str, np.ndarray], object_id: np.ndarray,
                       object_names: dict[int, str]) -> list[Any]:
    """The structures of the depth and amplitude residual left by ``prediction``
    (:mod:`tofhil.eval.diagnose.structure`), each against the noise of its pixels: the depth
    noise from the phasor's tangential variance (the best frequency), the amplitude's as a
    relative error from its radial variance."""
    from tofhil.eval.diagnose import structure as DS

    nf = data.n_freq
    a = np.maximum(np.abs(data.s_test[:nf]), 1e-30)
    sigma_depth, sigma_amp = V.channel_sigmas(data)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_amp = np.log(a.mean(axis=0) / np.abs(prediction[:nf]).mean(axis=0))
    edges = DS.edge_mask(maps["depth_measured"], data.usable, object_id)
    centre = (data.camera.cx, data.camera.cy)
    out = DS.channel_structure("depth", maps["depth_residual"], sigma_depth, data.usable, object_id, object_names,
                               edges, centre)
    out += DS.channel_structure("amplitude", np.where(np.isfinite(maps["depth_residual"]), log_amp, np.nan),
                                sigma_amp, data.usable, object_id, object_names, edges, centre)
    return out


def _evidence(selection: Selection, data: HeldOutData) -> list[str]:
    lines = []
    n = selection.n_test
    excess = selection.baseline_chi2_test - n
    lines.append(f"held-out misfit of the base twin: chi2 = {selection.baseline_chi2_test:.0f} for {n} values "
                 f"({selection.baseline_chi2_test / n:.2f} per value; 1.0 is noise)")
    for i, rnd in enumerate(selection.rounds):
        if not rnd:
            continue
        # the round's chosen effect (the best-scoring significant one), else its best score
        chosen = selection.causes[i] if i < len(selection.causes) else None
        best = next((c for c in rnd if c.effect == chosen), rnd[0])
        runner = next((c for c in rnd if c is not best), None)
        verdict = "selected" if chosen is not None else "not significant"
        others = [f or "simple" for f in best.forms if f != best.form]
        form = f" ({best.form or 'simple'} form; preferred over {', '.join(others)})" if others else ""
        alone = "" if best is rnd[0] else f"; {rnd[0].effect} alone scores best in this round"
        lines.append(f"round {i + 1}: {'best ' if best is rnd[0] else ''}{best.effect}{form} removes {100 * best.relative_gain:.1f}% of the held-out "
                     f"misfit (score gain {best.delta_score:.0f}, "
                     + (f"{best.dof:.{0 if best.details else 1}f} effective degrees of freedom" if best.details or best.prior
                        else f"{best.dof:g} degrees of freedom")
                     + f") -- {verdict}"
                     + (f"; runner-up {runner.effect} {100 * runner.relative_gain:.1f}%" if runner else "") + alone)
    for i, rnd in enumerate(selection.rounds):
        for c in rnd:
            # the channels a selected cause makes worse (the explanation is partial there); those
            # of candidates not chosen are in diagnosis.json's rounds, not worth a reader's line
            if c.worse_channels and i < len(selection.causes) and selection.causes[i] == c.effect:
                lines.append(f"round {i + 1}: {c.effect} lowers the held-out score and makes "
                             f"{', '.join(c.worse_channels)} worse beyond its noise -- selected: the explanation "
                             "is partial there")
    if len(selection.searches) > 1:
        lines.append("searched along the greedy path and from its rounds' closest runners-up; the sets found "
                     "(held-out score), the lowest chosen unless a set the data cannot tell from it is simpler: "
                     + "; ".join(f"{' + '.join(s['causes']) or 'nothing'} {s['score']:.0f}"
                                 + (" (chosen)" if s["chosen"] else "") for s in selection.searches))
    for e, names in selection.at_bounds.items():
        if names:
            lines.append(f"{e}: {', '.join(names)} fitted at the bound of the range searched")
    if not selection.searched:
        lines.append("nothing searched (max effects 0)")
    elif not selection.causes:
        lines.append("no effect of the library explains a significant part of the held-out residual"
                     + (" (the twin is consistent with the measurement within its noise)" if excess < 0.05 * n else ""))
    for e in selection.causes:
        for test in selection.unidentified.get(e, ()):
            lines.extend(test.lines)
    for e in selection.causes:
        lines.extend(a.text for a in selection.alternatives.get(e, ()))
    for e, prior in selection.priors.items():
        if e in selection.causes:
            strength = (f"strength {prior['prior_strength']:g} chosen" if prior["prior_strength"] else
                        "no shrinkage asked for")
            lines.append(f"{e}: form {selection.forms.get(e) or 'simple'} with its prior ({strength} on held-out "
                         f"blocks of the training frames): {prior['dof']:.1f} effective degrees of freedom of its "
                         f"{prior['params']} parameters")
    for c in (c for rnd in selection.rounds[:1] for c in rnd if c.details.get("pixel_part")):
        lines.append(f"{c.effect}: fitted form {c.details['form']} ({c.details['dof']:.1f} effective degrees of "
                     f"freedom); per-pixel part {c.details['pixel_part']}")
    return lines


def _held_out_data(session_path: str | Path, scene: Any, facts: Any, *, block_px: int,
                   max_frames: int | None) -> tuple[HeldOutData, bool]:
    """The session split into training and held-out data, and whether it has depth only."""
    with open_session(session_path) as s:
        if s.has_histograms or getattr(scene, "direct_tof", None) is not None:
            # the twin diagnosed here is the correlation forward model (taps, phase, effects)
            raise TofhilError("direct ToF (SPAD histograms) cannot be diagnosed: the twin's effects model "
                              "correlation ToF", file=session_path if s.has_histograms else scene.source,
                              field="histograms" if s.has_histograms else "direct_tof",
                              expected="a correlation-ToF session and scene")
        data = split_for_diagnosis(s, scene, block_px=block_px, max_frames=max_frames, valid_mask=facts.valid_mask,
                                   amplitude_model_error=facts.amplitude_model_error)
        return data, not s.has_raw


class _ExtendedScene:
    """The base scene with the fitted effects: its text (with a range offset map beside it),
    the twin it reads back as (in memory, for the decision: nothing is written before it is
    made) and, once the decision is made, the file."""

    def __init__(self, model: TwinModel, data: HeldOutData, ext_path: Path | None,
                 render_kwargs: dict[str, Any] | None) -> None:
        self.model, self.data, self.path, self.render_kwargs = model, data, ext_path, render_kwargs
        self.map_path = ext_path.parent / OFFSET_MAP_FILE if ext_path is not None else None

    def text(self, fitted: dict[str, dict[str, Any]], gain: float | None = None) -> str:
        """The file's text: a range offset map named by its file beside the scene (relative: the
        output directory can be moved) when there is a file to write, else inline. ``gain``: the
        set's profiled gain when the caller has it (a full prediction each time it is computed)."""
        import yaml

        from tofhil.sim.scene import scene_to_yaml

        block = self.model.extended_effects_block(fitted)
        scene = dataclasses.replace(self.model.scene, effects=block)
        g = self.model.gain(fitted) if gain is None else gain
        if g != 1.0:
            # the device gain profiled for this set is the scene's: written into its sensor
            scene = scaled_scene(scene, SignalScale(factor=g, fitted=True))
        if self.map_path is None or MAP_EFFECT not in fitted:
            return scene_to_yaml(scene)
        # the scene is made without the map (a Scene reads the files it names, and this one is
        # written after the decision), which goes back in at its place in the forward-model order
        entry = {k: v for k, v in block.pop(MAP_EFFECT).items() if k != "values"} | {"file": OFFSET_MAP_FILE}
        header, body = scene_to_yaml(dataclasses.replace(scene, effects=block)).split("\n", 1)
        doc = yaml.safe_load(body)
        doc["effects"] = {n: entry if n == MAP_EFFECT else doc["effects"][n] for n in ORDER
                          if n == MAP_EFFECT or n in doc["effects"]}
        return header + "\n" + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)

    def _map(self, fitted: dict[str, dict[str, Any]]) -> np.ndarray:
        return np.asarray(fitted[MAP_EFFECT]["values"], dtype=np.float64)

    def scene(self, fitted: dict[str, dict[str, Any]], gain: float | None = None) -> Any:
        """The scene the file will read back as, without writing it (the map, which the file
        names, given by its values: the same numbers its .npy file holds)."""
        from tofhil.sim.scene import scene_from_dict, scene_from_yaml
        from tofhil.yamlio import load_yaml

        text = self.text(fitted, gain)
        if self.path is None:
            return scene_from_yaml(text)
        source, base_dir = str(self.path), self.path.resolve().parent
        if MAP_EFFECT not in fitted:
            return scene_from_yaml(text, source=source, base_dir=base_dir)
        doc = load_yaml(text, source=source)
        doc["effects"][MAP_EFFECT] = {"values": self._map(fitted)}
        scene = scene_from_dict(doc, source=source, base_dir=base_dir)
        scene.text = text
        return scene

    def __call__(self, fitted: dict[str, dict[str, Any]]) -> tuple[TwinModel, np.ndarray]:
        """The extended scene's twin and its prediction, in memory."""
        # predicted with the base twin's sensor (its signal scale), times the gain profiled for
        # this set where the scale was fitted (the gain the file's sensor holds)
        sensor = self.model.scene.sensor
        g = self.model.gain(fitted)
        if g != 1.0:
            sensor = scaled_scene(self.model.scene, SignalScale(factor=g, fitted=True)).sensor
        after_model = TwinModel(self.scene(fitted, g), self.data, render_kwargs=self.render_kwargs,
                                renders_from=self.model, sensor=sensor)
        return after_model, after_model.predict({})

    def write(self, fitted: dict[str, dict[str, Any]]) -> None:
        """Write the extended scene, once, after the decision (a map beside it; a stale one removed)."""
        if self.path is None:
            return
        if self.map_path is not None:
            if MAP_EFFECT in fitted:
                np.save(self.map_path, self._map(fitted))
            else:
                self.map_path.unlink(missing_ok=True)
        self.path.write_text(self.text(fitted))


def _ranking(selection: Selection) -> tuple[list[dict[str, Any]], list[list[dict[str, Any]]]]:
    """The first round's candidates in full and every round's in brief, as JSON."""
    ranked = [{"effect": c.effect, "params": D.fitted_values_json(c.effect, c.params, c.details), "score": c.score,
               "delta_score": c.delta_score, "relative_gain": c.relative_gain, "significant": c.significant,
               "chi2_test": c.chi2_test, "n_params": c.n_params, "worse_channels": c.worse_channels,
               "at_bounds": c.at_bounds, "form": c.form, "dof": round(c.dof, 2), "forms": c.forms,
               "worth_naming": c.worth_naming, "rmse": {ch: g.to_json() for ch, g in c.rmse.items()},
               "prior": c.prior}
              for c in selection.first_round]
    rounds = [[{"effect": c.effect, "form": c.form, "delta_score": c.delta_score, "relative_gain": c.relative_gain,
                "significant": c.significant, "worse_channels": c.worse_channels} for c in rnd]
              for rnd in selection.rounds]
    return ranked, rounds


def _signature_maps(model: TwinModel, data: HeldOutData, causes: list[str],
                    params: dict[str, dict[str, Any]]) -> dict[str, np.ndarray]:
    """Each named cause's signature: how it changes the twin's depth and amplitude."""
    maps = {}
    nf = data.n_freq
    p_with = model.predict(params)
    for e in causes:
        p_without = model.predict({k: v for k, v in params.items() if k != e})
        change = M.wrapped_difference(depth_from_signal(p_with[:nf], data.freq_hz),
                                      depth_from_signal(p_without[:nf], data.freq_hz), data.unambiguous_range_m)
        maps[f"signature_depth_{e}"] = np.where(distance_defined(data, p_with, p_without), change, np.nan)
        maps[f"signature_amplitude_{e}"] = (np.abs(p_with[:nf]) - np.abs(p_without[:nf])).mean(axis=0)
    return maps


def _channel_tables(data: HeldOutData, model: TwinModel, after_model: TwinModel, base_pred: np.ndarray,
                    after_pred: np.ndarray) -> dict[str, Any]:
    """The held-out residual by channel with the base twin and with the extended one."""
    noise = sensor_noise_variance(data)
    out = {}
    for key, m, pred in (("before", model, base_pred), ("after", after_model, after_pred)):
        taps = m.taps({}) if data.taps_test is not None else None
        out[key] = residual_by_channel(data, pred, taps_measured=data.taps_test, taps_predicted=taps,
                                       model_variance=noise).to_json()
    return out


def _add_sampling_variance(data: HeldOutData, model: TwinModel) -> None:
    """Binned data: the twin's own sampling error is added to the noise of the comparison. A
    bin's noise is ``bin_px`` times below a pixel's, and the twin's estimate of a bin's light
    (finitely many samples over an area with edges and texture) is not exact; every prediction
    shares it (the samples sit where they sit), so it is a variance of the comparison that no
    candidate can remove."""
    extra = model.sampling_variance()
    ratio = float(np.median((extra[:data.n_freq] / data.var_test[:data.n_freq])[:, data.test_pixels]))
    data.var_train = data.var_train + extra
    data.var_test = data.var_test + extra
    data.noise += (f"; plus the binned twin's own sampling variance (two renders with independent sample "
                   f"placement; {100 * ratio:.1f} % of the held-out noise variance at the median pixel)")


def diagnose(session_path: str | Path, scene: Any, *, max_effects: int = 3, min_relative_gain: float = 0.02,
             candidates: list[str] | None = None, block_px: int = 8, max_frames: int | None = None,
             render_kwargs: dict[str, Any] | None = None, progress: Callable[[str], None] | None = None,
             extended_scene_path: str | Path | None = None) -> DiagnosisResult:
    """Run the diagnosis loop on a session against a base scene (a Scene object)."""
    from tofhil.sim.from_capture import capture_scene_facts

    t0 = time.perf_counter()
    facts = capture_scene_facts(scene)
    # the per-frame drift is a form of its own (not an effect of the scene): searched unless
    # a candidate list leaves it out
    want_drift = max_effects > 0 and (candidates is None or DRIFT in candidates)
    candidates = None if candidates is None else [c for c in candidates if c != DRIFT]
    data, depth_only = _held_out_data(session_path, scene, facts, block_px=block_px, max_frames=max_frames)
    candidates, unobservable = observable_candidates(candidates, data, depth_only=depth_only,
                                                     unobservable=facts.unobservable)
    if progress:
        progress(f"channels: {data.channels}; noise: {data.noise}")
        if data.defects is not None and data.defects.count:
            progress(data.defects.text())
    if data.test_pixels.sum() < 20:
        raise TofhilError("too few usable pixels (signal above noise, not saturated) to diagnose",
                          file=session_path, field="raw/taps")
    model = TwinModel(scene, data, render_kwargs=render_kwargs)
    scale = SignalScale()
    why_scale = needs_scale(getattr(scene, "sensor", None), data.sensor_config)
    if why_scale:
        device = model.scene if data.sensor_config is not None else without_fixed_pattern(model.scene)
        if device is not model.scene:
            model = TwinModel(scene, data, render_kwargs=render_kwargs, renders_from=model, sensor=device.sensor)
        scale = fit_signal_scale(data, model.predict({}), why_scale)
        model = TwinModel(scene, data, render_kwargs=render_kwargs, renders_from=model,
                          sensor=scaled_scene(device, scale).sensor)
        # every candidate's prediction gets its own gain: the scale fitted on the base twin
        # would otherwise charge a cause that adds light everywhere for the share it took up
        model.enable_gain_profile()
    if data.bin_px > 1:
        _add_sampling_variance(data, model)
    if progress:
        progress(model.setup.note)
        progress(scale.text())
    base_pred = model.predict({})
    if candidates is None or PoseEffect.name in candidates:
        if progress:
            progress("aligning the twin (ICP)")
        model.align_pose()
    sizes = V.EffectSize(data)
    selection = greedy_select(model, data, candidates=candidates, max_effects=max_effects,
                              min_relative_gain=min_relative_gain, progress=progress, effect_size=sizes)
    evidence = _evidence(selection, data)
    if data.defects is not None and data.defects.count:
        evidence.insert(0, "defects: " + data.defects.text())
    for line in selection.too_small.values():
        evidence.append(f"not named, its held-out gain is too small or makes a channel worse: {line}")
    evidence.extend(selection.exchanges)
    # (an effect fitted in one round and screened out in a later one was fitted: its rounds say how it did)
    fitted = {c.effect for rnd in selection.rounds for c in rnd}
    never = [text for name, text in selection.not_tried.items() if name not in fitted]
    if never:
        from tofhil.eval.diagnose.signature import NOT_FITTED

        evidence.append(f"{NOT_FITTED}: " + "; ".join(never))

    # decide: the rules over the selection's record (read, never changed), the extended scene
    # predicted in memory; written once, after
    ext_path = Path(extended_scene_path) if extended_scene_path else None
    extend = _ExtendedScene(model, data, ext_path, render_kwargs)
    object_id = np.asarray(model.base_render().object_id)
    object_names = {i: o.name for i, o in enumerate(model.scene.objects)}
    judge = D.Judge(data, selection, base_pred, object_id, object_names, sizes)
    n = judge.n
    decision = D.decide(D.Context(selection=selection, data=data, model=model, judge=judge, sizes=sizes,
                                  base_pred=base_pred, extended=extend, max_effects=max_effects,
                                  want_drift=want_drift, block_px=block_px,
                                  geometry_from_depth=bool(facts.geometry_from_depth)))
    extend.write(decision.params)
    causes, after_model, after_pred, reading = decision.names, decision.model, decision.prediction, decision.reading
    drift = decision.drift
    if drift is not None:
        evidence.append(drift.text)
    params = {e: D.fitted_values_json(e, v, selection.details.get(e)) for e, v in decision.params.items()}
    if MAP_EFFECT in params:
        params[MAP_EFFECT] = {"file": OFFSET_MAP_FILE if extend.map_path is not None else None} | params[MAP_EFFECT]
    amb = decision.ambiguities
    observability = Observability.of(unobservable, amb.observed)

    # measure: the held-out figures of the base twin and of the extended scene
    # A predicted pixel is compared where its signal is above the noise and no predicted tap
    # reaches the device's clip levels (compare applies the same rule to a twin session).
    defined = distance_defined(data, base_pred, after_pred)
    for m in (model, after_model):
        defined &= ~bad_tap_pixels(m.taps({}), data.tap_limits)
    objects = M.object_regions(object_id, object_names)
    before, maps_before, ev_before = heldout_metrics(data, base_pred, defined, objects)
    after, maps_after, ev_after = heldout_metrics(data, after_pred, defined, objects)
    ch_after = reading.channels
    channels = {c: {"before_per_value": round(selection.channels_before[c][0] / selection.channels_before[c][1], 4),
                    "after_per_value": round(ch_after[c][0] / ch_after[c][1], 4),
                    "values": ch_after[c][1],
                    "noise_margin_per_value": round(V.channel_margin(ch_after[c][1]) / ch_after[c][1], 4),
                    "worse": c in reading.worse} for c in ch_after}
    size_after = sizes.compare(base_pred, after_pred)
    regions_left, above_after = V.residual_regions(
        data, after_pred, judge.nu, object_id, object_names, maps_after["depth_residual"],
        maps_after["amplitude_residual"])
    gain = {k: {"before": before[k], "after": after.get(k, float("nan"))} for k in before}
    decision = D.with_measurement(decision, gain, data.defects.text() if data.defects is not None
                                  and data.defects.count else None)
    verdict = decision.verdict

    # report: what the result holds
    regions = {"before": ev_before.to_json()["regions"], "after": ev_after.to_json()["regions"]}
    ranked, rounds = _ranking(selection)
    maps = {f"{k}_before": v for k, v in maps_before.items()} | {f"{k}_after": v for k, v in maps_after.items()}
    maps |= _signature_maps(model, data, causes, decision.params)
    maps["above_noise_after"] = np.where(data.usable, above_after, np.nan)
    structure = residual_structure(data, after_pred, maps_after, object_id, object_names)
    if data.defects is not None:
        maps["defects"] = data.defects.mask.astype(float)
    table = _channel_tables(data, model, after_model, base_pred, after_pred)
    left = what_is_left(table["after"], [f.to_json() for f in structure], verdict.kind)
    return DiagnosisResult(cause=causes[0] if causes else None, causes=list(causes),
                           ranked=ranked, rounds=rounds, gain=gain, regions=regions,
                           extended_scene=str(ext_path) if ext_path else "", params=params,
                           evidence=[f"data: {data.channels}; noise: {data.noise}", model.setup.note, scale.text()]
                           + evidence + observability.lines,
                           chi2_per_value={"before": selection.baseline_chi2_test / n,
                                           "after_fit": selection.final_chi2_test / n,
                                           "after_extended_scene": data.chi2(after_pred, "test") / n},
                           data=data, maps=maps, evaluations={"before": ev_before, "after": ev_after},
                           seconds=time.perf_counter() - t0, verdict=verdict, channels=channels,
                           residual_regions=[r.to_json() | {"text": r.describe()} for r in regions_left],
                           objects={k: {"before": judge.objects_before.get(k), "after": v}
                                    for k, v in reading.objects.items()},
                           observability=observability, structure=[f.to_json() for f in structure],
                           forms={c.effect: c.form for c in decision.causes},
                           drift=None if drift is None else drift.to_json(),
                           effect_size={"rule": V.effect_size_rule(),
                                        "channels": {c: g.to_json() for c, g in size_after.items()},
                                        "fitted_too_small": dict(selection.too_small)},
                           identifiability={e: [t.to_json() for t in selection.unidentified.get(e, ())]
                                            for e in causes if selection.unidentified.get(e)},
                           alternatives={e: [a.to_json() for a in alts]
                                         for e, alts in amb.alternatives(causes).items()},
                           defects=data.defects.to_json() if data.defects is not None else {},
                           channel_table=table, left=left, signal_scale=scale, setup_note=model.setup.note,
                           geometry=reading.geometry,
                           ledger=decision.ledger() | {"searches": list(selection.searches)})


def at_sensor_pixels(doc: dict[str, Any], bin_px: int) -> dict[str, Any]:
    """A diagnosis's fitted parameters in the sensor's pixels: a diagnosis on ``bin_px x
    bin_px`` binned data fits lengths in pixels (unit ``px``) of the binned camera, which are
    ``bin_px`` of the sensor's (a PSF file is applied to the sensor's frames)."""
    if bin_px == 1:
        return doc
    from tofhil.sim.effects import EFFECTS

    params = {}
    for name, values in (doc.get("params") or {}).items():
        spec = EFFECTS[name].params if name in EFFECTS else {}
        params[name] = {k: v * bin_px if k in spec and spec[k].unit == "px" and isinstance(v, (int, float)) else v
                        for k, v in values.items()}
    return doc | {"params": params}


def run_diagnosis(session_path: str | Path, scene_path: str | Path, out_dir: str | Path, *, force: bool = False,
                  progress: Callable[[str], None] | None = None, **kwargs: Any) -> DiagnosisResult:
    """``tofhil diagnose``: diagnose and write diagnosis.json, extended_scene.yaml, report.html
    and the held-out pixels (:data:`HELD_OUT_MASK`).

    A run that fails leaves nothing behind: the files it wrote are removed, and the output
    directory too when this run created it.
    """
    from tofhil.eval.reports import html as H
    from tofhil.eval.diagnose.report import write_report
    from tofhil.sim.scene import load_scene

    names = ("diagnosis.json", "report.html", "extended_scene.yaml", HELD_OUT_MASK, "stray_light_psf.json",
             OFFSET_MAP_FILE)
    if Path(out_dir).is_dir() and any((Path(out_dir) / n).exists() for n in names):
        refuse_existing(out_dir, force, what="already holds a diagnosis", expected="an empty or new directory")
    out = prepare_output_dir(out_dir, names, force=force)
    scene = load_scene(scene_path)
    created = not out.exists()
    written: list[Path] = []
    try:
        out.mkdir(parents=True, exist_ok=True)
        written += [out / "extended_scene.yaml", out / OFFSET_MAP_FILE]
        res = diagnose(session_path, scene, extended_scene_path=out / "extended_scene.yaml", progress=progress,
                       **kwargs)
        written.append(out / "diagnosis.json")
        H.write_json(out / "diagnosis.json", res.to_json())
        written.append(out / HELD_OUT_MASK)
        ev = res.evaluations["before"]
        np.save(out / HELD_OUT_MASK, ev.maps.valid_both & res.data.test_pixels)
        if StrayLightEffect.name in res.causes:
            # The fitted stray light as a PSF file: `tofhil correct --method psf:psf=FILE` takes it.
            from tofhil.eval.corrections.straylight import psf_from_diagnosis

            written.append(out / "stray_light_psf.json")
            psf_from_diagnosis(at_sensor_pixels(res.to_json(), res.data.binned_by),
                               out / "diagnosis.json").save(out / "stray_light_psf.json", force=True)
        written.append(out / "report.html")
        write_report(res, out / "report.html", session_path=str(session_path), scene_path=str(scene_path),
                     camera=scene.camera)
    except BaseException:
        for p in written:
            p.unlink(missing_ok=True)
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    return res
