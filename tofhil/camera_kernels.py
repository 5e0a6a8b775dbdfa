"""Compiled inversion of the OpenCV lens distortion (numba), for :meth:`CameraModel.undistort_normalized`.

The renderer undistorts every subpixel sample and every re-fitted camera's pixel grid: 20
fixed-point iterations as numpy expressions are ~540 passes over arrays that do not fit in
the cache (the largest part of a 512 x 512 diagnosis). Here each block of points stays in
the L1 cache for all 20 iterations and the loop over the block vectorises. The arithmetic is
the numpy expression's, operation by operation (no fast-math: no reassociation, no fused
multiply-add), so the results are bit-identical to it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Points per block: x, y, xd, yd of a block (4 x 8 kB) stay in the L1 cache.
_BLOCK = 256


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def undistort_step(xd, yd, x, y, k1, k2, p1, p2, k3):  # pragma: no cover
    """One fixed-point step ``x = (xd - dx(x, y)) / radial(x, y)`` of one point, in the
    numpy expression's order (scalars only: inlined into the loops that call it)."""
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return (xd - dx) / radial, (yd - dy) / radial


@njit(cache=True, error_model="numpy", nogil=True)
def undistort(xd, yd, k1, k2, p1, p2, k3, iterations, x, y):  # pragma: no cover
    """Distorted normalised ``(xd, yd)`` (1-D float64) -> undistorted ``(x, y)``: the
    fixed-point iteration ``x = (xd - dx(x, y)) / radial(x, y)`` from ``x = xd``."""
    n = xd.shape[0]
    for b0 in range(0, n, _BLOCK):
        b1 = min(n, b0 + _BLOCK)
        for j in range(b0, b1):
            x[j] = xd[j]
            y[j] = yd[j]
        for _ in range(iterations):
            for j in range(b0, b1):
                x[j], y[j] = undistort_step(xd[j], yd[j], x[j], y[j], k1, k2, p1, p2, k3)


def undistort_arrays(xd: np.ndarray, yd: np.ndarray, dist: tuple[float, ...], iterations: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`undistort` on arrays of any (equal) shape."""
    shape = np.broadcast_shapes(np.shape(xd), np.shape(yd))
    a = np.ascontiguousarray(np.broadcast_to(xd, shape), dtype=np.float64).ravel()
    b = np.ascontiguousarray(np.broadcast_to(yd, shape), dtype=np.float64).ravel()
    x, y = np.empty_like(a), np.empty_like(b)
    k1, k2, p1, p2, k3 = (float(v) for v in dist)
    undistort(a, b, k1, k2, p1, p2, k3, iterations, x, y)
    return x.reshape(shape), y.reshape(shape)
