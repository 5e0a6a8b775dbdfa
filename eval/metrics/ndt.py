"""3D Normal Distributions Transform (NDT) scores of a cloud against a reference cloud.

The reference cloud is summarised by an NDT grid (Magnusson 2009): space is cut into
cubes of side ``cell_size`` anchored at the origin (cell ``floor(p / cell_size)``, as PCL's
``VoxelGridCovariance``); every cell with at least ``min_points`` points holds the mean and
the unbiased covariance of its points, regularised by flooring its eigenvalues at
``eig_floor`` times the largest (PCL: 0.01, Magnusson eq. 6.11).

Scores of a cloud ``X`` against that grid (all vectorised, no per-point Python loop):

- ``score_per_point`` -- PCL's ``NormalDistributionsTransform`` score at identity divided
  by the number of points (``getTransformationLikelihood()``): every point adds
  ``-d1 * exp(-d2/2 * q^T C^-1 q)`` for every cell whose *mean* lies within ``cell_size`` of
  it (PCL's radius search on the cell centroids), ``d1, d2`` from the outlier ratio (eq. 6.8).
- ``nvtl`` -- Autoware's nearest-voxel transformation likelihood (pclomp ``ndt_omp``): per
  point the largest of those terms, averaged over the points that have a neighbouring cell.
- ``likelihood`` -- ``exp(-q^T C^-1 q / 2)`` from the cell containing the point (0 if that
  cell has no distribution) and ``likelihood_trilinear`` -- the sum over the 8 cells whose
  centres surround the point of the trilinear weight times that cell's likelihood
  (Magnusson's and Stoyanov et al.'s interpolated NDT).
- ``fraction_above[t]`` -- the fraction of points whose trilinear likelihood exceeds ``t``.
- :func:`d2d_score` -- Stoyanov et al.'s distribution-to-distribution score between grids.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np

from tofhil.errors import TofhilError

# Cell keys pack (i, j, k) into one int64: 21 bits per axis, offset so negatives fit.
_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_KEY_LIMIT = _KEY_OFFSET - 2          # |index| must stay below this (one cell of margin)
_DENSE_MAX_CELLS = 1 << 25            # dense lookup table up to 32M entries (128 MB int32)
_POINT_BLOCK = 32768                  # points per thread task of the compiled scoring loop
_SCORE_BLOCK = 16384                  # points per block of pcl_score (its temporaries stay in L2)

DEFAULT_THRESHOLDS: tuple[float, ...] = (0.1, 0.5, 0.9)

_OFFSETS27 = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                      dtype=np.int64)
_CORNERS8 = np.array([(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)


def _as_points(points: Any, name: str = "points") -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise TofhilError(f"has shape {p.shape}", field=name, expected="an N x 3 array of points")
    if p.size and math.isfinite(p.min()) and math.isfinite(p.max()):   # no NaN, no inf: 2 passes
        return p
    return p[np.all(np.isfinite(p), axis=1)]


def _pack(ijk: np.ndarray) -> np.ndarray:
    """Integer cell indices [N, 3] -> int64 keys (order-preserving per axis)."""
    u = ijk + _KEY_OFFSET
    return (u[:, 0] << (2 * _KEY_BITS)) | (u[:, 1] << _KEY_BITS) | u[:, 2]


def gauss_params(cell_size: float, outlier_ratio: float = 0.55) -> tuple[float, float]:
    """PCL's Gaussian fitting constants ``(d1, d2)`` (Magnusson 2009, eq. 6.8).

    The mixture of a normal density and a uniform outlier density ``outlier_ratio /
    cell_size**3`` is approximated by ``-d1 * exp(-d2/2 * m)`` with ``m`` the squared
    Mahalanobis distance; ``d1 < 0``.
    """
    if not 0.0 < outlier_ratio < 1.0:
        raise TofhilError(f"is {outlier_ratio}", field="outlier_ratio", expected="a value in (0, 1)")
    c1 = 10.0 * (1.0 - outlier_ratio)
    c2 = outlier_ratio / cell_size ** 3
    d3 = -math.log(c2)
    d1 = -math.log(c1 + c2) - d3
    d2 = -2.0 * math.log((-math.log(c1 * math.exp(-0.5) + c2) - d3) / d1)
    return d1, d2


@dataclass(frozen=True)
class NDTGrid:
    """The NDT of a reference cloud: per occupied cell a mean and a regularised covariance.

    Only cells with at least ``min_points`` points and a positive largest covariance
    eigenvalue are kept. Arrays are indexed by cell number ``0..cells-1``.
    """

    cell_size: float
    min_points: int
    eig_floor: float
    ijk: np.ndarray          # [M, 3] int64 cell indices, cell = floor(p / cell_size)
    counts: np.ndarray       # [M] points per cell
    means: np.ndarray        # [M, 3]
    covs: np.ndarray         # [M, 3, 3] regularised covariances
    icovs: np.ndarray        # [M, 3, 3] their inverses
    _keys: np.ndarray = field(repr=False)      # [M] sorted packed keys
    _order: np.ndarray = field(repr=False)     # cell number of each sorted key
    _table: np.ndarray | None = field(repr=False, default=None)   # flat dense lookup table or None
    _lo_span: np.ndarray | None = field(repr=False, default=None)  # table origin and extent [6]
    _icov6_t: np.ndarray | None = field(repr=False, default=None)  # [6, M] xx yy zz 2xy 2xz 2yz
    _means_t: np.ndarray | None = field(repr=False, default=None)  # [3, M]

    @property
    def cells(self) -> int:
        return int(self.counts.size)

    @classmethod
    def from_points(cls, points: Any, cell_size: float, min_points: int = 6,
                    eig_floor: float = 0.01) -> "NDTGrid":
        """Build the grid of ``points`` ([N, 3], metres) with cubic cells of ``cell_size``.

        ``min_points`` >= 3 (PCL's default 6); eigenvalues below ``eig_floor`` times the
        largest are raised to it (PCL: 0.01).
        """
        if not (cell_size > 0 and math.isfinite(cell_size)):
            raise TofhilError(f"is {cell_size}", field="cell_size", expected="a positive length in metres")
        if min_points < 3:
            raise TofhilError(f"is {min_points}", field="min_points", expected="at least 3 (a covariance needs 3 points)")
        if not 0.0 <= eig_floor <= 1.0:
            raise TofhilError(f"is {eig_floor}", field="eig_floor", expected="a fraction in [0, 1]")
        # Column by column: numpy's reductions and broadcasts along a 3-wide axis of an [N, 3]
        # array run 10-40x slower than on contiguous columns (ijk.min(0): 20 ms at 300k).
        cols = _columns(_as_points(points))
        ijk = [np.floor(c / cell_size).astype(np.int64) for c in cols]
        if cols[0].size and max(max(-v.min(), v.max()) for v in ijk) >= _KEY_LIMIT:
            raise TofhilError(f"cloud spans more than {_KEY_LIMIT} cells of {cell_size} m from the origin",
                              field="cell_size", expected="a larger cell size or a cloud nearer the origin")
        keys, inverse, counts = _occupied_cells(ijk)
        keep = counts >= min_points
        # Two-pass covariance in cell-local coordinates (better conditioned than PCL's single
        # pass; identical in exact arithmetic).
        n = counts.astype(np.float64)
        mcols = [np.bincount(inverse, c, minlength=keys.size) / n for c in cols]
        means = np.stack(mcols, 1)
        d = [c - m.take(inverse) for c, m in zip(cols, mcols)]
        cov = np.empty((keys.size, 3, 3))
        for a in range(3):
            for b in range(a, 3):
                s = np.bincount(inverse, d[a] * d[b], minlength=keys.size)
                cov[:, a, b] = cov[:, b, a] = s / np.maximum(n - 1.0, 1.0)
        keys, counts, means, cov = keys[keep], counts[keep], means[keep], cov[keep]
        evals, evecs = np.linalg.eigh(cov) if keys.size else (np.zeros((0, 3)), np.zeros((0, 3, 3)))
        lmax = evals[:, 2] if keys.size else np.zeros(0)
        ok = lmax > 0
        evals, evecs, lmax = evals[ok], evecs[ok], lmax[ok]
        keys, counts, means = keys[ok], counts[ok], means[ok]
        evals = np.maximum(evals, eig_floor * lmax[:, None])
        covs = np.einsum("mij,mj,mkj->mik", evecs, evals, evecs)
        icovs = np.einsum("mij,mj,mkj->mik", evecs, 1.0 / evals, evecs)
        cell_ijk = _unpack(keys)
        order = np.arange(keys.size)
        table = lo_span = None
        if keys.size:
            # Dense lookup table with a margin of 2 empty cells: a query cell whose
            # neighbourhood leaves the table has no occupied neighbour at all.
            lo = cell_ijk.min(0) - 2
            span = cell_ijk.max(0) + 3 - lo
            if int(np.prod(span.astype(np.float64))) <= _DENSE_MAX_CELLS:
                table = np.full(int(np.prod(span)), -1, dtype=np.int32)
                table[_linear(cell_ijk - lo, span)] = order
                lo_span = np.concatenate([lo, span])
        icov6 = icovs[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]] * np.array([1, 1, 1, 2, 2, 2.0])
        return cls(float(cell_size), int(min_points), float(eig_floor), cell_ijk, counts, means, covs, icovs,
                   keys, order, table, lo_span, np.ascontiguousarray(icov6.T), np.ascontiguousarray(means.T))

    def lookup(self, ijk: np.ndarray) -> np.ndarray:
        """Cell numbers of integer cell indices ``[N, 3]``; -1 where no distribution."""
        return _Neighbours(self, np.asarray(ijk, dtype=np.int64)).at(np.zeros(3, dtype=np.int64))

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """Integer cell index ``floor(p / cell_size)`` of each point."""
        return np.floor(np.asarray(points, dtype=np.float64) / self.cell_size).astype(np.int64)


def _occupied_cells(ijk: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(_pack(ijk), return_inverse=True, return_counts=True)`` for the three
    columns of cell indices: the sorted keys of the occupied cells, each point's cell number
    and the counts. Where the bounding box of the cells is small (at most 4 cells per point)
    by counting over its linear index, in the same order (both are lexicographic in i, j, k)
    without sorting the points."""
    n = ijk[0].size
    if n:
        lo = [int(v.min()) for v in ijk]
        span = [int(v.max()) - a + 1 for v, a in zip(ijk, lo)]
        size = float(span[0]) * span[1] * span[2]
        if size <= max(4.0 * n, 1 << 16):
            lin = ijk[0] - lo[0]
            lin *= span[1]
            lin += ijk[1]
            lin -= lo[1]
            lin *= span[2]
            lin += ijk[2]
            lin -= lo[2]
            per_cell = np.bincount(lin, minlength=int(size))
            occupied = np.flatnonzero(per_cell)
            number = np.empty(per_cell.size, np.int64)
            number[occupied] = np.arange(occupied.size)
            rel = np.stack(np.unravel_index(occupied, tuple(span)), 1)
            return _pack(rel + np.array(lo)), number.take(lin), per_cell[occupied]
    return np.unique(_pack(np.stack(ijk, 1)), return_inverse=True, return_counts=True)


def _linear(rel: np.ndarray, span: np.ndarray) -> np.ndarray:
    return (rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2]


class _Neighbours:
    """Cell numbers of ``base + offset`` for a batch of base cells, offset by offset.

    With the dense table the base positions are computed once and each offset is one
    ``take``; otherwise packed keys are found with ``searchsorted``.
    """

    def __init__(self, grid: NDTGrid, base: np.ndarray) -> None:
        self.grid = grid
        self.base = base
        if grid._table is not None:
            lo, span = grid._lo_span[:3], grid._lo_span[3:]
            rel = base - lo
            self.ok = np.all((rel >= 1) & (rel <= span - 2), axis=1)
            self.lin = np.where(self.ok, _linear(rel, span), 0)   # table[0] is margin: -1
            self.span = span

    def at(self, off: np.ndarray) -> np.ndarray:
        g = self.grid
        n = self.base.shape[0]
        if g.cells == 0:
            return np.full(n, -1, dtype=np.int64)
        if g._table is not None:
            step = int((off[0] * self.span[1] + off[1]) * self.span[2] + off[2])
            return g._table[np.where(self.ok, self.lin + step, 0)]
        ijk = self.base + off
        out = np.full(n, -1, dtype=np.int64)
        inside = np.all(np.abs(ijk) < _KEY_LIMIT + 1, axis=1)
        k = _pack(ijk[inside])
        pos = np.minimum(np.searchsorted(g._keys, k), g._keys.size - 1)
        hit = g._keys[pos] == k
        res = np.full(k.size, -1, dtype=np.int64)
        res[hit] = g._order[pos[hit]]
        out[inside] = res
        return out


def _unpack(keys: np.ndarray) -> np.ndarray:
    mask = (1 << _KEY_BITS) - 1
    return np.stack([(keys >> (2 * _KEY_BITS)) & mask, (keys >> _KEY_BITS) & mask, keys & mask], 1) - _KEY_OFFSET


def _deltas(grid: NDTGrid, xyz: tuple[np.ndarray, np.ndarray, np.ndarray], cells: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``q = p - mean`` per coordinate for matched (point, cell) rows."""
    m = grid._means_t
    return xyz[0] - np.take(m[0], cells), xyz[1] - np.take(m[1], cells), xyz[2] - np.take(m[2], cells)


def _quad_d(grid: NDTGrid, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """``q^T C^-1 q`` from the packed inverse-covariance terms, factored as
    ``dx (a0 dx + a3 dy + a4 dz) + dy (a1 dy + a5 dz) + a2 dz^2``.

    Every gather is a 1-D ``np.take`` from a contiguous row (about 3x faster than fancy
    indexing [n, 3, 3] or [:, cells] arrays).
    """
    a = grid._icov6_t
    t = np.take(a[0], cells) * dx
    t += np.take(a[3], cells) * dy
    t += np.take(a[4], cells) * dz
    t *= dx
    u = np.take(a[1], cells) * dy
    u += np.take(a[5], cells) * dz
    u *= dy
    t += u
    u = np.take(a[2], cells) * dz
    u *= dz
    t += u
    return t


def _quad(grid: NDTGrid, xyz: tuple[np.ndarray, np.ndarray, np.ndarray], cells: np.ndarray
          ) -> np.ndarray:
    """``q^T C^-1 q`` with ``q = p - mean`` for matched (point, cell) rows."""
    return _quad_d(grid, *_deltas(grid, xyz, cells), cells)


def _columns(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]), np.ascontiguousarray(p[:, 2])


def _take(cols: tuple[np.ndarray, np.ndarray, np.ndarray], sel: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.take(cols[0], sel), np.take(cols[1], sel), np.take(cols[2], sel)


def cell_likelihood(grid: NDTGrid, points: np.ndarray) -> np.ndarray:
    """``exp(-q^T C^-1 q / 2)`` from the cell containing each point (0 where it has none)."""
    p = _as_points(points)
    cells = grid.lookup(grid.cell_of(p))
    out = np.zeros(p.shape[0])
    sel = np.flatnonzero(cells >= 0)
    out[sel] = np.exp(-0.5 * _quad(grid, _take(_columns(p), sel), cells[sel]))
    return out


def trilinear_weights(points: np.ndarray, cell_size: float) -> tuple[np.ndarray, np.ndarray]:
    """The 8 cells whose centres surround each point and their trilinear weights.

    Returns ``(ijk [N, 8, 3], weights [N, 8])``; the weights of a point sum to 1, a point at
    a cell centre gives that cell weight 1, a point halfway between two centres 0.5 each.
    """
    base, f = _trilinear_base(np.asarray(points, dtype=np.float64), cell_size)
    ijk = base[:, None, :] + _CORNERS8[None, :, :]
    w = np.stack([_corner_weight(f, c) for c in _CORNERS8], axis=1)
    return ijk, w


def _trilinear_base(p: np.ndarray, cell_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Lowest of the 8 surrounding cells and the fractional position between centres."""
    u = p / cell_size - 0.5          # in units of centre spacing, centres at integers
    base = np.floor(u)
    return base.astype(np.int64), u - base


def _corner_weight(f: np.ndarray, corner: np.ndarray) -> np.ndarray:
    w = f[:, 0] if corner[0] else 1.0 - f[:, 0]
    w = w * (f[:, 1] if corner[1] else 1.0 - f[:, 1])
    return w * (f[:, 2] if corner[2] else 1.0 - f[:, 2])


def trilinear_likelihood(grid: NDTGrid, points: np.ndarray) -> np.ndarray:
    """Trilinearly interpolated NDT likelihood: ``sum_k w_k exp(-q_k^T C_k^-1 q_k / 2)``.

    Each of the 8 cells whose centres surround the point evaluates its own Gaussian at the
    point, weighted by the trilinear weight of the point relative to those centres; cells
    without a distribution contribute 0.
    """
    p = _as_points(points)
    base, f = _trilinear_base(p, grid.cell_size)
    cols = _columns(p)
    out = np.zeros(p.shape[0])
    nb = _Neighbours(grid, base)
    for corner in _CORNERS8:
        cells = nb.at(corner)
        sel = np.flatnonzero(cells >= 0)
        if sel.size == 0:
            continue
        w = _corner_weight(f[sel], corner)
        out[sel] += w * np.exp(-0.5 * _quad(grid, _take(cols, sel), cells[sel]))
    return out


def pcl_point_scores(grid: NDTGrid, points: np.ndarray, outlier_ratio: float = 0.55
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCL's per-point NDT score terms at the identity transform.

    For every point, every cell whose mean lies within ``cell_size`` of it (PCL's
    ``radiusSearch`` on the centroid cloud) adds ``-d1 * exp(-d2/2 * q^T C^-1 q)``; like
    PCL's ``updateDerivatives``, a term with ``d2 * exp(...)`` outside [0, 1] adds 0.
    Such means lie in the 27 cells around the point's cell, so only those are checked.

    Returns ``(sum_score [N], nearest_score [N], has_neighbour [N])``: the sum (PCL's
    score), the largest term (Autoware's nearest-voxel score) and whether any cell mean is
    within the radius. Computed by the vectorised 27-offset pass (:func:`_all_point_terms`),
    the one numpy definition of the terms that the compiled loop is tested against.
    """
    return _all_point_terms(grid, _as_points(points), outlier_ratio)[2:]


def pcl_score(grid: NDTGrid, points: Any, outlier_ratio: float = 0.55) -> float:
    """PCL's score per point alone (``NDTScore.score_per_point``, the same sum), with numpy
    only: no numba import or kernel load (~0.6 CPU-s of a short process), no per-point
    arrays, none of the other scores.

    The neighbourhood is PCL's radius search (the cells whose *mean* lies within
    ``cell_size`` of the point), found among the 27 cells around the point: a cell's mean
    lies in its own cell, so no other cell can hold one; edge and corner cells whose box is
    farther than the radius are skipped before any distance is computed. Points are taken in
    blocks so that every temporary stays in the CPU cache. Non-finite points are ignored.
    """
    p = _as_points(points)
    n = p.shape[0]
    if n == 0 or grid.cells == 0:
        return 0.0
    d1, d2 = gauss_params(grid.cell_size, outlier_ratio)
    total = 0.0
    for a in range(0, n, _SCORE_BLOCK):
        total += _pcl_block_sum(grid, p[a:a + _SCORE_BLOCK], d1, d2)
    return total / n


def _pcl_block_sum(grid: NDTGrid, p: np.ndarray, d1: float, d2: float) -> float:
    """Sum of PCL's terms ``-d1 exp(-d2/2 q^T C^-1 q)`` over the points of ``p`` and their
    cells within the radius (a term with ``d2 exp(.)`` outside [0, 1] counts 0, as PCL).

    With the dense table, the neighbour at each offset is one gather from the table shifted
    by that offset (a view: no index arithmetic per point); every other step is a gather or
    an in-place update of the candidates (about 16 per point in a room scan, 6 within the
    radius)."""
    x, y, z = _columns(p)
    u = [c / grid.cell_size for c in (x, y, z)]
    base = [np.floor(c) for c in u]
    f = [a - b for a, b in zip(u, base)]                        # position inside the cell, [0, 1)
    base = [b.astype(np.int64) for b in base]
    dense = grid._table is not None
    if dense:
        # Columns, not [N, 3] arrays: see NDTGrid.from_points.
        lo, span = [int(v) for v in grid._lo_span[:3]], [int(v) for v in grid._lo_span[3:]]
        rel = [b - a for b, a in zip(base, lo)]
        inside = (rel[0] >= 1) & (rel[0] <= span[0] - 2)
        for a in (1, 2):
            inside &= (rel[a] >= 1) & (rel[a] <= span[a] - 2)    # else no neighbour at all
        if not inside.all():
            keep = np.flatnonzero(inside)
            x, y, z = x[keep], y[keep], z[keep]
            f = [v[keep] for v in f]
            rel = [v[keep] for v in rel]
        s1, s2 = span[1], span[2]
        shift = s1 * s2 + s2 + 1                                  # minus the lowest offset's step
        lin = (rel[0] * s1 + rel[1]) * s2 + rel[2] - shift        # >= 0 inside the margin
    else:
        nb = _Neighbours(grid, np.stack(base, 1))
    below, above = [v * v for v in f], [(1.0 - v) ** 2 for v in f]   # squared box gaps, cell units
    mx, my, mz = grid._means_t
    a0, a1, a2, a3, a4, a5 = grid._icov6_t
    r2 = grid.cell_size ** 2
    total = 0.0
    for off in _OFFSETS27:
        if dense:
            cells = grid._table[int((off[0] * s1 + off[1]) * s2 + off[2]) + shift:].take(lin)
        else:
            cells = nb.at(off)
        gaps = [below[a] if off[a] < 0 else above[a] for a in range(3) if off[a]]
        if len(gaps) > 1:      # edge and corner cells: is their box within the radius at all?
            g = gaps[0] + gaps[1]
            if len(gaps) == 3:
                g += gaps[2]
            sel = np.flatnonzero((cells >= 0) & (g <= 1.0))
        else:
            sel = np.flatnonzero(cells >= 0)
        if sel.size == 0:
            continue
        c = cells.take(sel).astype(np.intp)     # take() with int32 indices is ~7x slower
        dx = x.take(sel)
        dx -= mx.take(c)
        dy = y.take(sel)
        dy -= my.take(c)
        dz = z.take(sel)
        dz -= mz.take(c)
        dd = dx * dx
        dd += dy * dy
        dd += dz * dz
        near = np.flatnonzero(dd <= r2)
        c, dx, dy, dz = c.take(near), dx.take(near), dy.take(near), dz.take(near)
        # q^T C^-1 q factored as in _quad_d
        m = a0.take(c) * dx
        m += a3.take(c) * dy
        m += a4.take(c) * dz
        m *= dx
        t = a1.take(c) * dy
        t += a5.take(c) * dz
        t *= dy
        m += t
        t = a2.take(c) * dz
        t *= dz
        m += t
        m *= -0.5 * d2
        e = np.exp(m, out=m)
        de = d2 * e
        total += float(-d1 * e[(de <= 1.0) & (de >= 0.0)].sum())
    return total


def _all_point_terms(grid: NDTGrid, p: np.ndarray, outlier_ratio: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One pass over the 27 cells around each point for every per-point quantity.

    The containing cell is offset (0, 0, 0) and the 8 trilinear cells are among the 27
    neighbours, so each (point, cell) Mahalanobis distance is computed once and feeds the
    PCL term (mean within the radius), the containing-cell likelihood and the trilinear
    sum. Equal to :func:`cell_likelihood`, :func:`trilinear_likelihood` and
    :func:`pcl_point_scores` (tested).
    """
    d1, d2 = gauss_params(grid.cell_size, outlier_ratio)
    r2 = grid.cell_size ** 2
    n = p.shape[0]
    base = grid.cell_of(p)
    frac = _columns(p / grid.cell_size - base)       # position inside the cell, [0, 1)
    # Squared gap (cell units) from the point to the lower / upper neighbour cell on each
    # axis: a neighbour whose box is farther than the radius cannot hold a mean within it.
    zero = np.zeros(n)
    gap = {-1: [f * f for f in frac], 0: [zero] * 3, 1: [(1.0 - f) ** 2 for f in frac]}
    # Per-axis trilinear weight of the neighbour at offset -1 / 0 / +1: the two cell
    # centres bracketing the point are (c-1, c) below the cell's centre, (c, c+1) above.
    tw = {-1: [np.maximum(0.5 - f, 0.0) for f in frac], 0: [1.0 - np.abs(f - 0.5) for f in frac],
          1: [np.maximum(f - 0.5, 0.0) for f in frac]}
    lik, tri, total, best = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    has = np.zeros(n, dtype=bool)
    nb = _Neighbours(grid, base)
    cols = _columns(p)
    for off in _OFFSETS27:
        cells = nb.at(off)
        reach = cells >= 0
        if np.count_nonzero(off) > 1:
            reach &= (gap[off[0]][0] + gap[off[1]][1] + gap[off[2]][2]) <= 1.0
        sel = np.flatnonzero(reach)
        if sel.size == 0:
            continue
        c = np.take(cells, sel)
        dx, dy, dz = _deltas(grid, _take(cols, sel), c)
        dist2 = dx * dx + dy * dy + dz * dz
        m = _quad_d(grid, dx, dy, dz, c)
        g = np.exp(-0.5 * m)
        if not off.any():
            lik[sel] = g
        w = np.take(tw[off[0]][0], sel) * np.take(tw[off[1]][1], sel) * np.take(tw[off[2]][2], sel)
        tri[sel] += w * g
        near = dist2 <= r2
        sn = sel[near]
        e = np.exp(-0.5 * d2 * m[near])
        term = np.where((d2 * e <= 1.0) & (d2 * e >= 0.0), -d1 * e, 0.0)
        total[sn] += term
        best[sn] = np.maximum(best[sn], term)
        has[sn] = True
    return lik, tri, total, best, has


def _point_terms(grid: NDTGrid, p: np.ndarray, outlier_ratio: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The per-point terms: the compiled loop where the grid has a dense table, else the
    vectorised :func:`_all_point_terms`."""
    if grid._table is None or grid.cells == 0:
        return _all_point_terms(grid, p, outlier_ratio)
    from tofhil.eval.metrics.ndt_kernels import _point_terms_block   # numba: imported only here

    d1, d2 = gauss_params(grid.cell_size, outlier_ratio)
    n = p.shape[0]
    lik, tri, total, best = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    has = np.empty(n, dtype=np.bool_)
    pts = np.ascontiguousarray(p, dtype=np.float64)
    lo_span = grid._lo_span.astype(np.int64)

    def run(i0: int, i1: int) -> None:
        _point_terms_block(pts, i0, i1, float(grid.cell_size), grid._table, lo_span, grid._means_t,
                           grid._icov6_t, d1, d2, lik, tri, total, best, has)

    # Disjoint point ranges on both cores (the loop releases the GIL; Python threads, not
    # numba's parallel layer, so concurrent callers are safe).
    spans = [(a, min(n, a + _POINT_BLOCK)) for a in range(0, n, _POINT_BLOCK)]
    if len(spans) <= 1:
        run(0, n)
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(2, os.cpu_count() or 1)) as pool:
            list(pool.map(lambda ab: run(*ab), spans))
    return lik, tri, total, best, has


@dataclass
class NDTScore:
    """NDT scores of a cloud against a reference grid (see the module docstring)."""

    score_per_point: float
    nvtl: float
    mean_likelihood: float
    mean_likelihood_trilinear: float
    fraction_above: dict[float, float]
    cells: int
    n_points: int
    cell_size: float
    outlier_ratio: float
    d1: float
    d2: float
    likelihood: np.ndarray = field(repr=False)            # [N] containing-cell likelihood
    likelihood_trilinear: np.ndarray = field(repr=False)  # [N] trilinear likelihood
    point_score: np.ndarray = field(repr=False)           # [N] PCL per-point score (sum over neighbours)
    nearest_score: np.ndarray = field(repr=False)         # [N] Autoware per-point nearest-voxel score

    def to_dict(self) -> dict[str, Any]:
        """The scalar scores as a JSON-ready dict (the ``tofhil ndt --json`` keys first)."""
        return {"score_per_point": self.score_per_point, "nvtl": self.nvtl,
                "mean_likelihood": self.mean_likelihood,
                "mean_likelihood_trilinear": self.mean_likelihood_trilinear,
                "fraction_above": {_fmt_threshold(t): v for t, v in self.fraction_above.items()},
                "cells": self.cells, "n_points": self.n_points, "cell_size": self.cell_size,
                "outlier_ratio": self.outlier_ratio}


def _fmt_threshold(t: float) -> str:
    return repr(float(t))


def ndt_score(reference: NDTGrid | Any, points: Any, cell_size: float | None = None,
              outlier_ratio: float = 0.55, min_points: int = 6, eig_floor: float = 0.01,
              thresholds: Sequence[float] = DEFAULT_THRESHOLDS) -> NDTScore:
    """Score ``points`` ([N, 3]) against a reference grid or reference points.

    ``reference`` is an :class:`NDTGrid` (then ``cell_size`` must be None or equal to its
    cell size) or an [M, 3] array from which a grid is built with ``cell_size``,
    ``min_points`` and ``eig_floor``. ``thresholds`` are likelihood levels in (0, 1] for
    ``fraction_above`` (on the trilinear likelihood). Non-finite points are ignored by
    the scores; the per-point arrays keep the input's rows (NaN for those points), so
    they can be written back into an image as likelihood maps.
    """
    if isinstance(reference, NDTGrid):
        grid = reference
        if cell_size is not None and not math.isclose(cell_size, grid.cell_size):
            raise TofhilError(f"is {cell_size} but the grid was built with {grid.cell_size}",
                              field="cell_size", expected="None or the grid's cell size")
    else:
        if cell_size is None:
            raise TofhilError("is required when the reference is a point array", field="cell_size",
                              expected="a positive length in metres")
        grid = NDTGrid.from_points(reference, cell_size, min_points=min_points, eig_floor=eig_floor)
    raw = np.asarray(points, dtype=np.float64)
    if raw.ndim != 2 or raw.shape[1] != 3:
        raise TofhilError(f"has shape {raw.shape}", field="points", expected="an N x 3 array of points")
    finite = np.all(np.isfinite(raw), axis=1)
    p = raw[finite]
    d1, d2 = gauss_params(grid.cell_size, outlier_ratio)
    n = p.shape[0]
    lik, tri, total, best, has = _point_terms(grid, p, outlier_ratio)
    n_has = int(has.sum())
    frac = {float(t): (float(np.mean(tri > t)) if n else 0.0) for t in thresholds}

    def aligned(x: np.ndarray) -> np.ndarray:
        # Per-point arrays follow the input rows (for likelihood maps); NaN for non-finite points.
        if n == raw.shape[0]:
            return x
        full = np.full(raw.shape[0], np.nan)
        full[finite] = x
        return full

    return NDTScore(score_per_point=float(total.sum() / n) if n else 0.0,
                    nvtl=float(best[has].sum() / n_has) if n_has else 0.0,
                    mean_likelihood=float(lik.mean()) if n else 0.0,
                    mean_likelihood_trilinear=float(tri.mean()) if n else 0.0,
                    fraction_above=frac, cells=grid.cells, n_points=n, cell_size=grid.cell_size,
                    outlier_ratio=float(outlier_ratio), d1=d1, d2=d2, likelihood=aligned(lik),
                    likelihood_trilinear=aligned(tri), point_score=aligned(total),
                    nearest_score=aligned(best))


def multi_resolution(reference: Any, points: Any, cell_sizes: Iterable[float] = (0.05, 0.1, 0.2, 0.4),
                     **kwargs: Any) -> dict[float, NDTScore]:
    """:func:`ndt_score` at several cell sizes (coarse cells forgive misalignment, fine
    cells resolve shape); keys are the cell sizes."""
    ref = _as_points(reference, "reference")
    return {float(r): ndt_score(ref, points, cell_size=float(r), **kwargs) for r in cell_sizes}


@dataclass
class D2DScore:
    """Distribution-to-distribution score of grid B against grid A (Stoyanov et al. 2012)."""

    score: float            # sum over (a, b) pairs of -d1 exp(-d2/2 mu^T (Ca + Cb)^-1 mu)
    score_per_cell: float   # score / number of cells of B
    mean_similarity: float  # mean over B cells of max over pairs of exp(-mu^T (Ca+Cb)^-1 mu / 2)
    pairs: int              # number of (a, b) pairs within the radius
    cells_b: int

    def to_dict(self) -> dict[str, Any]:
        return {"score": self.score, "score_per_cell": self.score_per_cell,
                "mean_similarity": self.mean_similarity, "pairs": self.pairs, "cells_b": self.cells_b}


def d2d_score(grid_a: NDTGrid, grid_b: NDTGrid, outlier_ratio: float = 0.55) -> D2DScore:
    """D2D NDT score of ``grid_b`` against ``grid_a`` at the identity transform.

    Each B cell is paired with every A cell whose mean lies within A's cell size of its
    mean (the neighbourhood PCL uses for points); a pair adds
    ``-d1 * exp(-d2/2 * mu^T (C_a + C_b)^-1 mu)`` with ``mu = mean_b - mean_a``
    (Stoyanov et al., "Fast and accurate scan registration through minimization of the
    distance between compact 3D NDT representations", IJRR 2012), ``d1, d2`` from
    A's cell size and the outlier ratio.
    """
    d1, d2 = gauss_params(grid_a.cell_size, outlier_ratio)
    mb = grid_b.means
    nbrs = _Neighbours(grid_a, grid_a.cell_of(mb))
    total = 0.0
    pairs = 0
    best = np.zeros(grid_b.cells)
    r2 = grid_a.cell_size ** 2
    for off in _OFFSETS27:
        ca = nbrs.at(off)
        sel = np.flatnonzero(ca >= 0)
        if sel.size == 0:
            continue
        mu = mb[sel] - grid_a.means[ca[sel]]
        near = np.einsum("ni,ni->n", mu, mu) <= r2
        sel, mu = sel[near], mu[near]
        c = grid_a.covs[ca[sel]] + grid_b.covs[sel]
        m = np.einsum("ni,ni->n", mu, np.linalg.solve(c, mu[:, :, None])[:, :, 0])
        total += float(np.sum(-d1 * np.exp(-0.5 * d2 * m)))
        best[sel] = np.maximum(best[sel], np.exp(-0.5 * m))
        pairs += int(sel.size)
    nb = grid_b.cells
    return D2DScore(score=total, score_per_cell=total / nb if nb else 0.0,
                    mean_similarity=float(best.mean()) if nb else 0.0, pairs=pairs, cells_b=nb)
