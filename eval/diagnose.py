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
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.errors import TofhilError
from tofhil.eval.heldout import HeldOutData, depth_from_signal, split_session
from tofhil.eval.selection import Selection, greedy_select
from tofhil.eval.twin_model import TwinModel, to_effect_values
from tofhil.session import open_session


def wrapped_difference(a: np.ndarray, b: np.ndarray, period: float) -> np.ndarray:
    """``a - b`` on a circle of circumference ``period`` (distances near the wrap compare right)."""
    return (a - b + period / 2) % period - period / 2


@dataclass
class DiagnosisResult:
    cause: str | None
    causes: list[str]
    ranked: list[dict[str, Any]]
    rounds: list[list[dict[str, Any]]]
    gain: dict[str, dict[str, float]]
    regions: dict[str, dict[str, dict[str, float]]]
    extended_scene: str
    params: dict[str, dict[str, float]]
    evidence: list[str]
    chi2_per_value: dict[str, float]
    data: HeldOutData = field(repr=False)
    maps: dict[str, np.ndarray] = field(repr=False, default_factory=dict)
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {"cause": self.cause, "causes": self.causes, "ranked": self.ranked, "gain": self.gain,
                "regions": self.regions, "extended_scene": self.extended_scene, "params": self.params,
                "evidence": self.evidence, "chi2_per_value": self.chi2_per_value, "rounds": self.rounds,
                "split": {"train_frames": self.data.n_train_frames, "test_frames": self.data.n_test_frames,
                          "train_pixels": int(self.data.train_pixels.sum()),
                          "test_pixels": int(self.data.test_pixels.sum()),
                          "offset_channel": self.data.offset_channel},
                "seconds": round(self.seconds, 2)}


def distance_defined(data: HeldOutData, *predictions: np.ndarray, sigmas: float = 3.0) -> np.ndarray:
    """Pixels where every prediction has a signal above the noise, so that its distance means
    something (a twin pixel in a shadow has no phase to compare)."""
    nf = data.n_freq
    floor = sigmas * np.sqrt(2.0 * data.var_test[:nf]).max(axis=0)
    ok = np.ones(data.usable.shape, bool)
    for p in predictions:
        ok &= np.abs(p[:nf]).min(axis=0) > floor
    return ok


def heldout_metrics(data: HeldOutData, prediction: np.ndarray, mask: np.ndarray, *, ndt_cell_m: float = 0.05,
                    icp_max_distance_m: float = 0.05) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Residual, point-cloud and NDT figures of a prediction against the held-out data, on the
    held-out pixels in ``mask`` (the same for every prediction compared)."""
    from tofhil.eval.matching import icp
    from tofhil.eval.ndt import ndt_score

    nf = data.n_freq
    s_meas, s_pred = data.s_test[:nf], prediction[:nf]
    shown = data.usable & mask
    mask = data.test_pixels & mask
    period = data.unambiguous_range_m
    d_meas = depth_from_signal(s_meas, data.freq_hz)
    d_pred = depth_from_signal(s_pred, data.freq_hz)
    dres = wrapped_difference(d_meas, d_pred, period)
    ares = (np.abs(s_meas) - np.abs(s_pred)).mean(axis=0)
    metrics = {"depth_rmse_m": float(np.sqrt(np.mean(dres[mask] ** 2))),
               "depth_median_abs_m": float(np.median(np.abs(dres[mask]))),
               "amplitude_rmse": float(np.sqrt(np.mean(ares[mask] ** 2))),
               "chi2_per_value": data.chi2(prediction, "test") / max(data.n_values("test"), 1)}
    cam = data.camera
    p_meas = cam.points(d_meas, valid=mask)
    p_pred = cam.points(d_pred, valid=mask)
    lik_map = np.full(cam.shape, np.nan)
    if len(p_meas) > 50 and len(p_pred) > 50:
        r = icp(p_meas, p_pred, icp_max_distance_m)
        metrics["icp_inlier_rmse_m"] = r.inlier_rmse
        metrics["icp_fitness"] = r.fitness
        nd = ndt_score(p_pred, p_meas, cell_size=ndt_cell_m)
        metrics["ndt_score_per_point"] = nd.score_per_point
        metrics["ndt_nvtl"] = nd.nvtl
        metrics["ndt_mean_likelihood_trilinear"] = nd.mean_likelihood_trilinear
        valid = cam.valid_mask(d_meas, mask)
        lik_map[valid] = nd.likelihood_trilinear
    maps = {"depth_measured": d_meas, "depth_twin": d_pred, "depth_residual": np.where(shown, dres, np.nan),
            "amplitude_residual": np.where(data.usable, ares, np.nan), "ndt_likelihood": lik_map}
    return metrics, maps


def region_metrics(maps: dict[str, np.ndarray], pixels: np.ndarray, object_id: np.ndarray,
                   names: list[str]) -> dict[str, dict[str, float]]:
    """Depth and amplitude residual RMSE per object over ``pixels``, from the residual maps
    of :func:`heldout_metrics`."""
    dres, ares = maps["depth_residual"], maps["amplitude_residual"]
    out = {}
    for i, name in enumerate(names):
        m = pixels & (object_id == i)
        if m.sum() < 5:
            continue
        out[name] = {"pixels": int(m.sum()), "depth_rmse_m": float(np.sqrt(np.mean(dres[m] ** 2))),
                     "depth_mean_m": float(np.mean(dres[m])),
                     "amplitude_rmse": float(np.sqrt(np.mean(ares[m] ** 2)))}
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
        best = rnd[0]
        runner = rnd[1] if len(rnd) > 1 else None
        verdict = "selected" if best.effect in selection.causes and selection.causes.index(best.effect) == i else "not significant"
        lines.append(f"round {i + 1}: best {best.effect} removes {100 * best.relative_gain:.1f}% of the held-out "
                     f"misfit (score gain {best.delta_score:.0f}, {best.n_params} parameters) -- {verdict}"
                     + (f"; runner-up {runner.effect} {100 * runner.relative_gain:.1f}%" if runner else ""))
    if not selection.causes:
        lines.append("no effect of the library explains a significant part of the held-out residual"
                     + (" (the twin is consistent with the measurement within its noise)" if excess < 0.05 * n else ""))
    return lines


def diagnose(session_path: str | Path, scene: Any, *, max_effects: int = 3, min_relative_gain: float = 0.02,
             candidates: list[str] | None = None, block_px: int = 8, max_frames: int | None = None,
             render_kwargs: dict[str, Any] | None = None, progress: Callable[[str], None] | None = None,
             extended_scene_path: str | Path | None = None) -> DiagnosisResult:
    """Run the diagnosis loop on a session against a base scene (a Scene object)."""
    from tofhil.sim.scene import load_scene, scene_from_yaml, scene_to_yaml

    t0 = time.perf_counter()
    with open_session(session_path) as s:
        data = split_session(s, block_px=block_px, max_frames=max_frames)
    if data.test_pixels.sum() < 20:
        raise TofhilError("too few usable pixels (signal above noise, not saturated) to diagnose",
                          file=session_path, field="raw/taps")
    model = TwinModel(scene, data, render_kwargs=render_kwargs)
    if progress:
        progress(model.setup.note)
    base_pred = model.predict({})
    if candidates is None or "pose" in candidates:
        if progress:
            progress("aligning the twin (ICP)")
        model.align_pose()
    selection = greedy_select(model, data, candidates=candidates, max_effects=max_effects,
                              min_relative_gain=min_relative_gain, progress=progress)
    params = {e: to_effect_values(e, v) for e, v in selection.params.items()}

    # The extended scene: written, read back and re-rendered, so the gain is that of the file.
    ext_path = Path(extended_scene_path) if extended_scene_path else None
    ext_scene = dataclasses.replace(model.scene, effects=model.extended_effects_block(selection.params))
    extended_text = scene_to_yaml(ext_scene)
    if ext_path is not None:
        ext_path.write_text(extended_text)
        reloaded = load_scene(ext_path)
    else:
        reloaded = scene_from_yaml(extended_text)
    after_model = TwinModel(reloaded, data, render_kwargs=render_kwargs)
    after_pred = after_model.predict({})

    defined = distance_defined(data, base_pred, after_pred)
    before, maps_before = heldout_metrics(data, base_pred, defined)
    after, maps_after = heldout_metrics(data, after_pred, defined)
    gain = {k: {"before": before[k], "after": after.get(k, float("nan"))} for k in before}
    result = model.base_render()
    names = [o.name for o in model.scene.objects]
    # the maps hold the residuals on every usable pixel where distance is defined
    held_out = data.test_pixels & defined
    regions = {"before": region_metrics(maps_before, held_out, result.object_id, names),
               "after": region_metrics(maps_after, held_out, result.object_id, names)}
    ranked = [{"effect": c.effect, "params": to_effect_values(c.effect, c.params), "score": c.score,
               "delta_score": c.delta_score, "relative_gain": c.relative_gain, "significant": c.significant,
               "chi2_test": c.chi2_test, "n_params": c.n_params} for c in selection.first_round]
    rounds = [[{"effect": c.effect, "delta_score": c.delta_score, "relative_gain": c.relative_gain,
                "significant": c.significant} for c in rnd] for rnd in selection.rounds]
    maps = {f"{k}_before": v for k, v in maps_before.items()} | {f"{k}_after": v for k, v in maps_after.items()}
    # Each selected effect's signature: how it changes the twin's depth and amplitude.
    nf = data.n_freq
    p_with = model.predict(selection.params)
    for e in selection.causes:
        p_without = model.predict({k: v for k, v in selection.params.items() if k != e})
        change = wrapped_difference(depth_from_signal(p_with[:nf], data.freq_hz),
                                    depth_from_signal(p_without[:nf], data.freq_hz), data.unambiguous_range_m)
        maps[f"signature_depth_{e}"] = np.where(distance_defined(data, p_with, p_without), change, np.nan)
        maps[f"signature_amplitude_{e}"] = (np.abs(p_with[:nf]) - np.abs(p_without[:nf])).mean(axis=0)
    n = max(data.n_values("test"), 1)
    return DiagnosisResult(cause=selection.causes[0] if selection.causes else None, causes=list(selection.causes),
                           ranked=ranked, rounds=rounds, gain=gain, regions=regions,
                           extended_scene=str(ext_path) if ext_path else "", params=params,
                           evidence=_evidence(selection, data),
                           chi2_per_value={"before": selection.baseline_chi2_test / n,
                                           "after_fit": selection.final_chi2_test / n,
                                           "after_extended_scene": data.chi2(after_pred, "test") / n},
                           data=data, maps=maps, seconds=time.perf_counter() - t0)


def run_diagnosis(session_path: str | Path, scene_path: str | Path, out_dir: str | Path, *, force: bool = False,
                  progress: Callable[[str], None] | None = None, **kwargs: Any) -> DiagnosisResult:
    """``tofhil diagnose``: diagnose and write diagnosis.json, extended_scene.yaml, report.html."""
    from tofhil.eval.diagnose_report import write_report
    from tofhil.sim.scene import load_scene

    out = Path(out_dir)
    targets = [out / "diagnosis.json", out / "report.html", out / "extended_scene.yaml"]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not force:
        raise TofhilError("already holds a diagnosis; refusing to overwrite (use --force)", file=out,
                          expected="an empty or new directory")
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(scene_path)
    res = diagnose(session_path, scene, extended_scene_path=out / "extended_scene.yaml", progress=progress, **kwargs)
    (out / "diagnosis.json").write_text(json.dumps(res.to_json(), indent=2, default=float))
    write_report(res, out / "report.html", session_path=str(session_path), scene_path=str(scene_path))
    return res
