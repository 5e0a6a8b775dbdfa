"""The lens distortion models of :class:`tofhil.camera.CameraModel`, as OpenCV defines them.

* ``plumb_bob``: OpenCV's 5-parameter Brown-Conrady model ``(k1, k2, p1, p2, k3)``
  (``cv2.projectPoints`` with 5 coefficients; ROS ``plumb_bob``);
* ``rational``: OpenCV's rational model ``(k1, k2, p1, p2, k3, k4, k5, k6)``, optionally with
  the thin-prism terms ``(s1, s2, s3, s4)`` (12 coefficients; ``CALIB_RATIONAL_MODEL``,
  ``CALIB_THIN_PRISM_MODEL``; ROS ``rational_polynomial``);
* ``fisheye``: ``cv2.fisheye``'s equidistant (Kannala-Brandt) model ``(k1, k2, k3, k4)``:
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` with ``theta``
  the ray's angle to the optical axis and ``theta_d`` the distorted radius in normalised
  pixels (ROS ``equidistant``). Its field may reach 90 degrees and beyond.

Brown-Conrady, undistorted normalised ``(x, y)`` -> distorted ``(xd, yd)``, ``r^2 = x^2 + y^2``:

    g  = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
    xd = x g + 2 p1 x y + p2 (r^2 + 2 x^2) + s1 r^2 + s2 r^4
    yd = y g + p1 (r^2 + 2 y^2) + 2 p2 x y + s3 r^2 + s4 r^4

The arithmetic functions here take numbers or numpy arrays; :mod:`tofhil.camera_kernels`
compiles the same functions with numba (so the compiled and the numpy inversions are the same
operations) and adds the per-point loops. This module's arithmetic imports no numba (a camera
that undistorts a handful of points compiles nothing); only :func:`model_reach` of a distorted
model runs its grid scan compiled.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np

DistortionModel = Literal["plumb_bob", "rational", "fisheye"]

#: Coefficient names of each model in OpenCV's order; a model may allow several lengths.
COEFFICIENTS: dict[str, tuple[tuple[str, ...], ...]] = {
    "plumb_bob": (("k1", "k2", "p1", "p2", "k3"),),
    "rational": (("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
                 ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")),
    "fisheye": (("k1", "k2", "k3", "k4"),),
}
MODELS: tuple[str, ...] = tuple(COEFFICIENTS)
#: Other names of the same models (ROS ``sensor_msgs/CameraInfo.distortion_model``).
ALIASES: dict[str, str] = {"rational_polynomial": "rational", "equidistant": "fisheye"}

#: Newton iterations at most (converged points stop after 3 to 8).
MAX_ITER = 50
#: Step halvings at most per Newton iteration.
MAX_HALVINGS = 40
#: Relative step size at which Newton stops (the error left is then rounding).
STEP_TOL = 1e-14
#: Residual (normalised distorted coordinates) below which a step is accepted without the
#: descent test: rounding level, where the residual no longer decreases monotonically.
ROUNDING_RESIDUAL = 1e-13
#: Largest residual of a converged point (normalised coordinates: ~1e-7 px at f = 1000 px).
CONVERGED_RESIDUAL = 1e-10


def expected_dist(model: str) -> str:
    """What ``dist`` must hold for ``model`` (for error messages)."""
    lengths = COEFFICIENTS[model]
    count = " or ".join(str(len(n)) for n in lengths)
    names = ", ".join(lengths[0]) + ("".join(f"[, {', '.join(n[len(lengths[0]):])}]" for n in lengths[1:]))
    return f"{count} finite numbers ({names}) for model {model!r}"


#: Slot of :func:`kernel_coeffs` holding the reach of the model (see :func:`model_reach`).
REACH = 12


def kernel_coeffs(model: str, dist: tuple[float, ...]) -> np.ndarray:
    """The 13-slot vector the arithmetic below reads: the coefficients (missing terms zero)
    and, in slot :data:`REACH`, the model's reach (:func:`model_reach`)."""
    c = np.zeros(13)
    c[:len(dist)] = dist
    c[REACH] = model_reach(model, c)
    return c


def model_reach(model: str, c: np.ndarray) -> float:
    """Where the model stops being a lens: the first fold of its radial function, beyond which
    a larger angle no longer images farther out (a barrel ``k1 < 0`` turning back, a rational
    denominator's pole, a fisheye polynomial turning over). For Brown-Conrady the largest
    undistorted ``r^2`` of the first monotone branch of ``r g(r^2)``; for the fisheye the largest
    ``theta`` (at most pi) of ``theta_d(theta)``. Inverse solutions beyond it belong to another
    branch of the polynomial, not to the lens: the inversion refuses them (NaN), as the Azure
    Kinect SDK refuses pixels beyond its calibration's radius. inf / pi: the model never folds
    in the range searched (r up to 100, i.e. 89.4 degrees off axis).

    Found on a fine grid (:data:`REACH_GRID_BROWN`, :data:`REACH_GRID_FISHEYE`: the first point
    where the slope is not positive), then bisected to rounding. The scan runs compiled
    (:func:`tofhil.camera_kernels.first_fold`, the arithmetic below): a fit of the lens makes a
    new camera at every evaluation, and the scan in numpy was ~8 ms of each."""
    fisheye = model == "fisheye"
    if not fisheye and not any(c[[0, 1, 4, 5, 6, 7]]):
        return math.inf                               # radially a pinhole: no fold
    from tofhil.camera_kernels import first_fold

    grid = REACH_GRID_FISHEYE if fisheye else REACH_GRID_BROWN
    lo = first_fold(grid, np.ascontiguousarray(c, dtype=np.float64), fisheye)
    if math.isnan(lo):
        return math.pi if fisheye else math.inf
    return lo if fisheye else lo * lo


def brown_radial_slope(rr: Any, c: np.ndarray) -> Any:
    """``d(r g(r^2)) / dr = g + 2 r^2 g'`` of the Brown-Conrady radial function at one radius
    ``rr`` (-1 where the rational denominator is not positive: no lens there)."""
    r2 = rr * rr
    num = 1 + r2 * (c[0] + r2 * (c[1] + r2 * c[4]))
    den = 1 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
    dnum = c[0] + r2 * (2 * c[1] + r2 * 3 * c[4])
    dden = c[5] + r2 * (2 * c[6] + r2 * 3 * c[7])
    g = num / den
    return g + 2 * r2 * (dnum * den - num * dden) / (den * den) if den > 0 else -1.0


#: The radii (undistorted, normalised) on which :func:`model_reach` looks for a Brown-Conrady
#: fold: fine up to 10 (84 degrees), coarser to 100.
REACH_GRID_BROWN = np.concatenate([np.linspace(0.0, 10.0, 200001)[:-1], np.linspace(10.0, 100.0, 20001)])
#: The field angles on which :func:`model_reach` looks for a fisheye fold.
REACH_GRID_FISHEYE = np.linspace(0.0, math.pi, 200001)
for _g in (REACH_GRID_BROWN, REACH_GRID_FISHEYE):
    _g.setflags(write=False)


# --------------------------------------------------------------------------- arithmetic
# (numbers or arrays; compiled unchanged by tofhil.camera_kernels: keep the operation order)
def brown_distort(x: Any, y: Any, c: np.ndarray) -> tuple[Any, Any]:
    """Undistorted normalised ``(x, y)`` -> distorted (``cv2.projectPoints``' model)."""
    r2 = x * x + y * y
    num = 1 + r2 * (c[0] + r2 * (c[1] + r2 * c[4]))
    den = 1 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
    g = num / den
    xd = x * g + 2 * c[2] * x * y + c[3] * (r2 + 2 * x * x) + r2 * (c[8] + r2 * c[9])
    yd = y * g + c[2] * (r2 + 2 * y * y) + 2 * c[3] * x * y + r2 * (c[10] + r2 * c[11])
    return xd, yd


def radially_symmetric(c: np.ndarray) -> bool:
    """True for a Brown-Conrady model without tangential or thin-prism terms: it moves a point
    along its radius only, so its inversion is one radius's (:func:`brown_radius`)."""
    return c[2] == 0.0 and c[3] == 0.0 and c[8] == 0.0 and c[9] == 0.0 and c[10] == 0.0 and c[11] == 0.0


def brown_radius(r: Any, c: np.ndarray) -> tuple[Any, Any, Any]:
    """The radial function ``f = r g(r^2)`` of a radially symmetric Brown-Conrady model, its
    slope ``df/dr = g + 2 r^2 g'`` and ``g``. Without a denominator (k4 = k5 = k6 = 0) the
    divisions by it are left out: they are by exactly 1, so the results are the same bits."""
    r2 = r * r
    num = 1 + r2 * (c[0] + r2 * (c[1] + r2 * c[4]))
    dnum = c[0] + r2 * (2 * c[1] + r2 * 3 * c[4])
    if c[5] == 0.0 and c[6] == 0.0 and c[7] == 0.0:
        return r * num, num + 2 * r2 * dnum, num
    den = 1 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
    dden = c[5] + r2 * (2 * c[6] + r2 * 3 * c[7])
    g = num / den
    return r * g, g + 2 * r2 * ((dnum * den - num * dden) / (den * den)), g


def beyond_reach_sq(c: np.ndarray) -> float:
    """The squared distorted radius beyond which a radially symmetric Brown-Conrady model has
    no inverse within its reach (inf for a model with tangential or thin-prism terms, or one
    that never folds): ``r g(r^2)`` rises up to the reach, so a distorted point farther out
    than the reach's image has no root there, and the Newton search for one (every iteration
    and halving spent) is not run. The margin of 1e-9 leaves points within rounding of the
    boundary to the search."""
    # (radially_symmetric's test written out: numba compiles this function with its globals)
    if c[2] != 0.0 or c[3] != 0.0 or c[8] != 0.0 or c[9] != 0.0 or c[10] != 0.0 or c[11] != 0.0:
        return math.inf
    r2 = c[12]
    if not r2 < math.inf:
        return math.inf
    g = (1 + r2 * (c[0] + r2 * (c[1] + r2 * c[4]))) / (1 + r2 * (c[5] + r2 * (c[6] + r2 * c[7])))
    return r2 * g * g * (1.0 + 1e-9)


def brown_jacobian(x: Any, y: Any, c: np.ndarray) -> tuple[Any, Any, Any, Any]:
    """``d(xd, yd)/d(x, y)`` of :func:`brown_distort` as ``(j00, j01, j10, j11)``."""
    r2 = x * x + y * y
    num = 1 + r2 * (c[0] + r2 * (c[1] + r2 * c[4]))
    den = 1 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
    dnum = c[0] + r2 * (2 * c[1] + r2 * 3 * c[4])
    dden = c[5] + r2 * (2 * c[6] + r2 * 3 * c[7])
    g = num / den
    dg = (dnum * den - num * dden) / (den * den)       # dg / d(r^2)
    px = c[8] + 2 * c[9] * r2                          # d(prism x) / d(r^2)
    py = c[10] + 2 * c[11] * r2
    j00 = g + 2 * x * x * dg + 2 * c[2] * y + 6 * c[3] * x + 2 * x * px
    j01 = 2 * x * y * dg + 2 * c[2] * x + 2 * c[3] * y + 2 * y * px
    j10 = 2 * x * y * dg + 2 * c[2] * x + 2 * c[3] * y + 2 * x * py
    j11 = g + 2 * y * y * dg + 6 * c[2] * y + 2 * c[3] * x + 2 * y * py
    return j00, j01, j10, j11


def fisheye_theta_d(theta: Any, c: np.ndarray) -> tuple[Any, Any]:
    """``theta_d(theta)`` of ``cv2.fisheye`` and its derivative ``d theta_d / d theta``."""
    t2 = theta * theta
    poly = 1 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3])))
    dpoly = 1 + t2 * (3 * c[0] + t2 * (5 * c[1] + t2 * (7 * c[2] + t2 * 9 * c[3])))
    return theta * poly, dpoly


# --------------------------------------------------------------------------- inversion (numpy)
def brown_undistort(xd: np.ndarray, yd: np.ndarray, c: np.ndarray, max_iter: int = MAX_ITER
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised -> undistorted, Newton with step halving, every point to its own
    convergence; NaN where the model has no inverse (no convergence, or a root beyond the
    model's reach: :func:`model_reach`). Element by element the operations of
    :func:`tofhil.camera_kernels.brown_undistort` (bit-identical results). A radially
    symmetric model is inverted along each point's radius (:func:`brown_radius_undistort`)."""
    xd = np.asarray(xd, dtype=np.float64)
    yd = np.asarray(yd, dtype=np.float64)
    if radially_symmetric(c):
        return brown_radius_undistort(xd, yd, c, max_iter)
    with np.errstate(all="ignore"):
        x, y = xd.copy(), yd.copy()
        fx, fy = brown_distort(x, y, c)
        ex, ey = xd - fx, yd - fy
        r = np.abs(ex) + np.abs(ey)
        beyond = xd * xd + yd * yd > beyond_reach_sq(c)
        active = ~beyond
        for _ in range(max_iter):
            active &= r != 0.0
            if not active.any():
                break
            j00, j01, j10, j11 = brown_jacobian(x, y, c)
            det = j00 * j11 - j01 * j10
            active &= (det != 0.0) & np.isfinite(det)
            sx = (j11 * ex - j01 * ey) / det
            sy = (j00 * ey - j10 * ex) / det
            t = np.ones(x.shape)
            xn, yn, exn, eyn, rn = x, y, ex, ey, r
            pending = active.copy()
            for _h in range(MAX_HALVINGS):
                if not pending.any():
                    break
                xt = x + t * sx
                yt = y + t * sy
                fx, fy = brown_distort(xt, yt, c)
                ext, eyt = xd - fx, yd - fy
                rt = np.abs(ext) + np.abs(eyt)
                xn, yn = np.where(pending, xt, xn), np.where(pending, yt, yn)
                exn, eyn, rn = np.where(pending, ext, exn), np.where(pending, eyt, eyn), np.where(pending, rt, rn)
                pending &= ~((rt <= r) | (r < ROUNDING_RESIDUAL))
                t = np.where(pending, t * 0.5, t)
            x, y = np.where(active, xn, x), np.where(active, yn, y)
            ex, ey, r = np.where(active, exn, ex), np.where(active, eyn, ey), np.where(active, rn, r)
            active &= ~(t * (np.abs(sx) + np.abs(sy)) <= STEP_TOL * (1.0 + np.abs(x) + np.abs(y)))
        j00, j01, j10, j11 = brown_jacobian(x, y, c)
        ok = (r <= CONVERGED_RESIDUAL * (1.0 + np.abs(xd) + np.abs(yd))) & (j00 * j11 - j01 * j10 > 0.0) \
            & (x * x + y * y <= c[REACH]) & ~beyond
    return np.where(ok, x, np.nan), np.where(ok, y, np.nan)


def brown_radius_undistort(xd: np.ndarray, yd: np.ndarray, c: np.ndarray, max_iter: int = MAX_ITER
                           ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`brown_undistort` of a radially symmetric model (:func:`radially_symmetric`): the
    undistorted radius ``r`` with ``r g(r^2)`` the distorted one, Newton with step halving in
    one unknown (a third of the two-dimensional search's arithmetic), the point scaled along its
    radius. The same acceptance: the residual (in the two-dimensional search's units, the sum
    of both coordinates' errors), the Jacobian's determinant ``g df/dr`` positive, the root
    within the reach. Element by element the operations of
    :func:`tofhil.camera_kernels.brown_radius_undistort`."""
    with np.errstate(all="ignore"):
        rd2 = xd * xd + yd * yd
        rd = np.sqrt(rd2)
        r = rd.copy()
        f, df, g = brown_radius(r, c)
        e = rd - f
        a = np.abs(e)
        beyond = rd2 > beyond_reach_sq(c)
        active = ~beyond
        for _ in range(max_iter):
            active &= (a != 0.0) & (df != 0.0) & np.isfinite(df)
            if not active.any():
                break
            s = e / df
            t = np.ones(r.shape)
            rn, en, an, dfn, gn = r, e, a, df, g
            pending = active.copy()
            for _h in range(MAX_HALVINGS):
                if not pending.any():
                    break
                rt = r + t * s
                ft, dft, gt = brown_radius(rt, c)
                et = rd - ft
                at = np.abs(et)
                rn, en, an, dfn, gn = (np.where(pending, u, v) for u, v in
                                       ((rt, rn), (et, en), (at, an), (dft, dfn), (gt, gn)))
                pending &= ~((at <= a) | (a < ROUNDING_RESIDUAL))
                t = np.where(pending, t * 0.5, t)
            r, e, a, df, g = (np.where(active, u, v) for u, v in ((rn, r), (en, e), (an, a), (dfn, df), (gn, g)))
            active &= ~(t * np.abs(s) <= STEP_TOL * (1.0 + np.abs(r)))
        l1 = np.abs(xd) + np.abs(yd)
        ok = (a * l1 <= CONVERGED_RESIDUAL * (1.0 + l1) * rd) & (g * df > 0.0) & (r * r <= c[REACH]) & ~beyond
        k = r / rd
        x, y = xd * k, yd * k
    axis = rd2 == 0.0
    return np.where(axis, xd, np.where(ok, x, np.nan)), np.where(axis, yd, np.where(ok, y, np.nan))


def fisheye_theta(td: np.ndarray, c: np.ndarray, max_iter: int = MAX_ITER) -> np.ndarray:
    """Distorted radius ``theta_d`` -> field angle ``theta`` in ``[0, pi]``, Newton with step
    halving (as :func:`tofhil.camera_kernels.fisheye_theta`); NaN where ``theta_d`` lies
    beyond the largest the model reaches."""
    td = np.asarray(td, dtype=np.float64)
    with np.errstate(all="ignore"):
        th = np.minimum(td, math.pi)
        f, df = fisheye_theta_d(th, c)
        e = td - f
        r = np.abs(e)
        active = np.ones(td.shape, bool)
        for _ in range(max_iter):
            active &= (r != 0.0) & (df > 0.0) & np.isfinite(df)
            if not active.any():
                break
            s = e / df
            t = np.ones(td.shape)
            thn, en, rn, dfn = th, e, r, df
            pending = active.copy()
            for _h in range(MAX_HALVINGS):
                if not pending.any():
                    break
                tht = np.minimum(np.maximum(th + t * s, 0.0), math.pi)
                ft, dft = fisheye_theta_d(tht, c)
                et = td - ft
                rt = np.abs(et)
                thn, en, rn, dfn = (np.where(pending, a, b) for a, b in ((tht, thn), (et, en), (rt, rn), (dft, dfn)))
                pending &= ~((rt <= r) | (r < ROUNDING_RESIDUAL))
                t = np.where(pending, t * 0.5, t)
            step = np.abs(thn - th)
            th, e, r, df = (np.where(active, a, b) for a, b in ((thn, th), (en, e), (rn, r), (dfn, df)))
            active &= ~(step <= STEP_TOL * (1.0 + th))
        _, df = fisheye_theta_d(th, c)
        ok = (r <= CONVERGED_RESIDUAL * (1.0 + td)) & (df > 0.0) & (th <= c[REACH])
    return np.where(td == 0.0, 0.0, np.where(ok, th, np.nan))
