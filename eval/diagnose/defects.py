"""Defective pixels, found before any fit: a finding of their own, never a scene mismatch.

Real sensors have pixels that do not measure the light in front of them: stuck or dead
(the same taps in every frame), hot or blinking (a temporal scatter far above what the
pixel's signal level predicts), taps off the correlation model (for K >= 4 the part of the
taps no ``B + A cos(phi - theta_k)`` can make, far beyond its neighbours'), and isolated
spatial outliers (one pixel far from neighbours that agree with each other). A depth
camera's defects are depths of zero or none where the camera says the pixel is valid,
isolated outliers, and flying pixels at depth edges (mixed returns of two surfaces).

Each test compares a pixel with a model of the whole image or with its own neighbours, not
with an absolute level: a pattern every pixel shares (a tap gain imbalance, a harmonic) is
the diagnosis's to explain, not a defect. The thresholds are far in the tails of the noise
(stated with each kind), so that a capture without defects has none, and the mask they make
is taken out of both the training and the held-out pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from tofhil.binning import bin_mean
from tofhil.eval.metrics.noise import MAD_TO_SIGMA

#: A pixel's temporal variance this many times (or this fraction of) what the noise model
#: predicts at its signal level is hot / blinking (or stuck). With N frames the sample
#: variance of K F taps has N - 1 degrees of freedom per tap: a ratio of 16 has a probability
#: below 1e-12 for N = 4, K F = 4.
NOISY_RATIO = 16.0
STUCK_RATIO = 1.0 / 25.0
#: A stuck or hot pixel differs from its neighbours: at most this many of its 8 may do the
#: same (a dead or hot pair is found; a saturated region or a moving target's edge is not).
MAX_ALIKE_NEIGHBOURS = 2
#: A pixel whose taps repeat exactly is stuck only where a working pixel at its level would
#: repeat them (noise model + the ADC's 1 DN steps) with at most this probability: about one
#: false alarm in 4 megapixels.
STUCK_FALSE_ALARM = 2.5e-7
#: An off-model tap residual or a spatial deviation this many robust standard deviations
#: beyond the neighbourhood's is a defect.
OUTLIER_SIGMAS = 10.0
#: The neighbourhood (pixels on a side) a pixel is compared with.
NEIGHBOURHOOD_PX = 5

KINDS = {
    "stuck": "stuck or dead (the same taps in every frame)",
    "noisy": "hot or blinking (temporal scatter far above the noise model at its signal level)",
    "off_model": "taps off the correlation model (a part no B + A cos(phi - theta) makes, far beyond its neighbours')",
    "outlier": "isolated spatial outliers (far from neighbours that agree with each other)",
    "no_depth": "no depth (zero or none) where the camera marks the pixel valid",
    "flying": "flying pixels at depth edges (mixed returns of two surfaces)",
}


@dataclass
class Defects:
    """The defective pixels of a capture, by kind (bool maps ``[H, W]``; a pixel may be in several)."""

    shape: tuple[int, int]
    kinds: dict[str, np.ndarray] = field(default_factory=dict)
    #: How each kind was tested (what the data allowed: e.g. no stuck test on one frame).
    notes: list[str] = field(default_factory=list)
    #: Saturated or clipped pixels: a class of their own, not a defect (the pixel works; its
    #: light exceeds its range). Left out of the fit by the usable mask, never counted here.
    saturated: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.saturated is None:
            self.saturated = np.zeros(self.shape, bool)

    @property
    def mask(self) -> np.ndarray:
        out = np.zeros(self.shape, bool)
        for m in self.kinds.values():
            out |= m
        return out

    @property
    def count(self) -> int:
        return int(self.mask.sum())

    def text(self) -> str:
        n, total = self.count, int(np.prod(self.shape))
        sat = int(self.saturated.sum())
        said = (f"; {sat} saturated or clipped (not defects: their light exceeds the range)" if sat else "")
        if n == 0:
            return "no defective pixels found" + said
        parts = [f"{int(m.sum())} {KINDS[k].split(' (')[0]}" for k, m in self.kinds.items() if m.any()]
        return (f"{n} pixel{'s' if n != 1 else ''} ({100.0 * n / total:.2g} %) defective: " + ", ".join(parts)
                + "; excluded from the fit and the held-out figures" + said)

    def to_json(self) -> dict[str, Any]:
        total = int(np.prod(self.shape))
        return {"pixels": self.count, "fraction": self.count / total if total else 0.0,
                "kinds": {k: {"pixels": int(m.sum()), "what": KINDS[k]} for k, m in self.kinds.items()},
                "saturated_pixels": int(self.saturated.sum()),
                "text": self.text(), "notes": list(self.notes)}


def _local_median(img: np.ndarray, size: int = NEIGHBOURHOOD_PX) -> np.ndarray:
    return ndimage.median_filter(img, size=size, mode="nearest")


def _neighbours(img: np.ndarray) -> np.ndarray:
    """The 8 neighbours of every pixel ``[8, H, W]`` (mirrored at the border)."""
    h, w = img.shape
    padded = np.pad(img, 1, mode="reflect")
    return np.stack([padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                     for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])


def _robust_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """``y ~ a + b x`` (b >= 0) through the medians of y in 20 quantile bins of x: a noise
    model (read + shot noise) that a few defective pixels cannot pull, and the lowest bin's
    median (the quietest pixels' variance: a floor for the line). The intercept may be
    negative: the shot noise grows from the black level, not from 0 DN."""
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, 21)))
    if edges.size < 3:
        m = float(np.median(y))
        return m, 0.0, m
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    xm = np.array([np.median(x[idx == i]) for i in range(edges.size - 1) if np.any(idx == i)])
    ym = np.array([np.median(y[idx == i]) for i in range(edges.size - 1) if np.any(idx == i)])
    b, a = np.polyfit(xm, ym, 1) if xm.size >= 2 else (0.0, float(ym.mean()))
    if b < 0:
        b, a = 0.0, float(np.median(ym))
    return float(a), float(b), max(float(ym.min()), 0.0)


def _isolated(values: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Pixels far from every one of their 8 neighbours: the smallest difference exceeds
    ``OUTLIER_SIGMAS`` times both the neighbours' robust spread and the noise of a difference
    of two pixels. A corner or an edge, where some neighbours share the pixel's value, is not
    an outlier; a single pixel that differs from all of them is."""
    h, w = values.shape
    padded = np.pad(values, 1, mode="reflect")  # off the image: the mirrored interior neighbour
    nb = np.stack([padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                   for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])        # [8, H, W]
    nearest = np.abs(nb - values[None]).min(axis=0)
    med = np.median(nb, axis=0)
    spread = MAD_TO_SIGMA * np.median(np.abs(nb - med[None]), axis=0)
    scale = np.maximum(spread, np.sqrt(2.0) * noise)
    return nearest > OUTLIER_SIGMAS * np.maximum(scale, 1e-12)


#: Tap noise (DN) above which repeating taps are not computed as chance: at N = 3 frames and
#: 3 taps, (2 sqrt(pi) 6)^-6 ~ 1e-8, below STUCK_FALSE_ALARM.
NOISY_TAP_DN = 6.0


def _on_integers(taps: np.ndarray) -> bool:
    """Taps on the ADC's 1 DN grid (a sample of them, to bound the cost)."""
    flat = taps.reshape(-1)
    sample = flat[:: max(flat.size // 100_000, 1)]
    return bool(np.all(sample == np.round(sample)))


def repeat_probability(level: np.ndarray, variance: np.ndarray, n_frames: int, *, quantised: bool) -> np.ndarray:
    """Probability that a working pixel's taps repeat exactly over ``n_frames``: per tap
    (``level``, ``variance`` ``[..., P]`` in DN, the variance as measured, its 1/12 DN^2 of
    rounding included) the chance that every frame rounds to the same integer,
    ``sum_j p_j^N`` with ``p_j`` the Gaussian's mass on ``[j - 1/2, j + 1/2)``; the product
    over the leading axes (every tap of a pixel). Continuous taps never repeat: 0."""
    from scipy.special import ndtr

    level = np.asarray(level, dtype=np.float64)
    out_shape = level.shape[-1:] if level.ndim else ()
    if not quantised or level.size == 0:
        return np.zeros(out_shape)
    sigma = np.sqrt(np.maximum(np.asarray(variance, dtype=np.float64) - 1.0 / 12.0, 1e-4))
    # beyond NOISY_TAP_DN a tap repeats with probability below (2 sqrt(pi) sigma)^-(N-1): 0 here
    loud = sigma > NOISY_TAP_DN
    sigma = np.minimum(sigma, NOISY_TAP_DN)
    half = int(np.ceil(8.0 * float(sigma.max()))) + 1
    j = np.round(level)[None] + np.arange(-half, half + 1).reshape((-1,) + (1,) * level.ndim)
    p = ndtr((j + 0.5 - level[None]) / sigma[None]) - ndtr((j - 0.5 - level[None]) / sigma[None])
    per_tap = np.where(loud, 0.0, (p ** n_frames).sum(axis=0))
    return per_tap.reshape(-1, per_tap.shape[-1]).prod(axis=0)


def raw_defects(taps: np.ndarray, theta_rad: np.ndarray, clipped: np.ndarray | None = None) -> Defects:
    """Defects of raw-tap frames ``taps[N, F, K, H, W]`` (DN) with tap phases ``theta_rad[K]``.
    ``clipped`` (bool ``[H, W]``): pixels with a saturated tap; their taps hold still at the
    clip level, which is saturation, not a stuck pixel: they are neither defects nor used to
    fit the noise model."""
    taps = np.asarray(taps, dtype=np.float64)
    n, nf, k, h, w = taps.shape
    d = Defects((h, w))
    clipped = np.zeros((h, w), bool) if clipped is None else np.asarray(clipped, bool)
    mean = taps.mean(axis=0)                                      # [F, K, H, W]
    level = mean.mean(axis=(0, 1))                                # the pixel's mean tap level
    if n >= 3:
        var = taps.var(axis=0, ddof=1).mean(axis=(0, 1))          # temporal variance per tap
        fit = ~clipped if (~clipped).sum() >= 100 else np.ones((h, w), bool)
        a, b, floor = _robust_line(level[fit], var[fit])

        def noise_var(tap_level: np.ndarray) -> np.ndarray:  # the noise line, floored at its quietest bin
            return np.maximum(a + b * tap_level, floor)

        predicted = noise_var(level)
        # A defect is a pixel unlike its neighbours: a moving target or flicker changes whole
        # regions from frame to frame (and lifts the level-to-variance line), saturation holds
        # whole regions still; neither is a pixel that fails. The reference of each temporal
        # test is therefore its neighbours' variance, ranked so that up to
        # MAX_ALIKE_NEIGHBOURS of the 8 may share the pixel's fate (a dead pair is still found).
        ranked = np.sort(_neighbours(var), axis=0)                                 # [8, H, W]
        quiet_ref = ranked[-1 - MAX_ALIKE_NEIGHBOURS]   # most neighbours at or below this
        busy_ref = ranked[MAX_ALIKE_NEIGHBOURS]         # most neighbours at or above this
        d.kinds["noisy"] = var > NOISY_RATIO * np.maximum(np.minimum(quiet_ref, predicted), max(floor, 1e-12))
        spread = taps.std(axis=0, ddof=1).max(axis=(0, 1))    # every tap must hold still
        still = spread ** 2 < STUCK_RATIO * predicted
        # quantised taps of a quiet pixel repeat by chance: still only where that is unlikely
        chance = repeat_probability(mean[:, :, still], noise_var(mean[:, :, still]), n, quantised=_on_integers(taps))
        by_chance = np.zeros((h, w), bool)
        by_chance[still] = chance > STUCK_FALSE_ALARM
        d.kinds["stuck"] = still & ~by_chance & (spread ** 2 < STUCK_RATIO * busy_ref)
        if by_chance.any():
            d.notes.append(f"{int(by_chance.sum())} pixels repeat their taps in every frame, as quantised "
                           "taps of a quiet working pixel would (not called stuck)")
        # a region held still at the session's highest tap level is saturated: stated apart
        top = float(np.max(taps))
        d.saturated |= still & ~d.kinds["stuck"] & ~by_chance & (mean.max(axis=(0, 1)) >= top - 0.5)
        noise_mean = np.sqrt(np.maximum(predicted, 0.0) / n)
    else:
        d.notes.append(f"{n} frame(s): no temporal tests (stuck, hot); 3 or more frames allow them")
        noise_mean = np.zeros((h, w))
    if k >= 4:
        # the taps' part outside B + A cos(phi - theta_k), per frequency, of the frame mean
        e = np.exp(1j * np.asarray(theta_rad, dtype=np.float64))[None, :, None, None]
        s = (2.0 / k) * (mean * e).sum(axis=1, keepdims=True)
        model = mean.mean(axis=1, keepdims=True) + (s * np.conj(e)).real
        off = np.sqrt(((mean - model) ** 2).mean(axis=(0, 1)))
        local = _local_median(off)
        spread = MAD_TO_SIGMA * _local_median(np.abs(off - local))
        d.kinds["off_model"] = off - local > OUTLIER_SIGMAS * np.maximum(np.maximum(spread, noise_mean), 1e-12)
    amp = np.abs((2.0 / k) * (mean * np.exp(1j * np.asarray(theta_rad))[None, :, None, None]).sum(axis=1)).mean(axis=0)
    d.kinds["outlier"] = _isolated(level, noise_mean) | _isolated(amp, noise_mean)
    if "stuck" in d.kinds:  # a stuck pixel is one defect, not also an outlier
        for kind in ("outlier", "off_model", "noisy"):
            if kind in d.kinds:
                d.kinds[kind] &= ~d.kinds["stuck"]
    for kind in d.kinds:
        d.kinds[kind] &= ~clipped
    d.saturated |= clipped
    return d


#: A mixed (flying) pixel lies between the surfaces on its two sides, each gap at least
#: this fraction of its range (and ``OUTLIER_SIGMAS`` noise): a step of a few per cent.
FLYING_GAP_FRACTION = 0.02


def _flying(r: np.ndarray, ok: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Pixels strictly between their two opposite neighbours (left/right, up/down or a
    diagonal), both gaps large: a return mixed from the two surfaces of a depth step. The
    pixels of the step itself, equal to their own side, are not flagged."""
    h, w = r.shape
    padded = np.pad(r, 1, mode="edge")
    okp = np.pad(ok, 1, mode="constant")
    gap = np.maximum(FLYING_GAP_FRACTION * r, OUTLIER_SIGMAS * noise)
    out = np.zeros(r.shape, bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        b = padded[1 - dy:1 - dy + h, 1 - dx:1 - dx + w]
        both = okp[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] & okp[1 - dy:1 - dy + h, 1 - dx:1 - dx + w]
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        out |= both & (r - lo > gap) & (hi - r > gap)
    return out & ok


def depth_defects(radial_m: np.ndarray, valid: np.ndarray, camera: Any, noise_m: np.ndarray | None = None) -> Defects:
    """Defects of a depth frame ``[H, W]`` (radial metres, the camera's validity): no depth
    where valid, isolated outliers against ``noise_m`` (the depth noise per pixel), and
    flying pixels between the two surfaces of a depth step."""
    r = np.asarray(radial_m, dtype=np.float64)
    valid = np.asarray(valid, bool)
    d = Defects(r.shape)
    d.kinds["no_depth"] = valid & ~(np.isfinite(r) & (r > 0))
    ok = valid & ~d.kinds["no_depth"]
    med = float(np.median(r[ok])) if ok.any() else 0.0
    filled = np.where(ok, r, med)
    if noise_m is None:
        # no noise model: the local robust scatter about a 3 x 3 median, over 7 x 7 pixels (a
        # real depth image quantised to 1 mm has neighbours of equal value, whose spread alone
        # is 0: every pixel one step off would be an outlier)
        dev = np.abs(filled - ndimage.median_filter(filled, size=3, mode="nearest"))
        noise = MAD_TO_SIGMA * ndimage.median_filter(np.where(ok, dev, 0.0), size=7, mode="nearest")
    else:
        noise = np.nan_to_num(np.asarray(noise_m, dtype=np.float64))
    d.kinds["outlier"] = _isolated(filled, noise) & ok
    # an outlier is not a surface its neighbours could be mixed with
    clean = np.where(d.kinds["outlier"], ndimage.median_filter(filled, size=3, mode="nearest"), filled)
    d.kinds["flying"] = _flying(clean, ok & ~d.kinds["outlier"], noise)
    return d


#: Share of a bin's pixels that must be usable for the bin to be (their mean is the bin's).
BIN_USABLE_SHARE = 0.75


def binned_defects(defects: Defects, b: int) -> Defects:
    """Defects on the binned grid: a bin whose defective pixels are more than it can spare
    (:data:`BIN_USABLE_SHARE`) is one; the others are the mean of their good pixels."""
    shape = (defects.shape[0] // b, defects.shape[1] // b)
    # a bin holding a saturated pixel is saturated: the mean of the others is not the bin's light
    out = Defects(shape, notes=list(defects.notes), saturated=bin_mean(defects.saturated.astype(float), b) > 0)
    # a bin is left out when its defective pixels together are more than it can spare, and
    # is counted under the kind most of them have
    names = list(defects.kinds)
    if names:
        shares = np.stack([bin_mean(defects.kinds[k].astype(float), b) for k in names])
        left_out = bin_mean(defects.mask.astype(float), b) > 1.0 - BIN_USABLE_SHARE
        dominant = shares.argmax(axis=0)
        for i, kind in enumerate(names):
            out.kinds[kind] = left_out & (dominant == i)
    n, total = defects.count, int(np.prod(defects.shape))
    out.notes.append(f"found on the full image ({n} of its {total} pixels, {100.0 * n / max(total, 1):.2g} %), "
                     f"shown on the {b} x {b} binned grid the diagnosis uses: a bin is left out when more than "
                     f"{100 * (1 - BIN_USABLE_SHARE):.0f} % of its pixels are defective, else it is the mean of "
                     "its good pixels")
    return out
