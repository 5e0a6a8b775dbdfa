"""The figures of depth bench procedures, computed once (the bench reports and tests read them).

* :func:`depth_stack_stats` -- vendors' accuracy and precision: the systematic error is the
  mean of N frames minus the ground truth, the random error the temporal standard deviation,
  on a region (a centre ROI) and over the whole field; each with its standard error.
* :func:`plane_flatness` -- the residual of a plane fitted to a flat target's points (least
  squares in depth, orthogonal residuals; outliers beyond 4 robust sigma left out and counted).
* :func:`fill_rate` -- the share of a region's pixels with a valid depth.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


def centre_roi(shape: tuple[int, int], fraction: float = 0.2) -> tuple[int, int, int, int]:
    """A centred region ``X0, Y0, X1, Y1`` (half-open) covering ``fraction`` of each side."""
    h, w = shape
    rw, rh = max(2, round(w * fraction)), max(2, round(h * fraction))
    x0, y0 = (w - rw) // 2, (h - rh) // 2
    return x0, y0, x0 + rw, y0 + rh


@dataclass
class StackStats:
    """Accuracy and precision of N frames of one static target."""

    frames: int
    systematic_m: float          # ROI mean of (per-pixel mean - truth)
    systematic_se_m: float       # its standard error from the temporal noise
    random_m: float              # ROI RMS of the per-pixel temporal standard deviation
    random_var_se_m2: float      # standard error of random_m ** 2
    systematic_field_m: float    # median over the field's pixels of (mean - truth)
    random_field_m: float        # median over the field's pixels of the temporal std
    fill_rate_roi: float
    fill_rate_field: float
    pixels_roi: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def depth_stack_stats(radial_m: np.ndarray, valid: np.ndarray, truth_m: np.ndarray,
                      roi: tuple[int, int, int, int]) -> StackStats:
    """``radial_m``, ``valid``: ``[N, H, W]``; ``truth_m``: ``[H, W]`` (the same kind of distance).

    A pixel counts when it is valid in every frame (a pixel that drops out now and then is a
    fill-rate matter, not an accuracy one)."""
    d = np.asarray(radial_m, dtype=np.float64)
    ok = np.all(np.asarray(valid, dtype=bool) & np.isfinite(d), axis=0) & np.isfinite(truth_m)
    n = d.shape[0]
    mean = d.mean(axis=0)
    var = d.var(axis=0, ddof=1) if n > 1 else np.full(mean.shape, np.nan)
    err = mean - truth_m
    x0, y0, x1, y1 = roi
    sl = (slice(y0, y1), slice(x0, x1))
    r_ok = ok[sl]
    npx = int(r_ok.sum())
    e_r, v_r = err[sl][r_ok], var[sl][r_ok]
    if npx == 0:
        nan = math.nan
        return StackStats(n, nan, nan, nan, nan, nan, nan, 0.0, float(ok.mean()), 0)
    mv = float(v_r.mean()) if n > 1 else math.nan
    return StackStats(
        frames=n, systematic_m=float(e_r.mean()),
        systematic_se_m=math.sqrt(mv / (n * npx)) if n > 1 else math.nan,
        random_m=math.sqrt(mv) if n > 1 else math.nan,
        # the sample variance of N Gaussian draws has variance 2 s^4 / (N - 1); npx independent pixels
        random_var_se_m2=mv * math.sqrt(2.0 / ((n - 1) * npx)) if n > 1 else math.nan,
        systematic_field_m=float(np.median(err[ok])) if ok.any() else math.nan,
        random_field_m=float(np.median(np.sqrt(var[ok]))) if ok.any() and n > 1 else math.nan,
        fill_rate_roi=float(np.mean(np.all(valid, axis=0)[sl])), fill_rate_field=float(ok.mean()),
        pixels_roi=npx)


@dataclass
class Flatness:
    rms_m: float
    pv_m: float                # 1st to 99th percentile of the orthogonal residual
    normal: tuple[float, float, float]
    distance_m: float          # the plane's distance from the camera centre
    points: int
    outliers: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def plane_flatness(points: np.ndarray, *, clip_sigma: float = 4.0, iterations: int = 5) -> Flatness:
    """Fit a plane ``z = a x + b y + c`` to ``points [M, 3]`` by least squares in depth (the
    camera's noise is along its rays, close to z for a target facing it: a total-least-squares
    fit tilts a small noisy patch towards the noise), leaving out points beyond ``clip_sigma``
    robust sigma (1.4826 MAD) of the residual, and report the orthogonal residual's RMS and
    1-99 % peak-to-valley."""
    p = np.asarray(points, dtype=np.float64)
    finite = np.isfinite(p).all(axis=1)
    keep = finite.copy()
    if keep.sum() < 3:
        return Flatness(math.nan, math.nan, (math.nan,) * 3, math.nan, int(keep.sum()), 0)
    design = np.column_stack([p[:, 0], p[:, 1], np.ones(len(p))])
    for _ in range(iterations):
        coef, *_ = np.linalg.lstsq(design[keep], p[keep, 2], rcond=None)
        r = (p[:, 2] - design @ coef) / math.sqrt(1.0 + coef[0] ** 2 + coef[1] ** 2)   # orthogonal distance
        med = np.median(r[keep])
        mad = 1.4826 * np.median(np.abs(r[keep] - med))
        new = finite & (np.abs(r - med) <= clip_sigma * max(mad, 1e-12))
        if np.array_equal(new, keep) or new.sum() < 3:
            break
        keep = new
    rk = r[keep]
    nrm = np.array([coef[0], coef[1], -1.0]) / math.sqrt(1.0 + coef[0] ** 2 + coef[1] ** 2)   # towards the camera
    return Flatness(float(np.sqrt(np.mean(rk ** 2))), float(np.percentile(rk, 99) - np.percentile(rk, 1)),
                    tuple(float(v) for v in nrm), float(abs(coef[2]) / math.sqrt(1.0 + coef[0] ** 2 + coef[1] ** 2)),
                    int(keep.sum()), int(finite.sum() - keep.sum()))


def fill_rate(valid: np.ndarray, roi: tuple[int, int, int, int] | None = None) -> float:
    v = np.asarray(valid, dtype=bool)
    if roi is not None:
        x0, y0, x1, y1 = roi
        v = v[..., y0:y1, x0:x1]
    return float(v.mean()) if v.size else math.nan


@dataclass
class SphereFit:
    centre: tuple[float, float, float]
    radius_m: float
    form_m: float              # range of the radial residuals (VDI/VDE 2634-2 probing error, form)
    rms_m: float
    points: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def fit_sphere(points: np.ndarray, *, iterations: int = 20, radius: float | None = None) -> SphereFit:
    """Least-squares sphere through ``points [M, 3]``: the algebraic fit, then Gauss-Newton on
    the geometric distances ``|p - c| - r``; with ``radius`` (a calibrated sphere) the radius is
    held there and only the centre fitted (on a small cap a free radius trades off against the
    centre's depth)."""
    p = np.asarray(points, dtype=np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) < 4:
        return SphereFit((math.nan,) * 3, math.nan, math.nan, math.nan, len(p))
    # algebraic: |p|^2 = 2 c . p + (r^2 - |c|^2)
    a = np.column_stack([2 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(a, (p ** 2).sum(axis=1), rcond=None)
    c = sol[:3]
    r = math.sqrt(max(sol[3] + c @ c, 0.0)) if radius is None else float(radius)
    for _ in range(iterations):
        v = p - c
        dist = np.linalg.norm(v, axis=1)
        res = dist - r
        j = -v / dist[:, None] if radius is not None else np.column_stack([-v / dist[:, None], -np.ones(len(p))])
        step, *_ = np.linalg.lstsq(j, -res, rcond=None)
        c = c + step[:3]
        if radius is None:
            r = r + step[3]
        if np.abs(step).max() < 1e-9:
            break
    res = np.linalg.norm(p - c, axis=1) - r
    return SphereFit(tuple(float(x) for x in c), float(r), float(res.max() - res.min()),
                     float(np.sqrt(np.mean(res ** 2))), len(p))
