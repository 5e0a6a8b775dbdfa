"""Compiled lens models (numba), per point: :mod:`tofhil.lens_models`' arithmetic compiled
unchanged, and the Newton loops over it.

Shared by :meth:`CameraModel.undistort_normalized` (many points: each point's Newton
iterations stay in registers, where the numpy version makes a dozen array passes per
iteration) and the renderer's sub-pixel rays (:func:`tofhil.sim.kernels.subpixel_rays`), so
both invert a lens the same way. The loops do the numpy version's operations in the same
order (no fast-math: no reassociation, no fused multiply-add), so for the Brown-Conrady family
the results are bit-identical to it. Coefficients: :func:`tofhil.lens_models.kernel_coeffs`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tofhil import lens_models as lm
from tofhil.numba_cache import drop_stale_cache as _drop_stale_cache

_inline = njit(cache=True, error_model="numpy", nogil=True, inline="always")
brown_distort = _inline(lm.brown_distort)
brown_jacobian = _inline(lm.brown_jacobian)
fisheye_theta_d = _inline(lm.fisheye_theta_d)
brown_radial_slope = _inline(lm.brown_radial_slope)

_MAX_HALVINGS = lm.MAX_HALVINGS
_STEP_TOL = lm.STEP_TOL
_ROUNDING = lm.ROUNDING_RESIDUAL
_CONVERGED = lm.CONVERGED_RESIDUAL


beyond_reach_sq = _inline(lm.beyond_reach_sq)
radially_symmetric = _inline(lm.radially_symmetric)
brown_radius = _inline(lm.brown_radius)


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def brown_radius_undistort(xd, yd, c, max_iter):  # pragma: no cover
    """:func:`brown_undistort` of a radially symmetric model, along the point's radius
    (:func:`tofhil.lens_models.brown_radius_undistort`, operation by operation)."""
    rd2 = xd * xd + yd * yd
    if rd2 == 0.0:
        return xd, yd
    rd = math.sqrt(rd2)
    r = rd
    f, df, g = brown_radius(r, c)
    e = rd - f
    a = abs(e)
    for _ in range(max_iter):
        if not (a != 0.0 and df != 0.0 and math.isfinite(df)):
            break
        s = e / df
        t = 1.0
        rn, en, an, dfn, gn = r, e, a, df, g
        for _h in range(_MAX_HALVINGS):
            rn = r + t * s
            fn, dfn, gn = brown_radius(rn, c)
            en = rd - fn
            an = abs(en)
            if an <= a or a < _ROUNDING:
                break
            t = t * 0.5
        r, e, a, df, g = rn, en, an, dfn, gn
        if t * abs(s) <= _STEP_TOL * (1.0 + abs(r)):
            break
    l1 = abs(xd) + abs(yd)
    if not (a * l1 <= _CONVERGED * (1.0 + l1) * rd and g * df > 0.0 and r * r <= c[12]):
        return math.nan, math.nan
    k = r / rd
    return xd * k, yd * k


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def brown_undistort(xd, yd, c, max_iter):  # pragma: no cover
    """Distorted normalised ``(xd, yd)`` -> undistorted ``(x, y)``; NaN where the model has
    no inverse (no convergence, or a root beyond the model's reach ``c[12]``:
    :func:`tofhil.lens_models.model_reach`)."""
    if xd * xd + yd * yd > beyond_reach_sq(c):
        return math.nan, math.nan
    if radially_symmetric(c):
        return brown_radius_undistort(xd, yd, c, max_iter)
    x, y = xd, yd
    fx, fy = brown_distort(x, y, c)
    ex, ey = xd - fx, yd - fy
    r = abs(ex) + abs(ey)
    for _ in range(max_iter):
        if r == 0.0:
            break
        j00, j01, j10, j11 = brown_jacobian(x, y, c)
        det = j00 * j11 - j01 * j10
        if not (det != 0.0 and math.isfinite(det)):
            break
        sx = (j11 * ex - j01 * ey) / det
        sy = (j00 * ey - j10 * ex) / det
        t = 1.0
        xn, yn, exn, eyn, rn = x, y, ex, ey, r
        for _h in range(_MAX_HALVINGS):
            xn = x + t * sx
            yn = y + t * sy
            fx, fy = brown_distort(xn, yn, c)
            exn, eyn = xd - fx, yd - fy
            rn = abs(exn) + abs(eyn)
            if rn <= r or r < _ROUNDING:
                break
            t = t * 0.5
        x, y, ex, ey, r = xn, yn, exn, eyn, rn
        if t * (abs(sx) + abs(sy)) <= _STEP_TOL * (1.0 + abs(x) + abs(y)):
            break
    j00, j01, j10, j11 = brown_jacobian(x, y, c)
    if not (r <= _CONVERGED * (1.0 + abs(xd) + abs(yd)) and j00 * j11 - j01 * j10 > 0.0
            and x * x + y * y <= c[12]):
        return math.nan, math.nan
    return x, y


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def fisheye_theta(td, c, max_iter):  # pragma: no cover
    """Distorted radius ``theta_d`` -> field angle ``theta`` in [0, pi] (NaN: no inverse)."""
    if td == 0.0:
        return 0.0
    th = min(td, math.pi)
    f, df = fisheye_theta_d(th, c)
    e = td - f
    r = abs(e)
    for _ in range(max_iter):
        if r == 0.0:
            break
        if not (df > 0.0 and math.isfinite(df)):
            break
        s = e / df
        t = 1.0
        thn, en, rn = th, e, r
        for _h in range(_MAX_HALVINGS):
            thn = min(max(th + t * s, 0.0), math.pi)
            f, df = fisheye_theta_d(thn, c)
            en = td - f
            rn = abs(en)
            if rn <= r or r < _ROUNDING:
                break
            t = t * 0.5
        step = abs(thn - th)
        th, e, r = thn, en, rn
        if step <= _STEP_TOL * (1.0 + th):
            break
    f, df = fisheye_theta_d(th, c)
    if not (r <= _CONVERGED * (1.0 + td) and df > 0.0 and th <= c[12]):
        return math.nan
    return th


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def _radial_slope(t, c, fisheye):  # pragma: no cover
    if fisheye:
        return fisheye_theta_d(t, c)[1]
    return brown_radial_slope(t, c)


@njit(cache=True, error_model="numpy", nogil=True)
def first_fold(grid, c, fisheye):  # pragma: no cover
    """The last point before the radial function of the lens stops rising: the first point of
    ``grid`` whose slope is not positive, bisected (60 halvings) against the one before it;
    NaN when the slope is positive over the whole grid (:func:`tofhil.lens_models.model_reach`)."""
    for i in range(grid.shape[0]):
        if not _radial_slope(grid[i], c, fisheye) > 0:
            if i == 0:
                return grid[0]
            lo, hi = grid[i - 1], grid[i]
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                if _radial_slope(mid, c, fisheye) > 0:
                    lo = mid
                else:
                    hi = mid
            return lo
    return math.nan


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def pixel_ray(xd, yd, fisheye, c, max_iter):  # pragma: no cover
    """Distorted normalised ``(xd, yd)`` -> the unit ray ``(a, b, c)`` (NaN: no ray), as
    :meth:`CameraModel.pixel_rays`."""
    if fisheye:
        td = math.sqrt(xd * xd + yd * yd)
        if td == 0.0:
            return 0.0, 0.0, 1.0
        th = fisheye_theta(td, c, max_iter)
        s = math.sin(th) / td
        return xd * s, yd * s, math.cos(th)
    x, y = brown_undistort(xd, yd, c, max_iter)
    nrm = math.sqrt(x * x + y * y + 1.0)
    return x / nrm, y / nrm, 1.0 / nrm


@njit(cache=True, error_model="numpy", nogil=True)
def _undistort_brown(xd, yd, c, max_iter, x, y):  # pragma: no cover
    for j in range(xd.shape[0]):
        x[j], y[j] = brown_undistort(xd[j], yd[j], c, max_iter)


@njit(cache=True, error_model="numpy", nogil=True)
def _fisheye_thetas(td, c, max_iter, out):  # pragma: no cover
    for j in range(td.shape[0]):
        out[j] = fisheye_theta(td[j], c, max_iter)


def _flat(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    return np.ascontiguousarray(np.broadcast_to(a, shape), dtype=np.float64).ravel()


def undistort_arrays(xd: np.ndarray, yd: np.ndarray, coeffs: np.ndarray, max_iter: int = lm.MAX_ITER
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`brown_undistort` on arrays of any (equal) shape; ``coeffs`` float64[13]
    (:func:`tofhil.lens_models.kernel_coeffs`)."""
    shape = np.broadcast_shapes(np.shape(xd), np.shape(yd))
    a, b = _flat(xd, shape), _flat(yd, shape)
    x, y = np.empty_like(a), np.empty_like(b)
    _undistort_brown(a, b, np.ascontiguousarray(coeffs, dtype=np.float64), int(max_iter), x, y)
    return x.reshape(shape), y.reshape(shape)


def fisheye_theta_arrays(td: np.ndarray, coeffs: np.ndarray, max_iter: int = lm.MAX_ITER) -> np.ndarray:
    """:func:`fisheye_theta` on an array of distorted radii."""
    shape = np.shape(td)
    a = _flat(td, shape)
    out = np.empty_like(a)
    _fisheye_thetas(a, np.ascontiguousarray(coeffs, dtype=np.float64), int(max_iter), out)
    return out.reshape(shape)


# (the loops above inline lens_models' arithmetic: their cache is dropped when it changes)
_drop_stale_cache(_undistort_brown, [lm.__file__])
