"""What a diagnosis may claim: the noise threshold, per-channel misfits, the residual left
above noise, and the verdict.

Every "above noise" test here has the same false-alarm probability :data:`ALPHA` under the
noise model of ``heldout`` (Gaussian noise whose variance is estimated from the session's own
frame-to-frame scatter):

- **within noise**: a misfit of ``n`` whitened values is within the noise when it is below
  the ``1 - ALPHA`` quantile of a chi-square with ``n`` degrees of freedom, times
  ``nu / (nu - 2)``: the mean of a squared residual whitened by a variance estimated with
  ``nu`` degrees of freedom (an F(1, nu) variable), so that an estimated rather than known
  noise does not read as a misfit (:func:`noise_threshold`).
- **a channel got worse**: its misfit grew by more than ``z_ALPHA sqrt(2 n_c)``, the
  ``ALPHA`` one-sided margin of the chi-square of its ``n_c`` values (:func:`channel_margin`).
- **a residual region**: a connected set of pixels whose 3 x 3 mean misfit is above the
  threshold for the values of that window.
- **worth naming** (:class:`EffectSize`): a misfit far above noise can still hide a gain no
  ToF engineer would act on. The size of what a model change removes from a channel is the
  systematic part of the held-out residual it takes away, ``sqrt(before^2 - after^2)`` of the
  channel's RMSE in its own units: noise adds the same variance to both RMSEs, so the
  difference of the squares is the systematic variance removed, whereas the difference of
  the RMSEs shrinks as ``s^2 / 2 sigma`` under a noise ``sigma`` (a systematic part half the
  noise lowers the RMSE by an eighth of the noise only), capped by the rms of the correction
  itself (a ridge-shrunk correction can take more variance off a residual that has more along
  it than its own rms: what the cause changes is that rms; docs/diagnose.md has the cases that
  showed both). A cause is named only when that part
  reaches :data:`MIN_GAIN_NOISE_SHARE` of the channel's noise *and* an absolute minimum
  (:data:`MIN_DEPTH_GAIN_M` of depth; for amplitude and offset, counts with no common unit,
  :data:`MIN_LEVEL_GAIN_SHARE` of the channel's median level), and when no channel gains a
  systematic part (``sqrt(after^2 - before^2)``) beyond :data:`WORSE_SHARE_OF_MIN` of its own
  minimum that is also :data:`WORSE_SIGMAS` standard errors of ``after^2 - before^2`` above
  zero (the noise in the held-out pixels moves the squares by ``2 mean(n delta)``: a smaller
  change is a rounding, not a loss).

The verdict (:func:`verdict`) is one of ``nothing searched``, ``within noise`` (the base
twin already is), ``explained``, ``partly explained`` (with the share of the excess
removed), ``unexplained`` and ``scene does not match``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import ndimage, stats

from tofhil.eval.diagnose.heldout import HeldOutData, depth_from_signal, huber
from tofhil.eval.metrics.core import rmse
from tofhil.eval.metrics.noise import NOISE_POOL_PX, phasor_depth_sigma
from tofhil.sim.effects import OFFSET_CHANNEL

#: False-alarm probability of each "above noise" test (one in a thousand).
ALPHA = 1e-3
#: The misfit channels: the complex signal split along the predicted phasor (amplitude) and
#: across it (phase, i.e. depth), and the tap offset when the session has that channel.
CHANNELS = ("depth", "amplitude", OFFSET_CHANNEL)
#: Residual regions smaller than this many pixels are not listed (single hot pixels).
MIN_REGION_PX = 6


def distance_defined(data: HeldOutData, *predictions: np.ndarray, sigmas: float = 3.0) -> np.ndarray:
    """Pixels where every prediction has a signal above the noise, so that its distance means
    something (a twin pixel in a shadow has no phase to compare)."""
    nf = data.n_freq
    floor = sigmas * np.sqrt(2.0 * data.var_test[:nf]).max(axis=0)
    ok = np.ones(data.usable.shape, bool)
    for p in predictions:
        ok &= np.abs(p[:nf]).min(axis=0) > floor
    return ok


def unwrap_limit_m(data: HeldOutData) -> float | None:
    """The depth residual beyond which a pixel of a several-frequency session was unwrapped to
    another interval and carries no comparable depth (every figure leaves it out by this rule,
    ``tofhil.eval.metrics.core.UNWRAP_ERROR_FRACTION`` of the highest frequency's range); None
    with one frequency (the residual is wrapped instead)."""
    from tofhil.demod import ambiguity_range_m
    from tofhil.eval.metrics.core import UNWRAP_ERROR_FRACTION

    if data.n_freq < 2:
        return None
    return UNWRAP_ERROR_FRACTION * float(ambiguity_range_m(float(np.max(data.freq_hz))))


def channel_sigmas(data: HeldOutData, *, with_model_error: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel noise of the held-out mean ``[H, W]``: depth (m), from the phasor's tangential
    variance at the best frequency; amplitude as a relative error, from its radial variance
    (with the scene's own amplitude model error added when ``with_model_error``)."""
    nf = data.n_freq
    a = np.maximum(np.abs(data.s_test[:nf]), 1e-30)
    var = data.var_test[:nf].real
    sigma_depth = phasor_depth_sigma(var, a, data.freq_hz[:, None, None]).min(axis=0)
    radial = var * (data.radial_var_scale[:nf] if data.radial_var_scale is not None else 1.0)
    rel2 = radial / a ** 2
    if with_model_error and data.amplitude_model_error:
        rel2 = rel2 + data.amplitude_model_error ** 2
    return sigma_depth, np.sqrt(rel2).mean(axis=0) / np.sqrt(nf)


def noise_dof(data: HeldOutData) -> float:
    """Degrees of freedom of the noise variance estimate: every frame's deviation from the
    pixel mean (N - 1 per pixel), pooled over the ``NOISE_POOL_PX`` square (:mod:`tofhil.eval.metrics.noise`)."""
    n = data.n_train_frames + data.n_test_frames
    return float(max(n - 1, 1) * NOISE_POOL_PX ** 2)


def noise_mean(nu: float) -> float:
    """Expected whitened squared residual when the variance is estimated with ``nu`` dof."""
    return nu / (nu - 2.0) if nu > 2.0 else 1.0


def noise_threshold(n: int, nu: float, alpha: float = ALPHA) -> float:
    """Largest misfit per value of ``n`` values that is still noise (see the module doc)."""
    if n <= 0:
        return float("inf")
    return float(stats.chi2.isf(alpha, n) / n * noise_mean(nu))


def channel_margin(n_values: int, alpha: float = ALPHA) -> float:
    """How much a channel's misfit may grow before it counts as worse (the noise of it)."""
    return float(stats.norm.isf(alpha) * np.sqrt(2.0 * max(n_values, 1)))


def whitened_channels(data: HeldOutData, prediction: np.ndarray, part: str = "test") -> dict[str, np.ndarray]:
    """Whitened residual per channel, ``[values, pixels]`` on the part's pixels: the complex
    residual of each frequency rotated onto the predicted phasor (real: amplitude, imaginary:
    phase = depth). The noise is isotropic and the prediction's direction does not depend on
    it, so both components stay exactly whitened (rotating onto the measured phasor would
    not: its direction carries the noise, and the phase part would scale with |P| / |S|).

    A depth session's noise is not isotropic (``radial_var_scale``: the amplitude is known
    to the scene only to its own misfit); its channels are the polar residuals the fit
    minimises (``HeldOutData.whitened``), so the verdict, the regions and the fit judge by
    the same noise."""
    s, var, mask = data.part(part)
    nf = data.n_freq
    if data.radial_var_scale is not None and data.phase_ref is not None:
        r = data.whitened(prediction, part)[:nf]
        return {"depth": r.imag, "amplitude": r.real}
    meas, pred = s[:nf, mask], prediction[:nf, mask]
    a = np.abs(pred)
    u = np.where(a > 0, pred / np.where(a > 0, a, 1.0), meas / np.maximum(np.abs(meas), 1e-300))
    r = (meas - pred) * np.conj(u) / np.sqrt(var[:nf, mask])
    out = {"depth": r.imag, "amplitude": r.real}
    if data.offset_channel:
        out[OFFSET_CHANNEL] = ((s[nf, mask] - prediction[nf, mask]).real / np.sqrt(var[nf, mask].real))[None]
    return out


def channel_chi2(data: HeldOutData, prediction: np.ndarray, part: str = "test") -> dict[str, tuple[float, int]]:
    """Robust misfit (sum of Huber's rho) and number of values of each channel."""
    return {k: (float(huber(v).sum()), int(v.size)) for k, v in whitened_channels(data, prediction, part).items()}


def worse_channels(before: Mapping[str, tuple[float, int]], after: Mapping[str, tuple[float, int]],
                   alpha: float = ALPHA) -> list[str]:
    """Channels whose misfit grew by more than their noise (:func:`channel_margin`)."""
    return [c for c in CHANNELS if c in before and c in after
            and after[c][0] - before[c][0] > channel_margin(before[c][1], alpha)]


def pixel_misfit(data: HeldOutData, prediction: np.ndarray) -> tuple[np.ndarray, int]:
    """Per-pixel misfit (sum over channels) on every usable pixel of the held-out frames
    (NaN elsewhere) and the number of values per pixel."""
    ch = whitened_channels(data, prediction, "test_frames")
    per_px = sum(huber(v).sum(axis=0) for v in ch.values())
    n_per_px = sum(v.shape[0] for v in ch.values())
    img = np.full(data.usable.shape, np.nan)
    img[data.part("test_frames")[2]] = per_px
    return img, int(n_per_px)


@dataclass
class ResidualRegion:
    """A connected region of pixels left above noise, and which objects it lies on."""

    pixels: int
    bbox: tuple[int, int, int, int]  # X0, Y0, X1, Y1 half-open
    misfit_per_value: float
    objects: dict[str, float]  # object name -> share of the region's pixels
    depth_residual_mm: float  # median measured - twin
    amplitude_residual: float  # median measured - twin amplitude (DN)
    #: The depth residual's spread about its median (rms, mm), the median noise of one pixel
    #: (mm), and the median amplitude ratio measured / twin with its noise (relative).
    depth_spread_mm: float = float("nan")
    depth_sigma_mm: float = float("nan")
    amplitude_ratio: float = float("nan")
    amplitude_sigma: float = float("nan")

    @property
    def kind(self) -> str:
        """What the region looks like to a ToF engineer (each part beyond
        :data:`REGION_SIGMAS` of one pixel's noise and beyond the smallest gain worth naming:
        :data:`MIN_DEPTH_GAIN_M`, :data:`MIN_LEVEL_GAIN_SHARE`): the capture's surface nearer or farther
        than the twin's as a whole (an object the twin lacks or misplaces), a shape the twin's
        surface does not follow, or the depth right and the amplitude off (a wrong material)."""
        # (a saturated, bright pixel's noise is ~0: the absolute floor keeps 0.2 mm from reading as an object)
        lim = max(REGION_SIGMAS * self.depth_sigma_mm, MIN_DEPTH_GAIN_M * 1e3)
        parts = []
        if abs(self.depth_residual_mm) > lim:
            parts.append("missing object (a surface nearer than the twin's)" if self.depth_residual_mm < 0
                         else "misplaced object (the twin's surface nearer than the capture's)")
        if self.depth_spread_mm > lim:
            parts.append("wrong shape (the twin's surface does not follow the capture's)")
        ratio_off = abs(np.log(self.amplitude_ratio)) > max(REGION_SIGMAS * self.amplitude_sigma,
                                                             MIN_LEVEL_GAIN_SHARE) \
            if self.amplitude_ratio > 0 and np.isfinite(self.amplitude_sigma) else False
        if ratio_off and not parts:
            parts.append("wrong material (the depth right, the amplitude off)")
        elif ratio_off:
            parts.append("amplitude off too")
        return "; ".join(parts) or "no consistent offset, shape or material (an excess of scatter)"

    def to_json(self) -> dict[str, Any]:
        r = lambda x, n: None if not np.isfinite(x) else round(float(x), n)  # noqa: E731
        return {"pixels": self.pixels, "bbox_x0y0x1y1": list(self.bbox),
                "misfit_per_value": round(self.misfit_per_value, 4), "objects": self.objects,
                "depth_residual_mm": round(self.depth_residual_mm, 3),
                "amplitude_residual": round(self.amplitude_residual, 4),
                "depth_spread_mm": r(self.depth_spread_mm, 3), "depth_sigma_mm": r(self.depth_sigma_mm, 3),
                "amplitude_ratio": r(self.amplitude_ratio, 4), "amplitude_sigma": r(self.amplitude_sigma, 4),
                "kind": self.kind}

    def describe(self) -> str:
        on = ", ".join(f"{k} {100 * v:.0f} %" for k, v in self.objects.items()) or "no object"
        x0, y0, x1, y1 = self.bbox
        return (f"{self.pixels} px at x {x0}-{x1 - 1}, y {y0}-{y1 - 1} (on {on}): {self.kind}: depth residual "
                f"{self.depth_residual_mm:+.1f} mm (spread {self.depth_spread_mm:.1f} mm, pixel noise "
                f"{self.depth_sigma_mm:.1f} mm), amplitude x{self.amplitude_ratio:.2f} of the twin's "
                f"({self.amplitude_residual:+.3g} DN); misfit {self.misfit_per_value:.2f} per value")


#: A residual region's offset, shape or amplitude counts when beyond this many pixel noises.
REGION_SIGMAS = 3.0


def residual_regions(data: HeldOutData, prediction: np.ndarray, nu: float, object_id: np.ndarray | None = None,
                     object_names: Mapping[int, str] | None = None, depth_residual_m: np.ndarray | None = None,
                     amplitude_residual: np.ndarray | None = None, *, max_regions: int = 10
                     ) -> tuple[list[ResidualRegion], np.ndarray]:
    """Connected regions (8-connectivity) of pixels whose 3 x 3 mean misfit per value is above
    the noise threshold of the window's values; the largest excess first. Also returns the
    above-noise mask."""
    img, n_px = pixel_misfit(data, prediction)
    sigma_depth, sigma_amp = channel_sigmas(data)
    nf = data.n_freq
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio = np.log(np.abs(data.s_test[:nf]).mean(axis=0) / np.abs(prediction[:nf]).mean(axis=0))
    log_ratio = np.where(np.isfinite(log_ratio), log_ratio, np.nan)
    ok = np.isfinite(img)
    num = ndimage.uniform_filter(np.where(ok, img, 0.0), 3, mode="constant")
    den = ndimage.uniform_filter(ok.astype(float), 3, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = num / den / max(n_px, 1)
    cnt = np.rint(den * 9).astype(int)
    thr = np.full(img.shape, np.inf)
    for k in np.unique(cnt[ok]):
        thr[cnt == k] = noise_threshold(int(k) * n_px, nu)
    above = ok & (mean > thr)
    labels, n = ndimage.label(above, structure=np.ones((3, 3), bool))
    regions = []
    names = dict(object_names or {})
    for i, sl in enumerate(ndimage.find_objects(labels), start=1):
        m = labels[sl] == i
        px = int(m.sum())
        if px < MIN_REGION_PX:
            continue
        full = np.zeros_like(above)
        full[sl] = m
        objs: dict[str, float] = {}
        if object_id is not None:
            ids, counts = np.unique(np.asarray(object_id)[full], return_counts=True)
            for oid, c in sorted(zip(ids.tolist(), counts.tolist()), key=lambda t: -t[1]):
                objs[names.get(oid, "background" if oid < 0 else f"object {oid}")] = round(c / px, 3)

        def med(a: np.ndarray | None, scale: float = 1.0) -> float:
            if a is None:
                return float("nan")
            v = a[full]
            v = v[np.isfinite(v)]
            return float(np.median(v) * scale) if v.size else float("nan")

        d_med = med(depth_residual_m, 1e3)
        spread = float("nan")
        if depth_residual_m is not None:
            dv = depth_residual_m[full] * 1e3
            dv = dv[np.isfinite(dv)]
            spread = float(np.sqrt(np.mean((dv - d_med) ** 2))) if dv.size else float("nan")
        regions.append(ResidualRegion(px, (sl[1].start, sl[0].start, sl[1].stop, sl[0].stop),
                                      float(np.nanmean(img[full]) / n_px), objs,
                                      d_med, med(amplitude_residual), spread, med(sigma_depth, 1e3),
                                      float(np.exp(med(log_ratio))), med(sigma_amp)))
    regions.sort(key=lambda r: -(r.misfit_per_value - 1.0) * r.pixels)
    return regions[:max_regions], above


def object_misfits(data: HeldOutData, prediction: np.ndarray, nu: float, object_id: np.ndarray,
                   object_names: Mapping[int, str], min_pixels: int = 20) -> dict[str, dict[str, Any]]:
    """Each object's held-out misfit per value, its noise threshold and whether it is above."""
    img, n_px = pixel_misfit(data, prediction)
    out = {}
    for oid, name in object_names.items():
        m = data.test_pixels & (np.asarray(object_id) == oid)
        k = int(m.sum())
        if k < min_pixels:
            continue
        per_value = float(img[m].sum() / (k * n_px))
        thr = noise_threshold(k * n_px, nu)
        out[name] = {"pixels": k, "misfit_per_value": round(per_value, 4), "noise_threshold": round(thr, 4),
                     "above_noise": bool(per_value > thr)}
    return out


class Kind(str, Enum):
    """The kinds of verdict (their values are the words the reports and diagnosis.json use)."""

    NOTHING_SEARCHED = "nothing searched"
    WITHIN_NOISE = "within noise"
    EXPLAINED = "explained"
    PARTLY_EXPLAINED = "partly explained"
    UNEXPLAINED = "unexplained"
    SCENE_MISMATCH = "scene does not match"

    def __str__(self) -> str:
        return self.value

    @property
    def leaves_a_residual(self) -> bool:
        """A verdict after which something above noise is left to describe."""
        return self in (Kind.PARTLY_EXPLAINED, Kind.UNEXPLAINED, Kind.SCENE_MISMATCH)


@dataclass
class Verdict:
    """What the diagnosis claims, and the figures it rests on."""

    kind: Kind
    text: str
    threshold_per_value: float
    excess_removed: float | None  # share of the base twin's excess over noise removed (held-out)
    worse_channels: list[str] = field(default_factory=list)
    disagreeing_objects: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind.value, "text": self.text, "threshold_per_value": round(self.threshold_per_value, 4),
                "excess_removed": None if self.excess_removed is None else round(self.excess_removed, 4),
                "worse_channels": self.worse_channels, "disagreeing_objects": self.disagreeing_objects,
                "notes": self.notes}


def excess_removed(before: float, after: float, noise: float) -> float | None:
    """Share of the misfit in excess of the noise level removed (None: no excess to remove)."""
    excess = before - noise
    if excess <= 0:
        return None
    return float((before - after) / excess)


def verdict(*, searched: bool, causes: Sequence[str], n_values: int, nu: float, before_per_value: float,
            after_per_value: float, worse: Sequence[str], objects_before: Mapping[str, Mapping[str, Any]],
            objects_after: Mapping[str, Mapping[str, Any]], pinned: Mapping[str, Sequence[str]],
            rejected_for_channels: Sequence[str], geometry: Any = None) -> Verdict:
    """The verdict from the held-out figures (see the module doc for each test).

    The scene does not match the capture only when the geometry is wrong: the residual left by
    the best model is organised by the scene's objects and edges (``geometry``,
    :func:`tofhil.eval.diagnose.geometry.geometry_evidence`) and what the search found cannot
    be its cause: nothing named, an effect pinned at a bound of the range searched while the fit
    still misses, or less than half of the excess removed. A global or per-channel factor, a
    smooth field or a channel that rose is never a scene mismatch (``rejected_for_channels``
    is accounted in the notes, not a veto).
    """
    thr = noise_threshold(n_values, nu)
    noise = noise_mean(nu)
    removed = excess_removed(before_per_value, after_per_value, noise)
    state = f"threshold {thr:.3f} per value: the {100 * (1 - ALPHA):.1f} % quantile of chi2 with {n_values} values"
    if not searched:
        return Verdict(Kind.NOTHING_SEARCHED, "nothing searched (--max-effects 0): no effect was fitted, so this "
                       "says nothing about what is missing", thr, None)
    if before_per_value <= thr and not causes:
        return Verdict(Kind.WITHIN_NOISE, f"the base twin matches the capture within its noise (misfit "
                       f"{before_per_value:.3f} per value, {state})", thr, None)
    disagree_before = sorted(k for k, v in objects_before.items() if v["above_noise"])
    disagree = sorted(k for k, v in objects_after.items() if v["above_noise"])
    # A parameter at the bound of its range is a sign of a wrong scene only while the fit still
    # misses: a flexible form (a spline knot) may sit at its bound and explain the data to noise.
    pinned_any = any(pinned.get(c) for c in causes) and after_per_value > thr
    little = removed is None or removed < 0.5
    geometric = bool(getattr(geometry, "organised", False))
    if geometric and (not causes or pinned_any or little):
        why = [geometry.text()]
        if pinned_any:
            why.append("fitted " + ", ".join(f"{c} ({', '.join(pinned[c])})" for c in causes if pinned.get(c))
                       + " pinned at the bounds of the range searched")
        if little:
            why.append(f"{0 if removed is None else max(removed, 0) * 100:.0f} % of the excess removed")
        return Verdict(Kind.SCENE_MISMATCH,
                       f"the scene does not match the capture: the residual (misfit {before_per_value:.2f} per value, "
                       f"{state}) is organised by the scene's objects and edges, and no effect of the library "
                       f"removes it; objects that disagree: {', '.join(disagree_before) or 'none as a whole'} (see "
                       "the residual regions); no effect is named", thr, removed, list(worse), disagree_before, why)
    if not causes:
        return Verdict(Kind.UNEXPLAINED, f"no effect of the library explains a significant part of the held-out "
                       f"residual (misfit {before_per_value:.2f} per value, {state}); see the residual regions",
                       thr, None, list(worse), disagree_before)
    if after_per_value <= thr and not worse:
        at_bound = [f"{c}: {', '.join(pinned[c])} at the bound of the range searched" for c in causes if pinned.get(c)]
        return Verdict(Kind.EXPLAINED, f"explained by {' + '.join(causes)}: held-out misfit after the fit "
                       f"{after_per_value:.3f} per value is within the noise ({state})", thr, removed, [], [],
                       at_bound)
    pct = 0.0 if removed is None else 100.0 * removed
    text = (f"partly explained by {' + '.join(causes)}: {pct:.0f} % of the excess removed (misfit "
            f"{before_per_value:.2f} -> {after_per_value:.2f} per value, {state}); the rest is in the residual regions")
    if worse:
        text += "; worse after the fit: " + ", ".join(worse)
    return Verdict(Kind.PARTLY_EXPLAINED, text, thr, removed, list(worse), disagree)


# ---------------------------------------------------------------------------- effect size

#: A named cause removes a systematic part of some channel's held-out residual of at least
#: this share of its noise (the median pixel's, over the held-out pixels) ...
MIN_GAIN_NOISE_SHARE = 0.1
#: ... and of at least this much depth (a sub-half-millimetre change is nothing a ToF
#: engineer would correct for) ...
MIN_DEPTH_GAIN_M = 0.5e-3
#: ... or, for amplitude and offset (device counts: no common unit), this share of the
#: channel's median measured level.
MIN_LEVEL_GAIN_SHARE = 0.01
#: A channel is worse when the systematic part a change adds to it exceeds this share of its
#: minimum gain ...
WORSE_SHARE_OF_MIN = 0.5
#: ... and the growth of its mean squared residual is this many of its standard errors (the
#: held-out noise against the change of the prediction) above zero.
WORSE_SIGMAS = 3.0


def effect_size_rule() -> str:
    """The rule, as the report and diagnosis.json state it."""
    return (f"a cause is named only when the systematic part it removes from some channel's held-out residual, "
            f"sqrt(RMSE_before^2 - RMSE_after^2) and at most the rms of the correction, is at least {MIN_GAIN_NOISE_SHARE:g} x that channel's noise (the "
            f"median pixel's with every frame averaged: what the capture can reach) and at least {MIN_DEPTH_GAIN_M * 1e3:g} mm of depth, or "
            f"{100 * MIN_LEVEL_GAIN_SHARE:g} % of the median measured level of amplitude or offset; and when no "
            f"channel gains a systematic part, sqrt(RMSE_after^2 - RMSE_before^2), above {WORSE_SHARE_OF_MIN:g} x "
            f"its own minimum and {WORSE_SIGMAS:g} standard errors")


@dataclass(frozen=True)
class ChannelGain:
    """A channel's held-out RMSE before and after, in its own units, and the gain it needs."""

    channel: str
    before: float
    after: float
    noise: float  # the median held-out pixel's noise
    minimum: float
    pixels: int
    #: standard error of ``before^2 - after^2`` from the held-out noise (0: exact)
    square_change_se: float = 0.0
    #: rms of the change of the prediction itself on the same pixels (nan: not known)
    correction: float = float("nan")
    #: The same figures where the change acts: on the pixels it moves by at least ``minimum``
    #: (a stray light that moves a dark square by centimetres and the wall by a fraction of a
    #: millimetre is judged on the square, not diluted by the wall): pixel count, RMSE
    #: before and after, rms of the change.
    #: (None: not computed, the change is judged over all pixels.)
    acting_pixels: int | None = None
    acting_before: float = float("nan")
    acting_after: float = float("nan")
    acting_correction: float = float("nan")

    @property
    def systematic(self) -> float:
        """The systematic part removed (negative: added): sqrt(|before^2 - after^2|) signed,
        and no more than the correction itself. A ridge-shrunk correction of 0.2 mm can take
        0.7 mm of variance off a residual with 1.4 mm along it (2 <r, d> - |d|^2): the
        residual's part is larger, what the cause changes is 0.2 mm."""
        d = self.before ** 2 - self.after ** 2
        size = float(np.sign(d) * np.sqrt(abs(d)))
        return min(size, self.correction) if size > 0 and np.isfinite(self.correction) else size

    @property
    def gain(self) -> float:
        return self.systematic

    @property
    def systematic_where_acting(self) -> float:
        """The systematic part removed on the pixels the change moves by at least the minimum
        (as :attr:`systematic`, there)."""
        if self.acting_pixels is None:
            return self.systematic
        if not self.acting_pixels:
            return 0.0
        d = self.acting_before ** 2 - self.acting_after ** 2
        size = float(np.sign(d) * np.sqrt(abs(d)))
        return min(size, self.acting_correction) if size > 0 else size

    @property
    def enough(self) -> bool:
        """Worth naming in this channel: where the change acts, it removes at least the minimum
        (a change that fits noise moves pixels too, and removes nothing there on held-out
        values: its part is negative). Whether the gain is beyond noise is the likelihood's
        test, not this one's: a second test on the unweighted RMSE, weaker where the noise is
        largest, vetoed a tap offset that the held-out score had found."""
        if self.acting_pixels is None:
            return bool(self.systematic >= self.minimum)
        return bool(self.systematic_where_acting >= self.minimum)

    @property
    def worse(self) -> bool:
        grown = self.after ** 2 - self.before ** 2
        return bool(grown > (WORSE_SHARE_OF_MIN * self.minimum) ** 2 and grown > WORSE_SIGMAS * self.square_change_se)

    @property
    def _unit(self) -> tuple[float, str]:
        return (1e3, " mm") if self.channel == "depth" else (1.0, " DN")

    def to_json(self) -> dict[str, Any]:
        k, unit = self._unit
        return {"unit": unit.strip(), "rmse_before": round(self.before * k, 4), "rmse_after": round(self.after * k, 4),
                "systematic_removed": round(self.systematic * k, 4), "correction_rms": round(self.correction * k, 4),
                "noise_median_pixel": round(self.noise * k, 4), "minimum_gain": round(self.minimum * k, 4),
                "pixels": self.pixels, "acting_pixels": self.acting_pixels,
                "systematic_removed_where_acting": round(self.systematic_where_acting * k, 4),
                "enough": self.enough, "worse": self.worse}

    def describe(self) -> str:
        k, unit = self._unit
        where = ("" if self.acting_pixels in (None, 0, self.pixels) else
                 f"; {self.systematic_where_acting * k:.3g}{unit} on the {self.acting_pixels} pixels it moves by "
                 "at least that")
        return (f"{self.channel} RMSE {self.before * k:.4g} -> {self.after * k:.4g}{unit} (systematic part removed "
                f"{self.systematic * k:.3g}{unit} by a correction of {self.correction * k:.3g}{unit} rms, needs "
                f"{self.minimum * k:.3g}{unit}{where}" + (", worse" if self.worse else "") + ")")


class EffectSize:
    """Held-out RMSE per channel in its own units (depth in m: :data:`tofhil.eval.metrics.core.DEPTH_RMSE`
    on the held-out pixels where both predictions have a distance; amplitude and the tap
    offset in counts) and the minimum gain that makes a cause worth naming (module doc)."""

    def __init__(self, data: HeldOutData) -> None:
        from tofhil.eval.metrics.core import wrap_period

        self.data = data
        nf = data.n_freq
        s = data.s_test
        self._wrap = wrap_period(data.freq_hz)
        self._unwrap_limit = unwrap_limit_m(data)
        self._meas = {"depth": depth_from_signal(s[:nf], data.freq_hz), "amplitude": np.abs(s[:nf]).mean(axis=0)}
        sd, sa = channel_sigmas(data, with_model_error=False)
        m = data.test_pixels
        # the typical pixel's noise: an rms would be ruled by the few darkest pixels (depth
        # noise ~ 1/amplitude: a board's black squares made it 142 mm on a 4 mm capture)
        med = lambda x: float(np.median(x)) if x.size else float("nan")  # noqa: E731
        self._sigma = {"depth": sd, "amplitude": sa * self._meas["amplitude"]}
        self.noise = {c: med(v[m]) for c, v in self._sigma.items()}
        level = {"amplitude": float(np.median(self._meas["amplitude"][m])) if m.any() else 0.0}
        if data.offset_channel:
            self._meas[OFFSET_CHANNEL] = s[nf].real
            self._sigma[OFFSET_CHANNEL] = np.sqrt(data.var_test[nf].real)
            self.noise[OFFSET_CHANNEL] = med(self._sigma[OFFSET_CHANNEL][m])
            level[OFFSET_CHANNEL] = float(np.median(np.abs(s[nf].real[m]))) if m.any() else 0.0
        # Practical significance is judged against what the capture can reach: the noise of a
        # pixel with every frame averaged (the held-out mean has only the held-out frames).
        frames = max(data.n_train_frames + data.n_test_frames, 1) if data.frames_held_out else 1
        reach = float(np.sqrt(max(data.n_test_frames, 1) / frames))
        self.reach = {c: v * reach for c, v in self.noise.items()}
        self.minimum = {"depth": max(MIN_GAIN_NOISE_SHARE * self.reach["depth"], MIN_DEPTH_GAIN_M)}
        for c, lv in level.items():
            self.minimum[c] = max(MIN_GAIN_NOISE_SHARE * self.reach[c], MIN_LEVEL_GAIN_SHARE * lv)

    def _channel(self, c: str, prediction: np.ndarray) -> np.ndarray:
        nf = self.data.n_freq
        if c == "depth":
            d = depth_from_signal(prediction[:nf], self.data.freq_hz)
            r = self._meas[c] - d
            return r if self._wrap is None else (r + self._wrap / 2) % self._wrap - self._wrap / 2
        if c == "amplitude":
            return self._meas[c] - np.abs(prediction[:nf]).mean(axis=0)
        return self._meas[c] - prediction[nf].real

    def compare(self, before: np.ndarray, after: np.ndarray) -> dict[str, ChannelGain]:
        """Each channel's held-out RMSE with ``before`` and with ``after``, on the same pixels."""
        m = self.data.test_pixels & distance_defined(self.data, before, after)
        out = {}
        for c in self._meas:
            rb, ra, sig = self._channel(c, before)[m], self._channel(c, after)[m], self._sigma[c][m]
            ok = np.isfinite(rb) & np.isfinite(ra) & np.isfinite(sig)
            if c == "depth" and self._unwrap_limit is not None:
                # pixels unwrapped to another interval on either side carry no comparable depth
                # (the figures of compare and diagnose leave them out by the same rule)
                with np.errstate(invalid="ignore"):
                    ok &= (np.abs(rb) <= self._unwrap_limit) & (np.abs(ra) <= self._unwrap_limit)
            rb, ra, sig = rb[ok], ra[ok], sig[ok]
            n = max(rb.size, 1)
            # before^2 - after^2 = mean(2 r_b delta - delta^2): the noise in r_b moves it by
            # 2 mean(n delta), of standard error 2 sqrt(sum(sigma^2 delta^2)) / n
            se = 2.0 * float(np.sqrt(np.sum((sig * (rb - ra)) ** 2))) / n
            # where the change acts: chosen by the change alone, never by the residual
            acting = np.abs(rb - ra) >= self.minimum[c]
            na = int(acting.sum())
            out[c] = ChannelGain(c, rmse(rb), rmse(ra), self.noise[c], self.minimum[c], int(ok.sum()), se,
                                 rmse(rb - ra), na, rmse(rb[acting]) if na else float("nan"),
                                 rmse(ra[acting]) if na else float("nan"),
                                 rmse((rb - ra)[acting]) if na else float("nan"))
        return out

    @staticmethod
    def worth_naming(gains: Mapping[str, ChannelGain]) -> bool:
        """Some channel gains its minimum (a channel made worse is accounted by the caller,
        never a veto: it means the explanation is partial)."""
        return any(g.enough for g in gains.values())

    def names(self, reference: np.ndarray, after: np.ndarray) -> tuple[dict[str, ChannelGain], bool]:
        """The gains of ``after`` over ``reference`` (the model it extends), and whether they
        are worth naming."""
        gains = self.compare(reference, after)
        return gains, self.worth_naming(gains)

    @staticmethod
    def describe(gains: Mapping[str, ChannelGain]) -> str:
        return ", ".join(g.describe() for g in gains.values())

    @staticmethod
    def why_not(gains: Mapping[str, ChannelGain]) -> str:
        """Why gains that are not worth naming are not: too small (and which channels rose)."""
        worse = [c for c, g in gains.items() if g.worse]
        return "too small" + (f" (and makes {' and '.join(worse)} worse)" if worse else "")
