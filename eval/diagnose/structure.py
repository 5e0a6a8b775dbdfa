"""What the residual left after a diagnosis looks like: the structures a ToF engineer looks for.

A residual region above noise that covers a whole object says only "this object disagrees".
This module splits each channel's residual map (depth in m, amplitude as a log ratio) into
the parts an engineer names, each tested against the noise of the same pixels:

- **edges**: pixels next to a depth step or an object outline (mixed / flying pixels, a
  plane that ends where the patch does not); their residual is compared with the interior's;
- **smooth field component**, per object: a cubic polynomial in the image coordinates fitted
  to the interior residual (robustly: one refit without the pixels beyond 4 MAD), with the
  share of it that is radial about the principal point (lens distortion, a wrong focal
  length or a field-angle-dependent range error look radial; a bowed surface or a tilt does
  not have to);
- **fixed pattern**: column and row medians of what the smooth part leaves, against the
  scatter a median of that many pixels has;
- **spots**: connected pixels whose remaining residual exceeds 5 sigma (at least
  :data:`MIN_SPOT_PX`), placed on the object and flagged when they touch its outline.

A part is reported when its chi-square against the pixel noise exceeds the ``1 - ALPHA``
quantile for its degrees of freedom (:mod:`tofhil.eval.diagnose.verdict`), and when it is larger than
``min_fraction`` of the noise in rms (the twin cannot be asked to follow the device's
sub-noise texture). All coordinates are those of the diagnosis grid (binned pixels).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from scipy import ndimage, stats

from tofhil.eval.metrics.noise import robust_sigma
from tofhil.eval.diagnose.verdict import ALPHA

#: Fewest pixels for an object's smooth fit and for a spot.
MIN_OBJECT_PX = 40
MIN_SPOT_PX = 4
#: A spot: remaining residual beyond this many noise sigmas.
SPOT_SIGMAS = 5.0


@dataclass
class Finding:
    """One structure of a residual map."""

    channel: str            # depth | amplitude
    kind: str               # edges | smooth | column pattern | row pattern | spot
    obj: str                # the object it lies on ("" for the whole image)
    rms: float              # rms of the structure (m for depth, log ratio for amplitude)
    noise_rms: float        # the noise's rms on the same pixels (same unit)
    pixels: int
    text: str
    extra: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {"channel": self.channel, "kind": self.kind, "object": self.obj, "rms": self.rms,
                "noise_rms": self.noise_rms, "pixels": self.pixels, "text": self.text} | self.extra


def _significant(chi2: float, dof: int) -> bool:
    return dof > 0 and chi2 > stats.chi2.isf(ALPHA, dof)


def edge_mask(depth_m: np.ndarray, usable: np.ndarray, object_id: np.ndarray, *, step: float = 0.03) -> np.ndarray:
    """Pixels within one pixel of a depth step (neighbours differing by more than ``step``
    times the distance), of an outline between the twin's objects, or of the unusable."""
    d = np.where(usable, depth_m, np.nan)
    steps = np.zeros(usable.shape, bool)
    for ax in (0, 1):
        diff = np.abs(np.diff(d, axis=ax))
        with np.errstate(invalid="ignore"):
            jump = diff > step * np.fmin(np.take(d, range(d.shape[ax] - 1), axis=ax),
                                         np.take(d, range(1, d.shape[ax]), axis=ax))
        outline = np.diff(object_id, axis=ax) != 0
        hole = np.diff(usable.astype(np.int8), axis=ax) != 0
        e = jump | outline | hole
        sl_a = [slice(None)] * 2
        sl_b = [slice(None)] * 2
        sl_a[ax], sl_b[ax] = slice(0, -1), slice(1, None)
        steps[tuple(sl_a)] |= e
        steps[tuple(sl_b)] |= e
    return ndimage.binary_dilation(steps, np.ones((3, 3), bool)) & usable


def _poly_terms(u: np.ndarray, v: np.ndarray, degree: int = 3) -> np.ndarray:
    return np.stack([u ** i * v ** j for i in range(degree + 1) for j in range(degree + 1 - i)], axis=1)


def _fmt(x: float, channel: str) -> str:
    """Depth in mm; amplitude (a log ratio) as the relative change it means."""
    return f"{x * 1e3:.2f} mm" if channel == "depth" else f"{100 * float(np.expm1(x)):.1f} %"


def _robust_fit(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    coef = np.linalg.lstsq(X, y, rcond=None)[0]
    r = y - X @ coef
    mad = robust_sigma(r)
    keep = np.abs(r) <= 4.0 * max(mad, 1e-300)
    if keep.sum() > X.shape[1] * 3:
        coef = np.linalg.lstsq(X[keep], y[keep], rcond=None)[0]
    return coef


def channel_structure(channel: str, residual: np.ndarray, sigma: np.ndarray, usable: np.ndarray,
                      object_id: np.ndarray, object_names: Mapping[int, str], edges: np.ndarray,
                      centre: tuple[float, float], *, min_fraction: float = 0.5) -> list[Finding]:
    """The findings of one channel's residual map (see the module doc). ``sigma``: the noise
    standard deviation of each pixel's residual, in the residual's unit."""
    ok = usable & np.isfinite(residual) & np.isfinite(sigma) & (sigma > 0)
    out: list[Finding] = []
    h, w = residual.shape
    scale = 0.5 * max(h, w)
    vv, uu = np.mgrid[0:h, 0:w]
    un, vn = (uu - centre[0]) / scale, (vv - centre[1]) / scale

    # edges: mixed pixels, outlines
    e = ok & edges
    inner = ok & ~edges
    if e.sum() >= MIN_SPOT_PX and inner.sum() >= MIN_OBJECT_PX:
        z_e = residual[e] / sigma[e]
        med_in = float(np.median(np.abs(residual[inner])))
        med_e = float(np.median(np.abs(residual[e])))
        chi = float(np.sum(np.minimum(z_e, 1e6) ** 2))
        if _significant(chi, int(e.sum())) and med_e > 2.0 * med_in:
            ids, counts = np.unique(object_id[e], return_counts=True)
            on = ", ".join(f"{object_names.get(int(i), 'background')} {100 * c / e.sum():.0f} %"
                           for i, c in sorted(zip(ids, counts), key=lambda t: -t[1])[:3])
            rms = float(np.sqrt(np.mean(residual[e] ** 2)))
            what = ("mixed / flying pixels at depth edges and outlines" if channel == "depth"
                    else "amplitude at depth edges and outlines")
            out.append(Finding(channel, "edges", "", rms, float(np.sqrt(np.mean(sigma[e] ** 2))), int(e.sum()),
                               f"{channel}: {what}: {int(e.sum())} px within one pixel of an edge ({on}), median "
                               f"|residual| {_fmt(med_e, channel)} against {_fmt(med_in, channel)} inside; the twin "
                               "has no mixed pixels (one path per pixel)", {"median_abs_edge": med_e,
                                                                           "median_abs_inside": med_in}))
    # per object: smooth field component, patterns, spots
    for oid, name in object_names.items():
        m = inner & (object_id == oid)
        n = int(m.sum())
        if n < MIN_OBJECT_PX:
            continue
        y, s = residual[m], sigma[m]
        X = _poly_terms(un[m], vn[m])
        coef = _robust_fit(X / s[:, None], y / s)
        smooth = X @ coef
        mean = float(np.average(y, weights=1.0 / s ** 2))
        shape = smooth - np.average(smooth, weights=1.0 / s ** 2)
        noise_rms = float(np.sqrt(np.mean(s ** 2)))
        shape_rms = float(np.sqrt(np.mean(shape ** 2)))
        chi = float(np.sum((shape / s) ** 2))
        if _significant(chi, X.shape[1] - 1) and shape_rms > min_fraction * noise_rms / np.sqrt(max(n / 50.0, 1.0)):
            r2 = un[m] ** 2 + vn[m] ** 2
            R = np.stack([np.ones(n), r2, r2 ** 2], axis=1)
            rc = np.linalg.lstsq(R / s[:, None], smooth / s, rcond=None)[0]
            radial = R @ rc
            radial_share = float(1.0 - np.sum((smooth - radial) ** 2 / s ** 2) / max(np.sum(shape ** 2 / s ** 2), 1e-300))
            radial_share = min(max(radial_share, 0.0), 1.0)
            # the shape about the object's mean, as its rms is (the mean is a level, said apart:
            # a centre "811 %" beside "9.1 % rms" mixed the two)
            full = np.full(residual.shape, np.nan)
            full[m] = shape
            rows = np.array_split(np.arange(h), 3)
            cols = np.array_split(np.arange(w), 3)
            grid = [[np.nanmedian(full[np.ix_(r, c)]) if np.isfinite(full[np.ix_(r, c)]).any() else np.nan
                     for c in cols] for r in rows]
            centre_v = grid[1][1]
            corners = [grid[i][j] for i in (0, 2) for j in (0, 2) if np.isfinite(grid[i][j])]
            where = ""
            if np.isfinite(centre_v) and corners:
                where = (f" (about its mean: centre {_fmt(centre_v, channel)}, corners {_fmt(min(corners), channel)} "
                         f"to {_fmt(max(corners), channel)})")
            if radial_share >= 0.6:
                hint = ("mostly radial: the signature of lens distortion, a wrong focal length or a field-angle-"
                        "dependent error" if channel == "depth" else "mostly radial: the emitter's profile or the "
                        "lens's vignetting")
            elif radial_share > 0.4:
                hint = ("partly radial: a field-angle error (lens, focal length) and a surface or distance effect "
                        "together" if channel == "depth" else "partly radial: the emitter's profile or vignetting "
                        "and a reflectance that varies over the object together")
            elif channel == "depth":
                hint = ("mostly not radial: a bowed or tilted surface, a scene the twin places differently, or an "
                        "error that follows the distance or the amplitude rather than the field angle")
            else:
                hint = ("mostly not radial: a reflectance that varies over the object, or light the twin does not "
                        "have there (stray light, multipath)")
            out.append(Finding(channel, "smooth", name, shape_rms, noise_rms, n,
                               f"{channel} on {name}: a smooth error over the field of {_fmt(shape_rms, channel)} rms"
                               f"{where}, {100 * radial_share:.0f} % of it radial about the principal point, {hint}; "
                               f"the noise is {_fmt(noise_rms, channel)} per pixel",
                               {"radial_share": radial_share, "mean": mean, "grid_3x3": grid}))
        rest = np.full(residual.shape, np.nan)
        rest[m] = y - smooth
        # fixed pattern: column and row medians of what the smooth part leaves
        for axis, label in ((0, "column"), (1, "row")):
            cnt = np.isfinite(rest).sum(axis=axis)
            keep = cnt >= 5
            if keep.sum() < 5:
                continue
            med = np.nanmedian(rest[:, keep] if axis == 0 else rest[keep, :], axis=axis)
            sig2 = np.where(np.isfinite(rest), np.broadcast_to(sigma, rest.shape) ** 2, 0.0).sum(axis=axis)
            sig_line = np.sqrt(sig2[keep] / cnt[keep])
            # a median of k values scatters 1.2533 sigma / sqrt(k)
            se = 1.2533 * sig_line / np.sqrt(cnt[keep])
            chi = float(np.sum((med / se) ** 2))
            rms = float(np.sqrt(np.mean(med ** 2)))
            if _significant(chi, int(keep.sum())) and rms > min_fraction * float(np.sqrt(np.mean(se ** 2))) * 3:
                line = np.zeros(rest.shape[1 - axis])
                line[keep] = med
                rest = rest - (line[None, :] if axis == 0 else line[:, None])  # spots are what the pattern leaves
                out.append(Finding(channel, f"{label} pattern", name, rms, float(np.sqrt(np.mean(se ** 2))),
                                   int(keep.sum()),
                                   f"{channel} on {name}: a {label} pattern of {_fmt(rms, channel)} rms over "
                                   f"{int(keep.sum())} {label}s (each {label}'s median after the smooth part; "
                                   f"{_fmt(float(np.sqrt(np.mean(se ** 2))), channel)} expected from noise): a sensor "
                                   f"fixed pattern, or straight {label}-wise structure in the scene (a frame, an edge) "
                                   "the twin's surface does not have", {}))
        # spots: connected pixels far beyond the noise after the smooth part
        z = np.where(m, np.abs(rest) / sigma, 0.0)
        spot = z > SPOT_SIGMAS
        labels, k = ndimage.label(spot, np.ones((3, 3), bool))
        if not k:
            continue
        outline = ndimage.binary_dilation(~(object_id == oid) | ~usable, np.ones((5, 5), bool))
        spots = []
        for i, sl in enumerate(ndimage.find_objects(labels), start=1):
            sm = labels[sl] == i
            px = int(sm.sum())
            if px < MIN_SPOT_PX:
                continue
            full = np.zeros(residual.shape, bool)
            full[sl] = sm
            spots.append((px, sl, float(np.median(rest[full])), bool((full & outline).any())))
        spots.sort(key=lambda t: -t[0])
        for px, sl, med, at_edge in spots[:3]:
            x0, x1, y0, y1 = sl[1].start, sl[1].stop, sl[0].start, sl[0].stop
            out.append(Finding(channel, "spot", name, abs(med), noise_rms, px,
                               f"{channel} on {name}: {px} px at x {x0}-{x1 - 1}, y {y0}-{y1 - 1} "
                               f"{'on its outline' if at_edge else 'inside it'}, {_fmt(med, channel)} beyond the "
                               f"smooth part (> {SPOT_SIGMAS:g} sigma)"
                               + (": the patch ends or bends where the twin's plane does not" if at_edge else ""),
                               {"bbox_x0y0x1y1": [int(x0), int(y0), int(x1), int(y1)], "at_outline": at_edge}))
    return out
