"""Direct time of flight: a pulsed emitter and a SPAD histogram sensor on the renderer's transient.

The renderer gives, per pixel, the emitter's power arriving per optical-path-length bin
(``render(..., transient_bins=edges)``, watts for the scene emitter's ``power_w``). The
direct-ToF chain on top of it (the scene's ``direct_tof:`` block, :class:`DirectToFConfig`):

1. **Pulse**: a pulse of energy ``E_p`` (J) every ``1 / repetition_hz``; the share of the
   emitted energy reaching a pixel through path length ``L`` is ``transient(L) / power_w``
   (the render is linear in the emitter's power). The pulse shape (Gaussian of a given FWHM,
   or a table) and the sensor's timing jitter (Gaussian) spread each arrival time ``L / c``
   over the histogram bins; a Gaussian is integrated over each bin exactly (error function).
2. **Photons per cycle**: detected photons per bin and laser cycle
   ``lam_i = PDE * E_p / (h c / lambda) * share_i + (PDE * ambient + dark + extra) * bin``.
   Photon arrivals are Poisson in every bin, independent between bins and cycles.
3. **Dead time and pile-up**: a SPAD records at most one photon per dead time ``d`` (in bins,
   non-paralysable, re-armed at each cycle start). It is armed in bin ``i`` exactly when it
   recorded nothing in bins ``i-d .. i-1``, which does not depend on the photons in bin ``i``;
   so, over ``N`` cycles, ``n_i | n_<i ~ Binomial(N - sum_{j=i-d}^{i-1} n_j, 1 - exp(-lam_i))``
   exactly (:func:`sample_histogram`), with the expectation
   ``P_i = (1 - sum_{j=i-d}^{i-1} P_j) (1 - exp(-lam_i))`` (:func:`record_probabilities`).
   With ``d`` at least the histogram's length this is the classic first-photon (Coates 1968)
   model ``P_i = exp(-sum_{j<i} lam_j) (1 - exp(-lam_i))``; :func:`coates_correction` is its
   inverse (and the maximum-likelihood estimate of ``lam``).
4. **Depth**: peaks of the Coates-corrected histogram minus its background, matched-filtered
   with the pulse's own bin response, sub-bin position by Gaussian three-point interpolation
   of the filter output; a peak counts when its filter output exceeds ``peak_threshold``
   standard deviations of the filter's noise. The strongest peak gives the depth
   (``c t / 2``), the others are multipath returns (:func:`find_peaks`).

Limits: the lens prescription's vignetting and ghosts and the correlation effects (the
``effects:`` block) are not applied to histograms; after-pulsing and crosstalk between SPADs
are not modelled; dead time never carries over from one laser cycle into the next (the
repetition period must hold the histogram and the dead time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil import C_M_PER_S
from tofhil.schema import Schema, to_plain
from tofhil.sim.sensor import H_PLANCK

#: Keys of the ``direct_tof:`` block.
DIRECT_TOF_KEYS = ("pulse", "pulse_energy_j", "repetition_hz", "cycles_per_frame", "bin_width_s", "bins", "t0_s",
                   "jitter_s", "dark_count_rate_hz", "ambient_rate_hz", "pde", "dead_time_s", "peak_threshold",
                   "max_peaks", "oversample")
_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


@dataclass(frozen=True)
class PulseShape:
    """The emitted pulse's power versus time: a Gaussian of full width ``fwhm_s`` centred on
    t = 0, or a table (``times_s``, ``values``, linear between, 0 outside; its time origin is
    the emission time the histogram's t = 0 refers to)."""

    kind: str = "gaussian"
    fwhm_s: float = 1.0e-9
    times_s: tuple[float, ...] = ()
    values: tuple[float, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        if self.kind == "gaussian":
            return {"shape": "gaussian", "fwhm_s": self.fwhm_s}
        return {"shape": "table", "times_s": list(self.times_s), "values": list(self.values)}


@dataclass(frozen=True)
class DirectToFConfig:
    """The interpreted ``direct_tof:`` block of a scene (docs/scene-format.md)."""

    pulse: PulseShape = field(default_factory=PulseShape)
    #: Energy per pulse (J); None: the scene emitter's average power / repetition rate.
    pulse_energy_j: float | None = None
    repetition_hz: float = 1.0e6
    cycles_per_frame: int = 10_000
    bin_width_s: float = 100.0e-12
    bins: int = 128
    #: Time of the first bin's leading edge after the pulse's emission (s).
    t0_s: float = 0.0
    #: Standard deviation of the SPAD + TDC timing jitter (s).
    jitter_s: float = 50.0e-12
    dark_count_rate_hz: float = 100.0
    #: Extra detected background rate per pixel (counts/s) on top of the scene's ambient light.
    ambient_rate_hz: float = 0.0
    #: Photon detection efficiency (probability a photon on the pixel gives a count).
    pde: float = 0.25
    dead_time_s: float = 20.0e-9
    #: A peak counts when its matched-filter output exceeds this many noise standard deviations.
    peak_threshold: float = 5.0
    max_peaks: int = 3
    #: Render sub-bins per histogram bin (the pulse is applied to the finer transient).
    oversample: int = 4

    @property
    def edges_s(self) -> np.ndarray:
        """The histogram's bin edges in seconds after emission ``[bins + 1]``."""
        return self.t0_s + self.bin_width_s * np.arange(self.bins + 1)

    @property
    def dead_bins(self) -> int:
        """Dead time in whole bins (at least 1: one count per bin and cycle at most)."""
        return max(1, math.ceil(self.dead_time_s / self.bin_width_s - 1e-9))

    def energy_j(self, emitter_power_w: float) -> float:
        return self.pulse_energy_j if self.pulse_energy_j is not None else emitter_power_w / self.repetition_hz

    def to_dict(self) -> dict[str, Any]:
        d = {"pulse": self.pulse.to_dict()}
        for k in DIRECT_TOF_KEYS[1:]:
            d[k] = getattr(self, k)
        if d["pulse_energy_j"] is None:
            del d["pulse_energy_j"]
        return to_plain(d)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, *, source: str | Path = "<scene>") -> "DirectToFConfig":
        """Validate a ``direct_tof:`` mapping; errors name ``direct_tof.<field>``."""
        s = Schema(source)
        d = s.mapping(d, "direct_tof", allowed=DIRECT_TOF_KEYS)
        kw: dict[str, Any] = {}
        p = s.mapping(d.get("pulse"), "direct_tof.pulse", allowed=("shape", "fwhm_s", "times_s", "values"))
        shape = s.enum(p.get("shape", "gaussian"), "direct_tof.pulse.shape", ("gaussian", "table"))
        if shape == "gaussian":
            kw["pulse"] = PulseShape("gaussian", fwhm_s=s.number(p.get("fwhm_s", 1.0e-9), "direct_tof.pulse.fwhm_s",
                                                                  lo=0.0, lo_open=True, hi=1e-6))
        else:
            t = s.numbers(s.require(p, "times_s", "direct_tof.pulse", "a list of increasing times (s)"),
                          "direct_tof.pulse.times_s", min_len=2)
            v = s.numbers(s.require(p, "values", "direct_tof.pulse", "a list of powers >= 0"),
                          "direct_tof.pulse.values", n=len(t), lo=0.0)
            if np.any(np.diff(t) <= 0):
                raise s.bad(t, "direct_tof.pulse.times_s", "strictly increasing times (s)")
            if sum(v) <= 0:
                raise s.bad(v, "direct_tof.pulse.values", "powers >= 0, not all 0")
            kw["pulse"] = PulseShape("table", times_s=tuple(t), values=tuple(v))
        pos = {"lo": 0.0, "lo_open": True}
        if "pulse_energy_j" in d:
            kw["pulse_energy_j"] = s.number(d["pulse_energy_j"], "direct_tof.pulse_energy_j", **pos)
        for k, rng in (("repetition_hz", pos), ("bin_width_s", pos), ("t0_s", {"lo": 0.0}),
                       ("jitter_s", {"lo": 0.0}), ("dark_count_rate_hz", {"lo": 0.0}),
                       ("ambient_rate_hz", {"lo": 0.0}), ("pde", {"lo": 0.0, "hi": 1.0, "lo_open": True}),
                       ("dead_time_s", {"lo": 0.0}), ("peak_threshold", pos)):
            if k in d:
                kw[k] = s.number(d[k], f"direct_tof.{k}", **rng)
        for k, lo, hi in (("cycles_per_frame", 1, 10**12), ("bins", 2, 100_000), ("max_peaks", 1, 64),
                          ("oversample", 1, 64)):
            if k in d:
                kw[k] = s.integer(d[k], f"direct_tof.{k}", lo=lo, hi=hi)
        cfg = cls(**kw)
        span = cfg.t0_s + cfg.bins * cfg.bin_width_s
        if max(span, cfg.dead_time_s) > 1.0 / cfg.repetition_hz:
            raise s.bad(cfg.repetition_hz, "direct_tof.repetition_hz",
                        f"a laser period (1/repetition_hz) of at least t0_s + bins * bin_width_s = {span:.4g} s "
                        "and the dead time (the histogram and the dead time fit in one cycle)")
        return cfg


# ---------------------------------------------------------------------------------- pulse
def _sigma_s(cfg: DirectToFConfig) -> float:
    """Standard deviation of a Gaussian pulse convolved with the jitter."""
    return math.hypot(cfg.pulse.fwhm_s / _FWHM_PER_SIGMA, cfg.jitter_s)


def _pulse_table(cfg: DirectToFConfig) -> tuple[np.ndarray, np.ndarray]:
    """A tabulated pulse convolved with the Gaussian jitter, as a fine, normalised CDF table."""
    t = np.asarray(cfg.pulse.times_s)
    v = np.asarray(cfg.pulse.values)
    sj = cfg.jitter_s
    dt = min(np.min(np.diff(t)), max(sj, 1e-15)) / 4
    grid = np.arange(t[0] - 6 * sj, t[-1] + 6 * sj + dt, dt)
    p = np.interp(grid, t, v, left=0.0, right=0.0)
    if sj > 0:
        k = np.arange(-math.ceil(6 * sj / dt), math.ceil(6 * sj / dt) + 1) * dt
        g = np.exp(-0.5 * (k / sj) ** 2)
        p = np.convolve(p, g / g.sum(), mode="same")
    cdf = np.concatenate([[0.0], np.cumsum((p[1:] + p[:-1]) / 2)])
    return grid, cdf / cdf[-1]


def pulse_cdf(cfg: DirectToFConfig, t_s: np.ndarray) -> np.ndarray:
    """Share of one pulse's (jittered) energy arriving before ``t_s`` after a zero-delay arrival."""
    t_s = np.asarray(t_s, dtype=np.float64)
    if cfg.pulse.kind == "gaussian":
        from scipy.special import ndtr

        return ndtr(t_s / _sigma_s(cfg))
    grid, cdf = _pulse_table(cfg)
    return np.interp(t_s, grid, cdf, left=0.0, right=1.0)


def pulse_matrix(cfg: DirectToFConfig, delays_s: np.ndarray) -> np.ndarray:
    """``M[s, i]``: share of a pulse delayed by ``delays_s[s]`` that falls in histogram bin ``i``."""
    e = cfg.edges_s
    c = pulse_cdf(cfg, e[None, :] - np.asarray(delays_s, dtype=np.float64)[:, None])
    return np.diff(c, axis=1)


def pulse_support_s(cfg: DirectToFConfig) -> tuple[float, float]:
    """Times before and after its delay within which a pulse puts all but ~1e-9 of its energy."""
    if cfg.pulse.kind == "gaussian":
        w = 6.1 * _sigma_s(cfg)
        return -w, w
    return cfg.pulse.times_s[0] - 6.1 * cfg.jitter_s, cfg.pulse.times_s[-1] + 6.1 * cfg.jitter_s


def render_edges_m(cfg: DirectToFConfig) -> np.ndarray:
    """Optical-path-length bin edges (m) for the render: ``oversample`` sub-bins per histogram
    bin, widened by the pulse's support so light from outside the histogram spills in right."""
    lo, hi = pulse_support_s(cfg)
    sub = cfg.bin_width_s / cfg.oversample
    t_lo = max(0.0, cfg.t0_s - hi)
    t_hi = cfg.edges_s[-1] - lo
    n = max(1, math.ceil((t_hi - t_lo) / sub))
    return C_M_PER_S * (t_lo + sub * np.arange(n + 1))


# ------------------------------------------------------------------------- photons per cycle
def photon_energy_j(wavelength_m: float) -> float:
    return H_PLANCK * C_M_PER_S / wavelength_m


def signal_photons(cfg: DirectToFConfig, transient_w: np.ndarray, edges_m: np.ndarray, emitter_power_w: float,
                   wavelength_m: float) -> np.ndarray:
    """Expected detected signal photons per bin and laser cycle ``[bins, H, W]`` from a
    transient render (``[T, H, W]`` watts per path-length bin ``edges_m``)."""
    centres_s = 0.5 * (edges_m[1:] + edges_m[:-1]) / C_M_PER_S
    M = pulse_matrix(cfg, centres_s)                                     # [T, bins]
    T = transient_w.shape[0]
    if emitter_power_w == 0:  # a dark frame: no pulse, background counts only
        return np.zeros((cfg.bins,) + transient_w.shape[1:])
    share = transient_w.reshape(T, -1) / emitter_power_w                 # energy share per sub-bin
    photons = cfg.pde * cfg.energy_j(emitter_power_w) / photon_energy_j(wavelength_m)
    return (M.T @ share).reshape((cfg.bins,) + transient_w.shape[1:]) * photons


def background_photons(cfg: DirectToFConfig, ambient_w: np.ndarray | float, wavelength_m: float) -> np.ndarray:
    """Expected background counts per bin and cycle (ambient light on the pixel ``ambient_w``
    times the PDE, the dark count rate and the extra rate), the same in every bin."""
    rate = cfg.pde * np.asarray(ambient_w, dtype=np.float64) / photon_energy_j(wavelength_m)
    return (rate + cfg.dark_count_rate_hz + cfg.ambient_rate_hz) * cfg.bin_width_s


# ------------------------------------------------------------------------- dead time, pile-up
def record_probabilities(lam: np.ndarray, dead_bins: int) -> np.ndarray:
    """Probability per cycle that bin ``i`` records a count, ``lam[i, ...]`` the mean photons
    per bin and cycle (see the module docstring; ``dead_bins >= len(lam)``: Coates' model)."""
    lam = np.asarray(lam, dtype=np.float64)
    hit = -np.expm1(-lam)
    P = np.empty_like(lam)
    window = np.zeros(lam.shape[1:])                 # sum of P over the last dead_bins bins
    for i in range(lam.shape[0]):
        P[i] = (1.0 - window) * hit[i]
        window += P[i]
        if i - dead_bins + 1 >= 0:
            window -= P[i - dead_bins + 1]
    return P


def sample_histogram(lam: np.ndarray, cycles: int, dead_bins: int, rng: np.random.Generator) -> np.ndarray:
    """One frame's counts ``[bins, ...]`` over ``cycles`` laser cycles: bin by bin,
    ``Binomial(cycles still armed, 1 - exp(-lam_i))``, exact for a non-paralysable SPAD."""
    lam = np.asarray(lam, dtype=np.float64)
    hit = -np.expm1(-lam)
    n = np.empty(lam.shape, dtype=np.int64)
    window = np.zeros(lam.shape[1:], dtype=np.int64)
    for i in range(lam.shape[0]):
        n[i] = rng.binomial(cycles - window, hit[i])
        window += n[i]
        if i - dead_bins + 1 >= 0:
            window -= n[i - dead_bins + 1]
    return n


def coates_correction(counts: np.ndarray, cycles: int, dead_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Coates' inverse: mean photons per bin and cycle ``lam_i = -ln(1 - n_i / A_i)`` with
    ``A_i = cycles - sum_{j=i-d}^{i-1} n_j`` the cycles armed in bin ``i``, and its variance
    ``p / ((1 - p) A)`` (``p = n / A``, the binomial's, by the delta method). A bin that
    recorded in every armed cycle is clipped to ``p = 1 - 1/(2A)``."""
    n = np.asarray(counts, dtype=np.float64)
    armed = np.empty_like(n)
    window = np.zeros(n.shape[1:])
    for i in range(n.shape[0]):
        armed[i] = cycles - window
        window += n[i]
        if i - dead_bins + 1 >= 0:
            window -= n[i - dead_bins + 1]
    A = np.maximum(armed, 1.0)
    p = np.clip(n / A, 0.0, 1.0 - 0.5 / A)
    return -np.log1p(-p), p / ((1.0 - p) * A)


# ------------------------------------------------------------------------- peaks and depth
def time_to_distance(t_s: np.ndarray | float) -> np.ndarray:
    """Radial distance of a round trip of ``t_s`` (camera and emitter together: ``c t / 2``)."""
    return C_M_PER_S * np.asarray(t_s, dtype=np.float64) / 2.0


@dataclass
class Peaks:
    """Peaks of histograms ``[K, H, W]`` strongest first (NaN / 0 where fewer than K)."""

    time_s: np.ndarray
    photons: np.ndarray          # signal photons per cycle under the peak (background removed)
    significance: np.ndarray     # matched-filter output / its noise standard deviation
    background: np.ndarray       # [H, W] background photons per bin and cycle

    @property
    def distance_m(self) -> np.ndarray:
        return time_to_distance(self.time_s)

    @property
    def count(self) -> np.ndarray:
        return np.sum(np.isfinite(self.time_s), axis=0)


def _kernel(cfg: DirectToFConfig) -> tuple[np.ndarray, int]:
    """The pulse's bin response to an arrival at a bin centre, as a centred odd-length kernel."""
    lo, hi = pulse_support_s(cfg)
    half = max(1, math.ceil(max(-lo, hi) / cfg.bin_width_s))
    e = (np.arange(-half, half + 2) - 0.5) * cfg.bin_width_s
    g = np.diff(pulse_cdf(cfg, e))
    g = g[:2 * half + 1]
    keep = g > 1e-4 * g.max()                       # trim the far tails: a shorter filter
    first, last = np.flatnonzero(keep)[[0, -1]]
    r = max(half - first, last - half)
    return g[half - r: half + r + 1], r


def find_peaks(cfg: DirectToFConfig, lam: np.ndarray, var: np.ndarray) -> Peaks:
    """Peaks of Coates-corrected histograms ``lam`` (photons per bin and cycle ``[bins, H, W]``,
    variance ``var``): background = median bin, matched filter with the pulse's bin response,
    local maxima above ``peak_threshold`` sigmas at least a pulse width apart, sub-bin time by
    Gaussian interpolation of the filter output; photons = filter output / sum(g^2) (the
    amplitude of a pulse whose bin response is ``g``)."""
    from scipy.ndimage import correlate1d, maximum_filter1d

    lam = np.asarray(lam, dtype=np.float64)
    shape = lam.shape[1:]
    bg = np.median(lam, axis=0)
    g, r = _kernel(cfg)
    x = lam - bg
    f = correlate1d(x, g, axis=0, mode="constant")
    sd = np.sqrt(np.maximum(correlate1d(var, g * g, axis=0, mode="constant"), 1e-300))
    snr = f / sd
    local = (f == maximum_filter1d(f, 2 * r + 1, axis=0, mode="constant")) & (snr > cfg.peak_threshold)
    K = cfg.max_peaks
    score = np.where(local, f, -np.inf)
    order = np.argsort(-score, axis=0)[:K]                               # [K, H, W]
    top = np.take_along_axis(score, order, axis=0)
    ok = np.isfinite(top)
    # Gaussian three-point interpolation of the filter output around each peak bin.
    nb = lam.shape[0]
    fm = np.take_along_axis(f, np.clip(order - 1, 0, nb - 1), axis=0)
    f0 = np.take_along_axis(f, order, axis=0)
    fp = np.take_along_axis(f, np.clip(order + 1, 0, nb - 1), axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        positive = (fm > 0) & (f0 > 0) & (fp > 0)
        lm, l0, lp = (np.log(np.where(positive, v, 1.0)) for v in (fm, f0, fp))
        den_g = lm - 2 * l0 + lp
        den_p = fm - 2 * f0 + fp
        delta = np.where(positive & (den_g < 0), 0.5 * (lm - lp) / den_g,
                         np.where(den_p < 0, 0.5 * (fm - fp) / den_p, 0.0))
    delta = np.clip(delta, -0.5, 0.5)
    t = cfg.t0_s + (order + 0.5 + delta) * cfg.bin_width_s
    gg = float(np.sum(g * g))
    return Peaks(time_s=np.where(ok, t, np.nan), photons=np.where(ok, f0 / gg * np.sum(g), 0.0),
                 significance=np.where(ok, np.take_along_axis(snr, order, axis=0), 0.0),
                 background=bg.reshape(shape))


# ------------------------------------------------------------------------- the whole chain
@dataclass
class DirectToFFrames:
    """Simulated direct-ToF frames of one scene: histograms and the peaks found in them."""

    config: DirectToFConfig
    expected_photons: np.ndarray     # [bins, H, W] mean photons per bin and cycle (signal + background)
    counts: list[np.ndarray]         # per frame [bins, H, W] counts (expected counts without noise)
    peaks: list[Peaks]

    @property
    def edges_s(self) -> np.ndarray:
        return self.config.edges_s


def expected_photons(scene: Any, result: Any, cfg: DirectToFConfig) -> np.ndarray:
    """Mean detected photons per bin and laser cycle ``[bins, H, W]`` from a transient render
    of ``scene`` made with ``render_edges_m(cfg)``."""
    if result.transient is None:
        raise ValueError("the render has no transient: render with transient_bins=render_edges_m(cfg)")
    wl = scene.sensor.wavelength_m
    lam = signal_photons(cfg, result.transient, result.transient_edges_m, scene.emitter.power_w, wl)
    return lam + background_photons(cfg, result.ambient_power_w, wl)[None]


def render_direct(scene: Any, *, progress: Any = None, **render_kwargs: Any) -> Any:
    """The scene's transient render on the direct-ToF configuration's path-length bins."""
    from tofhil.sim.memory import check_memory, render_memory
    from tofhil.sim.render import render

    edges = render_edges_m(scene.direct_tof)
    kw = {"freq_hz": [0.0], "transient_bins": edges, **render_kwargs}
    # the transient [T, H, W] is this render's largest array: refuse before allocating it
    check_memory(render_memory(scene, kw), source=str(getattr(scene, "source", "")))
    return render(scene, progress=progress, **kw)


def simulate_direct(scene: Any, frames: int = 1, seed: int = 0, noise: bool = True, *, result: Any = None,
                    progress: Any = None) -> DirectToFFrames:
    """Render once and expose ``frames`` histogram frames (independent counts per frame,
    seeded by ``(seed, frame)``; without noise the expected counts ``cycles * P``), with the
    peaks of each frame's Coates-corrected histogram."""
    cfg = scene.direct_tof
    if cfg is None:
        raise ValueError("the scene has no direct_tof block")
    if result is None:
        result = render_direct(scene, progress=progress)
    lam = expected_photons(scene, result, cfg)
    N, d = cfg.cycles_per_frame, cfg.dead_bins
    counts, peaks = [], []
    for i in range(frames):
        if noise:
            n = sample_histogram(lam, N, d, np.random.default_rng([seed, i]))
        else:
            n = N * record_probabilities(lam, d)
        counts.append(n.astype(np.float32))
        peaks.append(find_peaks(cfg, *coates_correction(n, N, d)))
    return DirectToFFrames(config=cfg, expected_photons=lam, counts=counts, peaks=peaks)


__all__ = ["DIRECT_TOF_KEYS", "DirectToFConfig", "DirectToFFrames", "Peaks", "PulseShape", "background_photons",
           "coates_correction", "expected_photons", "find_peaks", "pulse_cdf", "pulse_matrix", "record_probabilities",
           "render_direct", "render_edges_m", "sample_histogram", "signal_photons", "simulate_direct",
           "time_to_distance"]
