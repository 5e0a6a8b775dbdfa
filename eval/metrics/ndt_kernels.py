"""The compiled per-point loop of :mod:`tofhil.eval.metrics.ndt` (numba).

A module of its own so that importing :mod:`tofhil.eval.metrics.ndt` does not import numba (about
0.3 CPU-s, and as much again to load the cached kernel): ``tofhil ndt --score
score_per_point`` computes PCL's score with numpy alone (:func:`tofhil.eval.metrics.ndt.pcl_score`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _point_terms_block(p, i0, i1, cell_size, table, lo_span, means_t, icov6_t, d1, d2,
                       lik, tri, total, best, has):  # pragma: no cover
    """:func:`_all_point_terms` with the dense table for points ``i0:i1``, one point at a
    time: the same 27 neighbours in the same order, the same arithmetic in the same order
    (so the same numbers), without the [N]-sized temporaries of every offset."""
    lo0, lo1, lo2 = lo_span[0], lo_span[1], lo_span[2]
    s0, s1, s2 = lo_span[3], lo_span[4], lo_span[5]
    r2 = cell_size ** 2
    gp = np.empty((3, 3))      # [offset + 1, axis] squared gap to the neighbour cell
    tw = np.empty((3, 3))      # [offset + 1, axis] trilinear weight of the neighbour
    for i in range(i0, i1):
        lik[i] = 0.0
        tri[i] = 0.0
        total[i] = 0.0
        best[i] = 0.0
        has[i] = False
        b0 = math.floor(p[i, 0] / cell_size)
        b1 = math.floor(p[i, 1] / cell_size)
        b2 = math.floor(p[i, 2] / cell_size)
        r0, r1_, r2_ = int(b0) - lo0, int(b1) - lo1, int(b2) - lo2
        if not (r0 >= 1 and r0 <= s0 - 2 and r1_ >= 1 and r1_ <= s1 - 2 and r2_ >= 1 and r2_ <= s2 - 2):
            continue                     # outside the table's margin: no occupied neighbour
        lin = (r0 * s1 + r1_) * s2 + r2_
        for a in range(3):
            f = p[i, a] / cell_size - (b0 if a == 0 else (b1 if a == 1 else b2))
            gp[0, a] = f * f
            gp[1, a] = 0.0
            gp[2, a] = (1.0 - f) ** 2
            tw[0, a] = max(0.5 - f, 0.0)
            tw[1, a] = 1.0 - abs(f - 0.5)
            tw[2, a] = max(f - 0.5, 0.0)
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        for ox in range(-1, 2):
            for oy in range(-1, 2):
                for oz in range(-1, 2):
                    c = table[lin + (ox * s1 + oy) * s2 + oz]
                    if c < 0:
                        continue
                    nz = (ox != 0) + (oy != 0) + (oz != 0)
                    if nz > 1 and not (gp[ox + 1, 0] + gp[oy + 1, 1] + gp[oz + 1, 2]) <= 1.0:
                        continue
                    dx = x - means_t[0, c]
                    dy = y - means_t[1, c]
                    dz = z - means_t[2, c]
                    dist2 = dx * dx + dy * dy + dz * dz
                    t = icov6_t[0, c] * dx
                    t += icov6_t[3, c] * dy
                    t += icov6_t[4, c] * dz
                    t *= dx
                    u = icov6_t[1, c] * dy
                    u += icov6_t[5, c] * dz
                    u *= dy
                    t += u
                    u = icov6_t[2, c] * dz
                    u *= dz
                    m = t + u
                    g = math.exp(-0.5 * m)
                    if nz == 0:
                        lik[i] = g
                    w = tw[ox + 1, 0] * tw[oy + 1, 1] * tw[oz + 1, 2]
                    tri[i] += w * g
                    if dist2 <= r2:
                        e = math.exp(-0.5 * d2 * m)
                        term = -d1 * e if (d2 * e <= 1.0 and d2 * e >= 0.0) else 0.0
                        total[i] += term
                        best[i] = max(best[i], term)
                        has[i] = True
