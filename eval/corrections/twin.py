"""The twin correction: remove what the fitted twin predicts beyond each pixel's direct return.

A fitted (extended) twin predicts, per pixel and frequency, the complex signal of the whole
model ``S_full`` and that of the pixel's own direct return ``S_direct``: the same forward
model (``tofhil.sim.twin.Twin``, one render, cached) with every effect whose light is not
the direct return switched off (``Effect.beyond_direct``: the lens's stray light, the
indirect bounces of multipath, a reflector outside the scene). Stray light and multipath
are sums of phasors, and the phasor estimator is linear in the taps, so what the twin
predicts beyond the direct path is ``S_full - S_direct``, removed from the measured signal::

    S_corr = S_meas - a * (S_full - S_direct)

With ``remove=all`` the twin's other modelled deviations go too -- everything its effects
add after the scene (waveform harmonics, per-pixel delays, tap errors, beam profile):
``S_corr = S_meas - a (S_full - S_ideal)``, the capture brought to the fitted scene seen by
an ideal camera (direct returns only), comparable with a base twin that lacks those effects.

``a`` is the device's signal scale against the twin's (DN per twin DN), the diagnosis's one
signal scale (:mod:`tofhil.eval.diagnose.signal_scale`): 1, not fitted, for a session that
records the sensor that made it when the scene's radiometric chain is that sensor's (a twin
session against its own scene); else the median measured / twin amplitude ratio over the
pixels that did not clip, fitted on other frames than those corrected when the caller gives
them (``CorrectionContext.fit_signal``: compare's held-out split), and reported. The twin is
rendered for the session's camera and acquisition (``tofhil.sim.session_setup``) with the
clip levels lifted, so the light of clipped (saturated) source pixels -- the bright card
beside the lens -- is the twin's prediction, not the clipped taps. Pixels where the removed
stray light or multipath is larger than 3 x the noise of ``S`` (the sensor model's shot and
read noise of the twin's taps, over the frames averaged) are flagged (``FLAG_STRAY_LIGHT``,
``FLAG_MULTIPATH``). Predictions are cached by content (scene, camera, acquisition).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tofhil.content_cache import LRUCache, content_digest
from tofhil.demod import phasor
from tofhil.errors import TofhilError
from tofhil.eval.corrections.context import FLAG_MULTIPATH, FLAG_STRAY_LIGHT, CorrectionContext

if TYPE_CHECKING:
    from tofhil.eval.diagnose.signal_scale import SignalScale

#: |removed| above this many standard deviations of the signal's noise is flagged.
FLAG_SIGMA = 3.0
#: The last predictions, by content (a compare with several corrections asks for one twin).
_CACHE = LRUCache(4)


@dataclass(frozen=True)
class TwinPrediction:
    """The twin's noise-free signal ``[F, H, W]`` (DN, clip levels lifted) for one session."""

    full: np.ndarray        # the whole model
    no_stray: np.ndarray    # the whole model without the lens's stray light
    direct: np.ndarray      # each pixel's own direct return only
    ideal: np.ndarray       # the direct return seen by an ideal camera (only scene-stage effects on)
    noise: np.ndarray       # std of one frame's S per component (shot + read noise of the taps)
    off: tuple[str, ...]    # the effects switched off for the direct return
    off_all: tuple[str, ...]  # ... for the ideal camera
    #: why the device's signal scale against the twin's must be fitted
    #: (:func:`tofhil.eval.diagnose.signal_scale.needs_scale`); None: the session records the
    #: sensor that made it and the scene's radiometric chain is that sensor's (scale 1)
    scale_reason: str | None
    scene: str
    #: [B + 1, H, W] share of each pixel's emitter light by bounce count (0 = direct), from the
    #: same render; None without multipath (or through glass, where it is not computed)
    bounce_share: np.ndarray | None = None

    @property
    def stray(self) -> np.ndarray:
        """The lens's stray light the twin predicts (moved in and out of each pixel)."""
        return self.full - self.no_stray

    @property
    def indirect(self) -> np.ndarray:
        """Multipath and other light of longer paths than the pixel's direct return."""
        return self.no_stray - self.direct


def _effects_off(twin: Any, kinds: tuple[str, ...] | None) -> tuple[dict[str, Any], tuple[str, ...]]:
    """The twin's effect set with the effects adding light of ``kinds`` switched off (None:
    every effect acting after the scene)."""
    from tofhil.sim.effects import EFFECTS

    eff = {k: dict(v) for k, v in twin.effects().items()}
    off = []
    for name in list(eff):
        e = EFFECTS[name]
        hit = e.stage != "scene" if kinds is None else e.beyond_direct in kinds
        if not hit or e.is_off(eff[name]):
            continue
        off.append(name)
        if e.stage == "render":  # recombines the render: kept, at its off values (direct only)
            eff[name].update(e.off_values())
        else:
            del eff[name]
    return eff, tuple(off)


def predict(scene: str | Path | Any, ctx: CorrectionContext) -> TwinPrediction:
    """The twin's prediction for the signal of ``ctx`` (its camera and acquisition), cached;
    ``scene`` a scene file or name, a loaded scene, or a :class:`TwinPrediction` itself."""
    from tofhil.eval.diagnose.signal_scale import needs_scale
    from tofhil.sim.scene import load_scene
    from tofhil.sim.session_setup import scene_for_setup, session_setup
    from tofhil.sim.twin import Twin

    if isinstance(scene, TwinPrediction):  # a prediction made elsewhere (a test's closed form)
        return scene
    sc = load_scene(scene) if isinstance(scene, (str, Path)) else scene
    key = content_digest(sc, ctx.camera, ctx.freq_hz, ctx.theta_rad, ctx.integration_time_s, ctx.sensor_config)
    hit = _CACHE.get(key)
    if hit is not None:
        return hit
    setup = session_setup(sc.sensor, camera=ctx.camera, freq_hz=ctx.freq_hz, theta_rad=ctx.theta_rad,
                          integration_time_s=ctx.integration_time_s, recorded=ctx.sensor_config, source=ctx.source)
    # Clip levels lifted: a source pixel that clips in the capture keeps its light in the twin.
    cfg = setup.sensor
    unclipped = dataclasses.replace(cfg, full_well_e=math.inf, adc_bits=62)
    from tofhil.sim.effects import EFFECTS
    from tofhil.sim.twin import render_arguments

    scene2 = scene_for_setup(sc, setup)
    full_eff = Twin(scene2, sensor=unclipped).effects()
    # One render for every effect set: the harmonics the full set needs, rendered for all.
    harm = render_arguments(scene2, full_eff, freq_hz=cfg.freq_hz)["harmonics"]
    kwargs: dict[str, Any] = {"harmonics": harm}
    if "multipath" in full_eff and not EFFECTS["multipath"].is_off(full_eff["multipath"]):
        kwargs["multipath_shares"] = True  # the light by bounce, from the same paths
    twin = Twin(scene2, sensor=unclipped, render_kwargs=kwargs)
    try:
        _, result = twin.render(full_eff)
    except TofhilError as exc:
        if exc.field != "multipath_shares":
            raise
        twin = Twin(scene2, sensor=unclipped, render_kwargs={"harmonics": harm})  # glass: no shares
        _, result = twin.render(full_eff)
    bounce_share = None
    if getattr(result, "share_power_w", None) is not None:
        from tofhil.sim.multipath import shares_from_render

        bounce_share = shares_from_render(result, [o.name for o in scene2.objects]).by_bounce
    theta = np.asarray(cfg.theta_rad, float)
    no_stray_eff, _ = _effects_off(twin, ("stray_light",))
    direct_eff, off = _effects_off(twin, ("stray_light", "multipath"))
    ideal_eff, off_all = _effects_off(twin, None)

    def signal(eff: Any) -> tuple[np.ndarray, np.ndarray]:
        taps = twin.expected_taps(eff).astype(np.float64)
        return phasor(taps, theta), taps

    full, taps = signal(full_eff)
    g = cfg.conversion_gain_dn_per_e
    # Shot noise (variance = electrons) and read noise of each tap in DN^2; the estimator
    # (2/K) sum c_k exp(i theta_k) has per-component variance (2/K^2) sum_k var_k.
    var_k = g * np.clip(taps - cfg.black_level_dn, 0.0, None) + (g * cfg.read_noise_e) ** 2
    noise = np.sqrt(2.0 / theta.size ** 2 * var_k.sum(axis=-3))
    pred = TwinPrediction(full, signal(no_stray_eff)[0], signal(direct_eff)[0], signal(ideal_eff)[0], noise, off,
                          off_all, needs_scale(getattr(sc, "sensor", None), ctx.sensor_config),
                          str(getattr(sc, "source", scene)), bounce_share)
    _CACHE.put(key, pred)
    return pred


@dataclass(frozen=True)
class _ScaleData:
    """What :func:`tofhil.eval.diagnose.signal_scale.fit_signal_scale` reads of a session's
    data: the signal it fits on and the pixels it may use."""

    s_train: np.ndarray       # [F, H, W]
    train_pixels: np.ndarray  # [H, W] bool
    source: str

    @property
    def n_freq(self) -> int:
        return int(self.s_train.shape[0])


def device_scale(s: np.ndarray, pred: TwinPrediction, ctx: CorrectionContext) -> SignalScale:
    """The device's signal against the twin's, the diagnosis's one signal scale
    (:mod:`tofhil.eval.diagnose.signal_scale`, a ``SignalScale``): not fitted (factor 1)
    when the session records the sensor that made it and the scene's radiometric chain is
    that sensor's; else fitted as the median measured / twin amplitude ratio over the pixels
    that did not clip and where the twin predicts light -- on ``ctx.fit_signal`` (other
    frames than those corrected, when the caller split them) or else on ``s`` itself."""
    from tofhil.eval.diagnose.signal_scale import SignalScale, fit_signal_scale

    if pred.scale_reason is None:
        return SignalScale()
    fit = s if ctx.fit_signal is None else np.asarray(ctx.fit_signal)
    sat = ctx.saturated if ctx.fit_signal is None else ctx.fit_saturated
    good = np.all(np.isfinite(fit), axis=0) & (np.abs(pred.full).min(axis=0) > 0)
    if sat is not None:
        good &= ~sat
    return fit_signal_scale(_ScaleData(fit, good, ctx.source), pred.full, pred.scale_reason)


def correct_twin(s: np.ndarray, ctx: CorrectionContext, scene: str | Path | Any, remove: str = "light") -> np.ndarray:
    """``S_corr = S - a (S_full - S_direct)`` (``remove="all"``: ``- a (S_full - S_ideal)``;
    module docstring); flags and notes on ``ctx``."""
    s = np.asarray(s)
    if s.ndim == 4:  # frames' deviations from a mean: the twin's light is the same in every frame
        return s
    pred = predict(scene, ctx)
    if pred.full.shape != s.shape[-3:]:
        raise TofhilError(f"the twin's signal is {pred.full.shape}, the session's {s.shape[-3:]}",
                          field="twin:scene", expected="a twin of the session's camera and frequencies")
    scale = device_scale(s, pred, ctx)
    a = scale.factor
    removed = a * (pred.full - (pred.ideal if remove == "all" else pred.direct))
    sigma = FLAG_SIGMA * abs(a) * pred.noise / math.sqrt(max(ctx.frames, 1))
    stray = np.any(np.abs(a * pred.stray) > sigma, axis=0)
    multi = np.any(np.abs(a * pred.indirect) > sigma, axis=0)
    ctx.flag(stray, FLAG_STRAY_LIGHT)
    ctx.flag(multi, FLAG_MULTIPATH)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(removed) / np.abs(s)
    ctx.info["twin"] = {"scene": pred.scene, "remove": remove,
                        "effects_removed": list(pred.off_all if remove == "all" else pred.off),
                        "effects_left": [] if remove == "all" else [e for e in pred.off_all if e not in pred.off],
                        "signal_scale": a, "scale": "fitted" if scale.fitted else "recorded units",
                        "signal_scale_fit": {**scale.to_json(), "fitted_on": ctx.fitted_on() if scale.fitted else None,
                                             "text": scale.text()},
                        "removed_fraction_median": float(np.nanmedian(rel)) if np.isfinite(rel).any() else None,
                        "flag_sigma": FLAG_SIGMA}
    if pred.bounce_share is not None and multi.any():
        # where multipath was removed: the mean share of the pixel's light by bounce count
        ctx.info["twin"]["multipath_share_by_bounce"] = [float(np.nanmean(b[multi])) for b in pred.bounce_share[1:]]
    if not pred.off:
        ctx.note(f"the twin {pred.scene} models no light beyond the direct path (no stray light, multipath or "
                 "unseen reflector): nothing removed")
    if ctx.saturated is not None and ctx.saturated.any():
        ctx.note("the light of the clipped source pixels is the twin's prediction")
    ctx.note(f"twin {scale.text()}" + (f"; fitted on {ctx.fitted_on()}" if scale.fitted else ""))
    return s - removed
